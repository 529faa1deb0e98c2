"""Shared fixtures (the helpers they are built on are in tests/helpers.py)."""
import mi_nerfpp  # noqa: F401  (libLLVM, variant, plugin registration)
import mitsuba as mi
import pytest

from tests.helpers import TINY_RUN, make_capture, scene_dict, tiny_model


@pytest.fixture
def tiny_scene():
    """A small scene whose integrator holds a tiny seeded model."""
    scene = mi.load_dict(scene_dict())
    scene.integrator().set_model(tiny_model())
    return scene


@pytest.fixture(scope='session')
def capture(tmp_path_factory):
    """A small unbounded capture in the NeRF++ layout (see :func:`tests.helpers.make_capture`)."""
    return make_capture(str(tmp_path_factory.mktemp('capture') / 'data'))


@pytest.fixture(scope='session')
def tiny_run(capture, tmp_path_factory):
    """A run folder of ``optimize`` on the capture, trained for a few steps."""
    from mi_nerfpp.commands.cli import main
    out = str(tmp_path_factory.mktemp('run') / 'tiny')
    assert main(['optimize', capture, '--out', out] + TINY_RUN) == 0
    return out
