"""The scene normalization: the one map between the world frame and the model frame.

NeRF++ fits its volumes in a *model* frame where every camera lies inside the unit sphere:

    x_model = (x_world - center) · scale

:class:`Normalization` holds ``(center, scale)`` and converts points, distances, cameras and
rays both ways. The data layer computes it from the cameras (:meth:`Normalization.for_cameras`,
NeRF++'s rule: mean camera centre to the origin, farthest camera at :data:`NERFPP_CAMERA_RADIUS`),
training may shrink it further (the NeRF baseline, :meth:`Normalization.with_camera_radius`),
the checkpoint stores it, the integrator maps sensor rays and depth with it, and evaluation and
synthetic captures map cameras and the foreground sphere back to the world with it.

The near-clip distances of the sensors mi-nerfpp builds are named here too: Mitsuba's
perspective sensor starts its rays on the near plane, not at the camera centre.

This module must not import drjit or mitsuba at import time.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

# NeRF++ places the farthest camera at this radius (the 1.1 margin of its normalize_cam_dict.py).
NERFPP_CAMERA_RADIUS = 1.0 / 1.1
# The NeRF baseline (paper §5): one bounded volume, cameras scaled into this radius.
NERF_CAMERA_RADIUS = 1.0 / 8.0

# Near clip of the sensors that render dataset views (evaluation, previews, videos), in model
# units: negligible, so the rays start at the camera centre as in training.
VIEW_NEAR_CLIP = 1e-4
# Near clip of the sensor in a written ``render.xml``, in model units.
SCENE_NEAR_CLIP = 1e-3
# Mitsuba's own default near clip (world units), set explicitly where depth is corrected by it.
MITSUBA_NEAR_CLIP = 0.01


@dataclass(frozen=True)
class Normalization:
    """``x_model = (x_world - center) · scale``; the identity is ``Normalization()``."""

    center: tuple = (0.0, 0.0, 0.0)
    scale: float = 1.0

    def __post_init__(self):
        center = tuple(float(v) for v in np.asarray(self.center, dtype=np.float64).reshape(3))
        object.__setattr__(self, 'center', center)
        object.__setattr__(self, 'scale', float(self.scale))
        if not self.scale > 0:
            raise ValueError(f'normalization scale must be positive, got {self.scale}')

    # ------------------------------------------------------------------ construction
    @classmethod
    def for_cameras(cls, cameras, always: bool = False) -> Normalization:
        """NeRF++'s normalization of a capture, or the identity when every camera centre
        already lies strictly inside the unit sphere (unless ``always``).

        Otherwise the mean camera centre goes to the origin and the farthest camera to radius
        :data:`NERFPP_CAMERA_RADIUS`.

        Raises:
            ValueError: no cameras, or all camera centres coincide.
        """
        if not cameras:
            raise ValueError('normalization: no cameras given')
        centers = np.stack([cam.center for cam in cameras])
        if not always and np.all(np.linalg.norm(centers, axis=1) < 1.0):
            return cls()
        center = centers.mean(axis=0)
        radius = np.linalg.norm(centers - center, axis=1).max()
        if not radius > 0:
            raise ValueError(f'normalization: all {len(cameras)} camera centres coincide, so '
                             f'there is no scale to normalize; add cameras from other positions')
        return cls(center, NERFPP_CAMERA_RADIUS / radius)

    def with_camera_radius(self, radius: float) -> Normalization:
        """The same normalization shrunk about the model origin so that cameras at
        :data:`NERFPP_CAMERA_RADIUS` land at ``radius`` (the NeRF baseline's frame)."""
        return Normalization(self.center, self.scale * radius / NERFPP_CAMERA_RADIUS)

    @classmethod
    def from_config(cls, config: dict) -> Normalization:
        """Read ``{"normalization": {"center", "scale"}}``, or the older top-level
        ``center`` / ``scale`` keys of checkpoints written before this class existed."""
        stored = config.get('normalization', config)
        return cls(stored['center'], stored['scale'])

    def to_config(self) -> dict:
        return {'center': list(self.center), 'scale': self.scale}

    # ------------------------------------------------------------------ points and distances
    @property
    def center_array(self) -> np.ndarray:
        return np.array(self.center, dtype=np.float64)

    def to_model_point(self, x) -> np.ndarray:
        return (np.asarray(x, dtype=np.float64) - self.center_array) * self.scale

    def to_world_point(self, x) -> np.ndarray:
        return np.asarray(x, dtype=np.float64) / self.scale + self.center_array

    def to_model_distance(self, t):
        return t * self.scale

    def to_world_distance(self, t):
        return t / self.scale

    # ------------------------------------------------------------------ cameras
    def to_model_camera(self, camera):
        """The camera moved into the model frame (rotation and intrinsics unchanged)."""
        return self._move(camera, self.to_model_point)

    def to_world_camera(self, camera):
        """A model-frame camera placed back in the world frame."""
        return self._move(camera, self.to_world_point)

    @staticmethod
    def _move(camera, move):
        c2w = np.array(camera.c2w, dtype=np.float64)
        c2w[:3, 3] = move(c2w[:3, 3])
        return dataclasses.replace(camera, c2w=c2w)

    # ------------------------------------------------------------------ rays (Dr.Jit)
    def to_model_rays(self, o, d):
        """World-space rays -> model frame; directions are only renormalized."""
        return ((mi.Point3f(o) - mi.Point3f(*self.center)) * self.scale,
                dr.normalize(mi.Vector3f(d)))


def reframe_cameras(cameras, source: Normalization, target: Normalization):
    """Cameras of the model frame of ``source`` expressed in the model frame of ``target``."""
    if source == target:
        return list(cameras)
    return [target.to_model_camera(source.to_world_camera(cam)) for cam in cameras]
