"""The Mitsuba integrator ``nerfpp`` (:class:`NeRFPPIntegrator`), one module per concern:

* :mod:`.parameters` - the XML parameters, read once, and the limits checked before Dr.Jit
  sees them;
* :mod:`.loading` - the model: a checkpoint next to the scene file, its appearance transforms;
* :mod:`.volumes` - the volumes' layers of world-space rays, chunked;
* :mod:`.shapes` - the scene's shapes: paths through them, shadow catchers;
* :mod:`.nerfpp` - the class that puts them together, Mitsuba's entry points.
"""
from mi_nerfpp.integrator.nerfpp import NeRFPPIntegrator, camera_axis, register
from mi_nerfpp.integrator.parameters import MAX_FILM_SAMPLES

__all__ = ['MAX_FILM_SAMPLES', 'NeRFPPIntegrator', 'camera_axis', 'register']
