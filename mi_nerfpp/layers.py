"""The layers of a render: the one definition of each layer's name, channels, content and precision.

A render is the film's beauty channels ``R G B A`` followed by the ``nerfpp`` integrator's AOVs
(:data:`AOVS`, in the order :meth:`NeRFPPIntegrator.aov_names
<mi_nerfpp.integrator.NeRFPPIntegrator.aov_names>` reports and ``mi.render`` returns them).
Channel names follow the ``layer.channel`` convention that Nuke, Blender and Natron read as
layers. Everything that names, orders, documents or stores the channels - the integrator's
AOV list, :func:`mi_nerfpp.views.render_layers`, the EXR writer's precision rule and the layer
tables of :mod:`mi_nerfpp.exr` and of the integrator's docstring - is derived from
:data:`LAYER_TABLE`: a layer is changed here, in one edit (and computed in the integrator).

This module must not import drjit or mitsuba.
"""
from __future__ import annotations

import textwrap
from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class Layer:
    """One layer of a render.

    ``name``: the EXR layer ('' for the beauty, whose channels have no prefix);
    ``suffixes``: its channels' last parts, in order (``('R', 'G', 'B', 'A')``);
    ``content``: what it holds (the documentation of the layer, reStructuredText);
    ``float32``: the suffixes of the channels that hold distances: they stay float32 in a
    half-float EXR, because half precision cannot hold scene-scale distances accurately.
    """
    name: str
    suffixes: tuple[str, ...]
    content: str
    float32: tuple[str, ...] = ()

    @property
    def channels(self) -> tuple[str, ...]:
        """The channel names, ``layer.suffix`` (the suffix alone for the beauty)."""
        return tuple(f'{self.name}.{s}' if self.name else s for s in self.suffixes)

    @property
    def full_precision(self) -> tuple[str, ...]:
        """The channels that are always written as float32."""
        return tuple(c for c, s in zip(self.channels, self.suffixes) if s in self.float32)


LAYER_TABLE = (
    Layer('', ('R', 'G', 'B', 'A'),
          'the full image, ``R G B = fg + (1 - fg.A)·bg + obj + shadow`` in linear light; '
          '``A`` is 1 where the background volume is rendered (it is opaque), else the '
          'foreground over the shapes\' coverage, ``fg.A + (1 - fg.A)·obj.A``'),
    Layer('fg', ('R', 'G', 'B', 'A'),
          'premultiplied foreground radiance and the foreground opacity ``1 - λ`` (the one '
          'foreground alpha, in [0, 1]); in front of a scene\'s shape, the volume up to it'),
    Layer('bg', ('R', 'G', 'B'),
          'background radiance as seen unoccluded (0 behind opaque foreground unless the '
          'integrator\'s ``occluded_background`` is on)'),
    Layer('depth', ('Z',),
          'camera-space z (distance along the view axis, world units, positive in front) of '
          'the point where the accumulated opacity of the composite reaches 0.5 (a scene\'s '
          'shape is opaque)', float32=('Z',)),
    Layer('distance', ('Y',),
          'expected distance along the ray (world units), blended over both volumes (the '
          'background at infinity capped at 1000 unit-sphere radii, :mod:`mi_nerfpp.render`): '
          'not a surface, not for Z-based tools', float32=('Y',)),
    Layer('obj', ('R', 'G', 'B', 'A', 'Z'),
          'radiance that the scene\'s shapes add as it reaches the camera (through the volumes '
          'in front of them), the fraction of the pixel\'s samples whose camera ray meets a '
          'shape, and that shape\'s camera-space z (0 off them); all 0 in a scene without '
          'shapes', float32=('Z',)),
    Layer('shadow', ('R', 'G', 'B'),
          'the change that the shadow catchers make (negative in shadows); 0 in a scene '
          'without shapes'),
)

LAYERS_BY_NAME = {layer.name: layer for layer in LAYER_TABLE}
# The film's beauty channels, the integrator's AOVs after them, and all channels of a render.
BEAUTY = LAYERS_BY_NAME[''].channels
AOVS = tuple(channel for layer in LAYER_TABLE if layer.name for channel in layer.channels)
LAYERS = BEAUTY + AOVS
# Channels a half-float EXR keeps as float32.
FULL_PRECISION_CHANNELS = frozenset(c for layer in LAYER_TABLE for c in layer.full_precision)


def layer_channels(**values) -> dict:
    """``{channel: value}`` from per-layer values in channel order, e.g.
    ``layer_channels(fg=(r, g, b, a), depth=(z,))`` -> ``{'fg.R': r, ..., 'depth.Z': z}``.

    Raises:
        ValueError: an unknown layer, or a number of values other than its channels'.
    """
    out = {}
    for name, layer_values in values.items():
        layer = LAYERS_BY_NAME.get(name)
        if layer is None or not name:
            raise ValueError(f"unknown layer '{name}': the layers are "
                             f"{', '.join(l.name for l in LAYER_TABLE if l.name)}")
        layer_values = tuple(layer_values)
        if len(layer_values) != len(layer.channels):
            raise ValueError(f"layer '{name}' has {len(layer.channels)} channels "
                             f"({' '.join(layer.channels)}), got {len(layer_values)} values")
        out.update(zip(layer.channels, layer_values))
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
