"""Limits checked before Dr.Jit sees them (issue 37, the integrator's part): XML parameters
that size arrays, the film and the sensor are refused with one line naming the parameter
and the largest value that fits, instead of Dr.Jit's internals or a segfault."""
import subprocess
import sys
import textwrap

import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.core.budget import MAX_CHUNK_ENTRIES
from mi_nerfpp.integrator.parameters import MAX_CAMERA_RADIUS
from tests.helpers import scene_dict, tiny_model


def refusal(make):
    """The message of the ValueError behind what ``make()`` raises (Mitsuba wraps errors of
    Python plugins in RuntimeErrors)."""
    with pytest.raises(Exception) as info:
        make()
    err = info.value
    while err is not None and not isinstance(err, ValueError):
        err = err.__cause__ or err.__context__
    # At load, Mitsuba's parser keeps only the text: "... failed to instantiate ... (<ours>)".
    message = str(err) if err is not None else str(info.value)
    assert 'nerfpp: ' in message, message
    message = message[message.index('nerfpp: '):]
    if err is None:
        message = message.rstrip(')')
    assert '\n' not in message
    return message


def test_sample_counts_beyond_a_chunk_are_refused_at_load():
    largest = MAX_CHUNK_ENTRIES // (1 << 15) - 8
    message = refusal(lambda: mi.load_dict(scene_dict(fg_samples=10 ** 9)))
    assert message.startswith("nerfpp: parameter 'fg_samples' is 1000000000")
    assert f'the largest fg_samples that fits (with fine_samples=8) is {largest}' in message
    message = refusal(lambda: mi.load_dict(scene_dict(fine_samples=10 ** 6)))
    assert message.startswith("nerfpp: parameter 'fine_samples' is 1000000")
    assert 'the largest fine_samples that fits' in message
    # Fewer rays per chunk make room: the limit follows chunk_rays.
    mi.load_dict(scene_dict(fg_samples=100000, chunk_rays=256))
    for name in ('max_depth', 'catcher_samples'):
        message = refusal(lambda: mi.load_dict(scene_dict(**{name: 10 ** 7})))
        assert f"parameter '{name}' is 10000000" in message
        assert f'the largest {name} that fits is {MAX_CHUNK_ENTRIES // (1 << 15)}' in message
    assert "parameter 'seed' is 4294967296; the largest seed is 4294967295" in refusal(
        lambda: mi.load_dict(scene_dict(seed=2 ** 32)))


def test_the_model_sample_counts_are_checked_before_rendering():
    """A model handed over with counts that do not fit is refused at render, not by Dr.Jit."""
    from mi_nerfpp.core.render import Sampling
    desc = scene_dict()
    for name in ('fg_samples', 'bg_samples', 'fine_samples'):
        del desc['integrator'][name]
    scene = mi.load_dict(desc)
    model = tiny_model()
    model.sampling = Sampling(10 ** 9, 8, 8)
    scene.integrator().set_model(model)
    assert "parameter 'fg_samples' is 1000000000" in refusal(lambda: mi.render(scene))


def _scene(**sensor):
    desc = scene_dict()
    desc['sensor'].update(sensor)
    scene = mi.load_dict(desc)
    scene.integrator().set_model(tiny_model())
    return scene


def test_an_empty_film_is_refused():
    desc = scene_dict()
    desc['sensor']['film']['width'] = 0
    scene = mi.load_dict(desc)
    scene.integrator().set_model(tiny_model())
    assert refusal(lambda: mi.render(scene)) == (
        'nerfpp: the film is 0x6 pixels: give it a width and a height of at least 1 '
        '(<integer name="width" value="..."/>)')


@pytest.mark.parametrize('distance', [1e20, 1e30])
@pytest.mark.parametrize('kind', ['translate', 'lookat'])
def test_a_sensor_far_from_the_model_is_refused(distance, kind):
    if kind == 'translate':
        to_world = mi.ScalarTransform4f().translate([distance, 0, 0]).rotate([0, 1, 0], -90)
    else:           # (Mitsuba's lookat overflows float32 there: NaN in the rotation)
        to_world = mi.ScalarTransform4f().look_at(origin=[distance, 0, 0], target=[0, 0, 0],
                                                  up=[0, 1, 0])
    scene = _scene(to_world=to_world)
    message = refusal(lambda: mi.render(scene))
    assert message.startswith(f'nerfpp: the sensor is at {distance:.3g} world units from the '
                              f'origin')
    assert f'the largest distance that renders is {MAX_CAMERA_RADIUS:g} radii' in message
    # Just inside the limit it renders.
    inside = _scene(to_world=mi.ScalarTransform4f().look_at(
        origin=[0.5 * MAX_CAMERA_RADIUS, 0, 0], target=[0, 0, 0], up=[0, 1, 0]))
    assert np.all(np.isfinite(np.array(mi.render(inside))))


def test_a_nan_in_the_sensor_transform_is_refused():
    m = np.eye(4)
    m[0, 3] = float('nan')
    scene = _scene(to_world=mi.ScalarTransform4f(m))
    assert refusal(lambda: mi.render(scene)).startswith(
        "nerfpp: the sensor's to_world has NaN or infinite entries")


def _render_scene_file(tmp_path, name, scene):
    """``python -m mi_nerfpp render`` of ``scene`` (XML text) written to ``name`` in
    ``tmp_path``: the finished process, the scene file and the output path."""
    xml = tmp_path / name
    xml.write_text(textwrap.dedent(scene))
    out = tmp_path / 'out.exr'
    r = subprocess.run([sys.executable, '-m', 'mi_nerfpp', 'render', str(xml), '-o', str(out)],
                       capture_output=True, text=True, timeout=300)
    return r, xml, out


def test_the_render_command_gives_one_line_for_a_far_sensor(tmp_path):
    """End to end: the command exits with the one line, no segfault, nothing written."""
    r, _, out = _render_scene_file(tmp_path, 'far.xml', '''\
        <scene version="3.0.0">
            <integrator type="nerfpp"><integer name="fg_samples" value="4"/>
                <integer name="bg_samples" value="4"/><integer name="fine_samples" value="0"/>
            </integrator>
            <sensor type="perspective">
                <transform name="to_world"><lookat origin="1e25, 0, 0" target="0, 0, 0"
                                                   up="0, 1, 0"/></transform>
                <film type="hdrfilm"><integer name="width" value="4"/>
                    <integer name="height" value="4"/></film>
            </sensor>
        </scene>''')
    assert r.returncode == 1, (r.returncode, r.stderr[-2000:])
    assert 'the sensor is at 1e+25 world units from the origin' in r.stderr
    assert not out.exists()


@pytest.mark.parametrize('name, value', [('rr_depth', 0), ('rr_depth', -3), ('max_depth', 0)])
def test_path_depths_below_one_are_named_by_the_integrator(name, value):
    """Issue 49, item 6: rr_depth 0 reached Mitsuba's own text ('"rr_depth" must be set to a
    value greater than zero!', from its base class): the integrator names the parameter."""
    message = refusal(lambda: mi.load_dict(scene_dict(**{name: value})))
    assert message == f"nerfpp: parameter '{name}' must be >= 1, got {value}"


def test_the_render_command_names_rr_depth_and_the_scene_file(tmp_path):
    """End to end: one line naming the parameter and the scene file, nothing written."""
    r, xml, out = _render_scene_file(tmp_path, 'rr.xml', '''\
        <scene version="3.0.0">
            <integrator type="nerfpp"><integer name="rr_depth" value="0"/></integrator>
            <sensor type="perspective">
                <film type="hdrfilm"><integer name="width" value="4"/>
                    <integer name="height" value="4"/></film>
            </sensor>
        </scene>''')
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 1 and len(lines) == 1, r.stderr[-2000:]
    assert lines[0].startswith("error: render: nerfpp: parameter 'rr_depth' must be >= 1, got 0")
    assert str(xml) in lines[0] and 'greater than zero' not in lines[0]
    assert not out.exists()


def test_a_film_beyond_max_samples_names_the_largest_spp_and_film():
    """``render --spp 1e9`` said 'the largest at 1000000000 spp is 0 pixels' alone: the message
    also names the most samples per pixel that fit at the film's size."""
    from mi_nerfpp.integrator.parameters import MAX_FILM_SAMPLES, check_film
    check_film((32, 24), MAX_FILM_SAMPLES // (32 * 24), MAX_FILM_SAMPLES)
    with pytest.raises(ValueError) as e:
        check_film((32, 24), 10 ** 9, MAX_FILM_SAMPLES)
    assert (f'(spp: at most {MAX_FILM_SAMPLES // (32 * 24)} at 32x24)' in str(e.value)
            and 'the largest at 1000000000 spp is 0 pixels' in str(e.value))
