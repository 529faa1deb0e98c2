"""A batch of rays: the one value that carries each ray's data from the camera or the training
photos to the samples (data flows rays -> samples -> fields -> quadrature -> image)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


@dataclass
class Rays:
    """Rays ``o + t·d`` (``|d| = 1``), one entry per ray in every array, and what each ray
    carries besides; any of these may be None (not given):

    * ``far``: the distance at which a surface ends the ray (Mitsuba's ``Ray3f.maxt``; ``inf``:
      none). None: no ray is ended.
    * ``footprint``: the ray's pixel width per unit distance
      (:func:`~mi_nerfpp.core.geometry.pixel_footprint`), for fields that filter their lookups
      by it (:mod:`.render`, "Pixel footprints"). None: looked up as points.
    * ``seed``: jitters the placement of the ray's samples. None: strata midpoints.
    * ``path_seed``: the ray's random paths through a scene's shapes (:mod:`.objects`).
    * ``image``: the training photo the ray comes from (its appearance and pose correction).

    A Dr.Jit PyTree (a dataclass): ``dr.eval(rays)`` evaluates every array it holds."""
    o: mi.Point3f
    d: mi.Vector3f
    far: mi.Float | None = None
    footprint: mi.Float | None = None
    seed: mi.UInt32 | None = None
    path_seed: mi.UInt32 | None = None
    image: mi.UInt32 | None = None

    @property
    def width(self) -> int:
        """The number of rays."""
        return dr.width(self.o)

    def gather(self, index) -> Rays:
        """The rays ``index`` (UInt32), with everything they carry (None stays None)."""
        return Rays(**{f.name: _gathered(getattr(self, f.name), index)
                       for f in dataclasses.fields(self)})

    def replace(self, **changes) -> Rays:
        """A copy with some fields replaced (``rays.replace(far=None)``)."""
        return dataclasses.replace(self, **changes)


def _gathered(value, index):
    return None if value is None else dr.gather(type(value), value, index)
