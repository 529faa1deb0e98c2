"""The ``nerfpp`` integrator's XML parameters: a reader that checks each one's type and range as
the integrator reads it, and the limits that keep a render within memory and Dr.Jit's arrays,
checked before Dr.Jit sees them.

Every size that a parameter, the film or the sensor sets is refused here with one line naming
it and the largest value that fits (issue 37): sample counts per ray, path depth and catcher
directions (arrays of ``chunk_rays`` times them per chunk), the film (pixels times samples per
pixel) and the sensor (a finite ``to_world`` within :data:`MAX_CAMERA_RADIUS` of the model).
The rule for a chunk's arrays lives in :mod:`mi_nerfpp.core.budget`, which the training options
check too.
"""
from __future__ import annotations

import math

import numpy as np

# Largest number of camera rays (film pixels x samples per pixel) one render may trace: memory
# grows by roughly 100 bytes per ray, so this bounds a render to about 2 GB. Raise it with the
# ``max_samples`` parameter on a machine with more memory.
MAX_FILM_SAMPLES = 1 << 24
# Cameras farther than this from the model's centre, in unit-sphere radii, are refused: float32
# ray origins there no longer resolve the reconstruction (1e4 radii leave steps of ~1e-3).
MAX_CAMERA_RADIUS = 1e4

_XML_TAGS = {int: 'integer', float: 'float', bool: 'boolean', str: 'string'}


class ParameterReader:
    """Reads the integrator's XML parameters once, each with its type and range checked."""

    def __init__(self, props):
        self.props, self.known = props, set()

    def __call__(self, name, kind, default, minimum=None, choices=None):
        self.known.add(name)
        if name not in self.props:
            return default
        value = self.props.get(name)
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
            raise ValueError(
                f"nerfpp: parameter '{name}' must be given as <{_XML_TAGS[kind]} "
                f"name=\"{name}\" value=\"...\"/>, got {type(value).__name__} {value!r}")
        if kind in (int, float) and not value == value:
            raise ValueError(f"nerfpp: parameter '{name}' is NaN")
        if kind is float and math.isinf(value):
            raise ValueError(f"nerfpp: parameter '{name}' is {value}: give a finite value")
        if minimum is not None and value < minimum:
            raise ValueError(f"nerfpp: parameter '{name}' must be >= {minimum}, got {value}")
        if choices is not None and value not in choices:
            raise ValueError(f"nerfpp: parameter '{name}' must be one of "
                             f"{', '.join(choices)}, got {value!r}")
        return value

    def reject_unknown(self):
        unknown = sorted(set(self.props.unqueried()) - self.known)
        if unknown:
            raise ValueError(f"nerfpp: unknown parameter(s) {', '.join(unknown)}; the nerfpp "
                             f"integrator takes {', '.join(sorted(self.known))}")


def check_film(size, count, max_samples):
    """Refuse an empty film, a sample count of 0, and films beyond ``max_samples`` rays."""
    if count < 1:
        raise ValueError('nerfpp: the sampler has sample_count 0: give it at least 1 '
                         '(<integer name="sample_count" value="1"/>) or pass spp >= 1')
    width, height = int(size[0]), int(size[1])
    if width < 1 or height < 1:
        raise ValueError(f'nerfpp: the film is {width}x{height} pixels: give it a width and '
                         f'a height of at least 1 (<integer name="width" value="..."/>)')
    rays = width * height * int(count)
    if rays > max_samples:
        raise ValueError(
            f'nerfpp: a {width}x{height} film at {count} samples per pixel traces '
            f'{rays} rays, more than max_samples={max_samples} (about 100 bytes each): '
            f'render a smaller film or crop (the largest at {count} spp is '
            f'{max_samples // count} pixels) or fewer samples per pixel (spp: at most '
            f'{max_samples // (width * height)} at {width}x{height}), or raise the '
            f'integrator\'s max_samples')


def check_sensor(to_world, normalization):
    """Refuse a sensor transform with NaN or infinite entries, a degenerate one, or a camera
    farther than :data:`MAX_CAMERA_RADIUS` unit-sphere radii from the model (world-frame
    ``to_world``, 4x4; ``normalization``: the model's
    :class:`~mi_nerfpp.core.frame.Normalization`)."""
    m = np.asarray(to_world, dtype=np.float64).reshape(4, 4)
    centre, scale = normalization.center_array, float(normalization.scale)
    # Distance first: a lookat that far away also fills its rotation with NaN (float32
    # overflow), and the distance is what to fix.
    if np.all(np.isfinite(m[:3, 3])):
        radius = float(np.linalg.norm((m[:3, 3] - centre) * scale))
        if not radius <= MAX_CAMERA_RADIUS:
            largest = MAX_CAMERA_RADIUS / scale
            raise ValueError(
                f"nerfpp: the sensor is at {np.linalg.norm(m[:3, 3]):.3g} world units from the "
                f"origin, {radius:.3g} unit-sphere radii from the model's centre; the largest "
                f"distance that renders is {MAX_CAMERA_RADIUS:g} radii ({largest:.6g} world "
                f"units from the centre {centre.tolist()}): move the sensor's to_world closer")
    if not np.all(np.isfinite(m)):
        raise ValueError("nerfpp: the sensor's to_world has NaN or infinite entries: give a "
                         "finite <transform name=\"to_world\">")
    if abs(np.linalg.det(m[:3, :3])) < 1e-30:
        raise ValueError("nerfpp: the sensor's to_world is degenerate (a zero scale or a "
                         "lookat with origin = target or up parallel to the view): fix its "
                         "<transform name=\"to_world\">")
