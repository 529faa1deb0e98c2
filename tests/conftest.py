"""Shared fixtures: tiny scenes and models that render in milliseconds."""
import mi_nerfpp  # noqa: F401  (libLLVM, variant, plugin registration)
import mitsuba as mi
import pytest

from mi_nerfpp.model import NeRFPPModel

TINY_GRID = dict(kind='grid', resolutions=[4, 8], channels=3, hidden=8, dir_octaves=1)


def tiny_model(seed=0, background=True):
    return NeRFPPModel.create(seed=seed, background=background,
                              fg_config=dict(TINY_GRID, domain='ball'),
                              bg_config=dict(TINY_GRID, domain='inverted_sphere'))


def scene_dict(width=8, height=6, origin=(0.1, 0.2, 0.6), target=(0, 0, 0), spp=1, near_clip=0.01,
               jitter=True, **integrator):
    """A nerfpp scene; ``jitter=False`` puts every ray through its pixel centre."""
    return {
        'type': 'scene',
        'integrator': dict({'type': 'nerfpp', 'fg_samples': 8, 'bg_samples': 8,
                            'fine_samples': 8}, **integrator),
        'sensor': {
            'type': 'perspective', 'fov': 60, 'near_clip': near_clip,
            'to_world': mi.ScalarTransform4f().look_at(origin=origin, target=target, up=[0, 1, 0]),
            'sampler': {'type': 'stratified', 'sample_count': spp, 'jitter': jitter},
            'film': {'type': 'hdrfilm', 'width': width, 'height': height,
                     'rfilter': {'type': 'box'}, 'pixel_format': 'rgba'},
        },
    }


@pytest.fixture
def tiny_scene():
    """A small scene whose integrator holds a tiny seeded model."""
    scene = mi.load_dict(scene_dict())
    scene.integrator().model = tiny_model()
    return scene
