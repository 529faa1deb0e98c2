"""The Mitsuba integrator ``nerfpp`` (:class:`NeRFPPIntegrator`, :mod:`.nerfpp`) and its parts:
its XML parameters' checks (:mod:`.parameters`), the model it loads (:mod:`.loading`), and the
renderers it holds for the volumes (:mod:`.volumes`) and the scene's shapes (:mod:`.shapes`)."""
from mi_nerfpp.integrator.nerfpp import NeRFPPIntegrator, camera_axis, register
from mi_nerfpp.integrator.parameters import MAX_FILM_SAMPLES

__all__ = ['MAX_FILM_SAMPLES', 'NeRFPPIntegrator', 'camera_axis', 'register']
