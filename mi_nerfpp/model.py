"""A NeRF++ scene representation: foreground and background fields plus the scene normalization.

The model lives in a *normalized* frame where all cameras are inside the unit
sphere: ``x_model = (x_world - center) · scale``. Rays from a Mitsuba sensor in
world space are mapped into it with :meth:`NeRFPPModel.world_to_model`.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .fields import make_field

FIELD_KINDS = ('grid', 'nerf', 'vanilla')


def default_field_config(kind, domain):
    if kind not in FIELD_KINDS:
        raise ValueError(f"unknown field kind '{kind}' (expected one of {', '.join(FIELD_KINDS)})")
    return {'kind': kind, 'domain': domain}


class NeRFPPModel:
    """Foreground field (unit ball), optional background field (inverted sphere), normalization.

    ``bg=None`` is a bounded NeRF: one volume, nothing behind it.
    ``color_space`` says what the radiance values mean: 'srgb' when the model
    was fitted to sRGB-encoded photos (PNG/JPG), 'linear' for EXR inputs.
    """

    def __init__(self, fg, bg=None, center=(0.0, 0.0, 0.0), scale=1.0, color_space='srgb'):
        self.fg, self.bg = fg, bg
        self.center = np.asarray(center, dtype=np.float64).reshape(3)
        self.scale = float(scale)
        if not self.scale > 0:
            raise ValueError(f'normalization scale must be positive, got {scale}')
        self.color_space = color_space

    @classmethod
    def create(cls, field='grid', background=True, seed=0, fg_config=None, bg_config=None, **kwargs):
        """A freshly initialized (seeded random) model."""
        fg = make_field(fg_config or default_field_config(field, 'ball'), seed=seed)
        bg = None
        if background:
            bg = make_field(bg_config or default_field_config(field, 'inverted_sphere'), seed=seed + 1)
        return cls(fg, bg, **kwargs)

    @property
    def config(self):
        return {'fg': self.fg.config, 'bg': self.bg.config if self.bg else None,
                'center': self.center.tolist(), 'scale': self.scale, 'color_space': self.color_space}

    def parameters(self):
        """All learnable arrays, named ``fg.<name>`` / ``bg.<name>`` (live references)."""
        out = {f'fg.{k}': v for k, v in self.fg.params.items()}
        if self.bg is not None:
            out.update({f'bg.{k}': v for k, v in self.bg.params.items()})
        return out

    def n_parameters(self):
        """Number of learnable scalars."""
        return sum(dr.width(v.array) for v in self.parameters().values())

    def set_parameters(self, values):
        """Replace parameters by their ``fg.``/``bg.`` names."""
        for volume, field in (('fg', self.fg), ('bg', self.bg)):
            sub = {k[len(volume) + 1:]: v for k, v in values.items() if k.startswith(volume + '.')}
            if sub and field is None:
                raise KeyError(f'model has no {volume} field for parameters {sorted(sub)}')
            if sub:
                field.set_parameters(sub)
        unknown = [k for k in values if not k.startswith(('fg.', 'bg.'))]
        if unknown:
            raise KeyError(f'unknown parameter names {unknown}')

    def world_to_model(self, o, d):
        """Map world-space rays into the normalized frame (directions are unchanged)."""
        c = mi.Point3f(*[float(x) for x in self.center])
        return (mi.Point3f(o) - c) * self.scale, dr.normalize(mi.Vector3f(d))
