"""The layers of a render: the one definition of each layer's name, channels, content and precision,
and of how the layers are made from the samples of a pixel so that they add up at any spp.

A render has two sets of channels:

* the **layers** (:data:`LAYERS`, :data:`LAYER_TABLE`) that the EXR holds and a compositor reads;
* the **sample channels** (:data:`AOVS`): what the ``nerfpp`` integrator returns per camera
  sample as Mitsuba AOVs, in the order :meth:`NeRFPPIntegrator.aov_names
  <mi_nerfpp.integrator.NeRFPPIntegrator.aov_names>` reports and ``mi.render`` returns them
  after the film's ``R G B [A]``. The film averages every channel over a pixel's samples with
  the same (reconstruction filter) weights.

**Why two sets.** The layers must add up after that averaging: ``beauty = fg + (1 - fg.A)·bg
+ obj + shadow`` per pixel, whatever the samples per pixel. Averages of sums are sums of
averages, but an average of products is not a product of averages: ``mean(λ·bg) ≠ mean(λ)
·mean(bg)`` where the foreground's transmittance ``λ = 1 - fg.A`` varies within a pixel (soft
edges, objects). So a sample carries the background *as seen through the foreground*, ``(λ +
ε)·bg``, and the layer is the ratio of averages :func:`develop` takes,

    ``bg = mean((λ + ε)·bg) / (mean(λ) + ε)``,  ``ε =`` :data:`BACKGROUND_WEIGHT_FLOOR`,

so that ``(1 - fg.A)·bg = mean(λ·bg)`` up to ``ε·max(bg)``: the identity holds to about 1e-6,
and where the foreground is opaque in every sample (``λ = 0``) ``bg`` is the plain average of
the background (0 unless the integrator's ``occluded_background`` rendered it). Likewise the
objects' depth is ``mean(hit·z) / mean(hit)`` (the depth of the shapes where they cover the
pixel, not a blend with 0) and the beauty alpha is the average of each sample's own alpha.
The other layers are plain averages.

Channel names follow the ``layer.channel`` convention that Nuke, Blender and Natron read as
layers; no layer has more than four channels. Everything that names, orders, documents or
stores the channels - the integrator's AOV list, :func:`develop`, the EXR writer's precision
rule and the layer tables of :mod:`mi_nerfpp.files.exr` and of the integrator's docstring - is
derived from :data:`LAYER_TABLE`: a layer is changed here, in one edit (and computed in the
integrator).

This module must not import drjit or mitsuba.
"""
from __future__ import annotations

import textwrap
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

# ε of the background's per-sample weight ``λ + ε`` (module docs): bounds the error of
# ``beauty = fg + (1 - fg.A)·bg`` by ε·max(bg), and gives fully occluded pixels the plain
# average of their background samples.
BACKGROUND_WEIGHT_FLOOR = 1e-6


@dataclass(frozen=True)
class Layer:
    """One layer of a render.

    ``name``: the EXR layer ('' for the beauty, whose channels have no prefix);
    ``suffixes``: its channels' last parts, in order (``('R', 'G', 'B', 'A')``);
    ``content``: what it holds (the documentation of the layer, reStructuredText);
    ``float32``: the suffixes of the channels that hold distances: they stay float32 in a
    half-float EXR, because half precision cannot hold scene-scale distances accurately;
    ``weight``: '' for a layer that is the plain average of its samples; else the channel
    whose average it is divided by (its samples are premultiplied by that channel's sample
    value: module docs), and its sample channels are named ``<name>_w.<suffix>``.
    """
    name: str
    suffixes: tuple[str, ...]
    content: str
    float32: tuple[str, ...] = ()
    weight: str = ''

    @property
    def channels(self) -> tuple[str, ...]:
        """The channel names, ``layer.suffix`` (the suffix alone for the beauty)."""
        return tuple(f'{self.name}.{s}' if self.name else s for s in self.suffixes)

    @property
    def sample_channels(self) -> tuple[str, ...]:
        """The names of the integrator's AOVs this layer is made from."""
        if not self.weight:
            return self.channels
        return tuple(f'{self.name}_w.{s}' for s in self.suffixes)

    @property
    def full_precision(self) -> tuple[str, ...]:
        """The channels that are always written as float32."""
        return tuple(c for c, s in zip(self.channels, self.suffixes) if s in self.float32)


LAYER_TABLE = (
    Layer('', ('R', 'G', 'B', 'A'),
          'the full image, ``R G B = fg + (1 - fg.A)·bg + obj + shadow`` in linear light, per '
          'pixel at any number of samples per pixel; ``A``: the average of each sample\'s '
          'alpha, 1 where the background volume is rendered (it is opaque), else the '
          'foreground over the shapes (``1 - λ·(1 - hit)``)'),
    Layer('fg', ('R', 'G', 'B', 'A'),
          'premultiplied foreground radiance and the foreground opacity ``1 - λ`` (the one '
          'foreground alpha, in [0, 1]); in front of a scene\'s shape, the volume up to it'),
    Layer('bg', ('R', 'G', 'B'),
          'background radiance as seen through the foreground, unpremultiplied: '
          '``mean((λ + ε)·bg) / (1 - fg.A + ε)`` over the pixel\'s samples (ε = 1e-6), so '
          'that ``fg + (1 - fg.A)·bg`` is exact; behind opaque foreground the plain average '
          '(0 unless the integrator\'s ``occluded_background`` is on)', weight='transmittance'),
    Layer('depth', ('Z',),
          'camera-space z (distance along the view axis, world units, positive in front) of '
          'the point where the accumulated opacity of the composite reaches 0.5 (a scene\'s '
          'shape is opaque)', float32=('Z',)),
    Layer('distance', ('Y',),
          'expected distance along the ray (world units), blended over both volumes (the '
          'background at infinity capped at 1000 unit-sphere radii, :mod:`mi_nerfpp.core.render`): '
          'not a surface, not for Z-based tools', float32=('Y',)),
    Layer('obj', ('R', 'G', 'B', 'A'),
          'radiance that the scene\'s shapes add as it reaches the camera (through the volumes '
          'in front of them), and the fraction of the pixel\'s samples whose camera ray meets '
          'a shape (coverage); all 0 in a scene without shapes'),
    Layer('obj_depth', ('Z',),
          'camera-space z of the scene\'s shapes where they cover the pixel, '
          '``mean(hit·z) / obj.A`` (0 where ``obj.A`` is 0)', float32=('Z',), weight='obj.A'),
    Layer('shadow', ('R', 'G', 'B'),
          'the change that the shadow catchers make (negative in shadows); 0 in a scene '
          'without shapes'),
)

LAYERS_BY_NAME = {layer.name: layer for layer in LAYER_TABLE}
# The film's beauty channels and all channels of a render (the EXR's).
BEAUTY = LAYERS_BY_NAME[''].channels
LAYERS = tuple(channel for layer in LAYER_TABLE for channel in layer.channels)
# The sample channel of the beauty alpha (the film's own A is 1 for every valid sample).
ALPHA_SAMPLE = 'alpha.A'
# The integrator's AOVs: the sample channels of every layer but the beauty, and its alpha.
AOVS = tuple(c for layer in LAYER_TABLE if layer.name for c in layer.sample_channels) \
    + (ALPHA_SAMPLE,)
# Channels a half-float EXR keeps as float32.
FULL_PRECISION_CHANNELS = frozenset(c for layer in LAYER_TABLE for c in layer.full_precision)


def layer_channels(**values) -> dict:
    """``{sample channel: value}`` from per-layer sample values in channel order, e.g.
    ``layer_channels(fg=(r, g, b, a), depth=(z,))`` -> ``{'fg.R': r, ..., 'depth.Z': z}``;
    a weighted layer's values are its premultiplied samples (``bg=(w·r, w·g, w·b)`` gives
    ``bg_w.R`` ...), and ``A=(a,)`` is the beauty's alpha of the sample.

    Raises:
        ValueError: an unknown layer, or a number of values other than its channels'.
    """
    out = {}
    for name, layer_values in values.items():
        layer_values = tuple(layer_values)
        if name == 'A':
            channels = (ALPHA_SAMPLE,)
        else:
            layer = LAYERS_BY_NAME.get(name)
            if layer is None or not name:
                raise ValueError(f"unknown layer '{name}': the layers are "
                                 f"{', '.join(l.name for l in LAYER_TABLE if l.name)}, A")
            channels = layer.sample_channels
        if len(layer_values) != len(channels):
            raise ValueError(f"layer '{name}' has {len(channels)} channels "
                             f"({' '.join(channels)}), got {len(layer_values)} values")
        out.update(zip(channels, layer_values))
    return out


def aov_list(channels: Mapping, missing) -> list:
    """The values of ``channels`` (``{AOV channel: value}``) in :data:`AOVS` order, as
    ``mi.render`` expects them; ``missing()`` gives the value of a channel not in the dict.

    Raises:
        ValueError: a name that is not an AOV channel.
    """
    unknown = set(channels) - set(AOVS)
    if unknown:
        raise ValueError(f"not AOV channels: {', '.join(sorted(unknown))}")
    return [channels[c] if c in channels else missing() for c in AOVS]


def develop(rgb: Mapping, samples: Mapping) -> dict:
    """The layers (:data:`LAYERS` order, H x W float32 each) of a pixel-averaged render: the
    film's ``R G B`` (``rgb``) and the averaged sample channels (``samples``, :data:`AOVS`).
    Ratios as in the module docs."""
    f32 = {name: np.asarray(v, dtype=np.float32) for name, v in samples.items()}
    out = {c: np.asarray(rgb[c], dtype=np.float32) for c in BEAUTY[:3]}
    out['A'] = f32[ALPHA_SAMPLE]
    for layer in LAYER_TABLE[1:]:
        if not layer.weight:
            out.update({c: f32[c] for c in layer.channels})
            continue
        if layer.weight == 'transmittance':
            # The same float32 1 - fg.A that a compositor computes from the file.
            denominator = (np.float32(1.0) - out['fg.A']) + np.float32(BACKGROUND_WEIGHT_FLOOR)
        else:
            denominator = out[layer.weight]
        for c, s in zip(layer.channels, layer.sample_channels):
            with np.errstate(divide='ignore', invalid='ignore'):
                out[c] = np.where(denominator > 0, f32[s] / denominator,
                                  np.float32(0.0)).astype(np.float32)
    return {name: out[name] for name in LAYERS}


def _content(layer: Layer) -> str:
    """The layer's content, with its precision rule."""
    if layer.full_precision == layer.channels:
        return layer.content + '; always float32'
    if layer.full_precision:
        return layer.content + f"; {', '.join(f'``{c}``' for c in layer.full_precision)} " \
                               f'always float32'
    return layer.content


def rst_table(indent: str = '') -> str:
    """:data:`LAYER_TABLE` as a reStructuredText simple table (layer, channels, content)."""
    widths = (12, 24, 56)
    rule = '  '.join('=' * w for w in widths)
    rows = [rule, '  '.join(h.ljust(w) for h, w in zip(('layer', 'channels', 'content'),
                                                       widths)).rstrip(), rule]
    for layer in LAYER_TABLE:
        cells = [[f'``{layer.name}``' if layer.name else '(beauty)'],
                 textwrap.wrap(f"``{' '.join(layer.channels)}``", widths[1],
                               break_on_hyphens=False),
                 textwrap.wrap(_content(layer), widths[2], break_on_hyphens=False)]
        for i in range(max(map(len, cells))):
            line = [c[i] if i < len(c) else '' for c in cells]
            rows.append('  '.join(t.ljust(w) for t, w in zip(line, widths)).rstrip())
    rows.append(rule)
    return '\n'.join(indent + r if r else r for r in rows)
