"""Scenes: the render command refuses, with one line naming the scene or the option, what it
cannot do right - a scene without a camera, an output name whose extension is not the format
written - and the integrator's XML parameters are checked where they are read."""
import time

import pytest

from tests.robustness.common import one_clear_line, run_cli

SCENE = """<scene version="3.0.0">
    <integrator type="nerfpp">
        {integrator}
    </integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, 0.5" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
        <film type="hdrfilm"><integer name="width" value="{w}"/><integer name="height" value="{h}"/></film>
    </sensor>
</scene>
"""

SENSORS = {
    'radiancemeter': '<sensor type="radiancemeter"><point name="origin" value="0, 0, 0.5"/>'
                     '<vector name="direction" value="0, 0, -1"/><film type="hdrfilm">'
                     '<integer name="width" value="1"/><integer name="height" value="1"/>'
                     '</film></sensor>',
    'orthographic': '<sensor type="orthographic"><film type="hdrfilm"><integer name="width" '
                    'value="4"/><integer name="height" value="3"/></film></sensor>',
    'thinlens': '<sensor type="thinlens"><float name="aperture_radius" value="0.01"/>'
                '<float name="focus_distance" value="0.5"/><transform name="to_world"><lookat '
                'origin="0, 0, 0.5" target="0, 0, 0" up="0, 1, 0"/></transform><film '
                'type="hdrfilm"><integer name="width" value="4"/><integer name="height" '
                'value="3"/></film></sensor>',
    'none': '',
}


def render_xml(capsys, tmp_path, integrator='', spp=1, w=4, h=3, *extra, out='out.exr'):
    scene = tmp_path / 'scene' / 'scene.xml'
    scene.parent.mkdir(exist_ok=True)
    scene.write_text(SCENE.format(integrator=integrator, spp=spp, w=w, h=h))
    return run_cli(capsys, 'render', scene, '-o', tmp_path / out, *extra)


def scene_with(tmp_path, sensor):
    path = tmp_path / f'{sensor}.xml'
    path.write_text(f'<scene version="3.0.0"><integrator type="nerfpp"/>{SENSORS[sensor]}'
                    f'</scene>')
    return path


def test_a_scene_without_sensor_is_refused(capsys, tmp_path):
    """Was an IndexError traceback."""
    scene = scene_with(tmp_path, 'none')
    status, _, err = run_cli(capsys, 'render', scene, '-o', tmp_path / 'out.exr')
    assert status == 1 and one_clear_line(err) == (
        f'error: render: {scene}: the scene has no sensor: add a <sensor type="perspective"> '
        f'with a film (see scenes/render_random.xml)')
    assert not (tmp_path / 'out.exr').exists()


@pytest.mark.parametrize('sensor', ['radiancemeter', 'orthographic'])
def test_a_sensor_that_is_not_a_pinhole_camera_is_refused(capsys, tmp_path, sensor):
    """A radiancemeter was an AttributeError traceback (no near_clip); an orthographic camera
    wrote an EXR whose camera matrices were NaN."""
    scene = scene_with(tmp_path, sensor)
    status, _, err = run_cli(capsys, 'render', scene, '-o', tmp_path / 'out.exr')
    assert status == 1 and one_clear_line(err) == (
        f"error: render: {scene}: the scene's sensor is '{sensor}': render takes a perspective "
        f"or thinlens sensor (a camera with a film image, which the EXR header describes)")
    assert not (tmp_path / 'out.exr').exists()


def test_a_thinlens_camera_renders(capsys, tmp_path):
    from mi_nerfpp.files.exr import read_exr
    scene = scene_with(tmp_path, 'thinlens')
    status, _, _ = run_cli(capsys, 'render', scene, '-o', tmp_path / 'out.exr')
    assert status == 0 and read_exr(tmp_path / 'out.exr')['R'].shape == (3, 4)


@pytest.mark.parametrize('option, name, message', [
    ('-o', 'out.png', 'the render writes a multi-layer OpenEXR file here: give a name ending '
                      'in .exr (a PNG preview: --preview NAME.png)'),
    ('-o', 'out', 'the render writes a multi-layer OpenEXR file here: give a name ending in '
                  '.exr (a PNG preview: --preview NAME.png)'),
    ('--preview', 'preview.jpg', 'the render writes an sRGB PNG here: give a name ending in '
                                 '.png'),
])
def test_an_output_name_of_another_format_is_refused(capsys, tmp_path, option, name, message):
    """render -o out.png exited 0 and wrote an OpenEXR file named .png."""
    scene = tmp_path / 'scene.xml'
    scene.write_text(SCENE.format(integrator='', spp=1, w=4, h=3))
    argv = ['-o', tmp_path / 'out.exr'] if option == '--preview' else []
    status, _, err = run_cli(capsys, 'render', scene, *argv, option, tmp_path / name)
    assert status == 1 and one_clear_line(err) == (
        f'error: render: {option} {tmp_path / name}: {message}')
    assert sorted(p.name for p in tmp_path.iterdir()) == ['scene.xml']


@pytest.mark.parametrize('seed', [-1, 2 ** 32, 2 ** 64])
def test_a_render_seed_beyond_32_bits_is_refused(capsys, tmp_path, seed):
    """Was nanobind's 'incompatible function arguments ... Invoked with types: int, int'."""
    status, _, err = render_xml(capsys, tmp_path, '', 1, 4, 3, '--seed', seed)
    assert status == 1 and one_clear_line(err) == (
        f'error: render: --seed must be a whole number from 0 to 4294967295, got {seed}')


# ----------------------------------------------------------------------------- XML parameters

@pytest.mark.parametrize('integrator, message', [
    ('<integer name="fg_sample" value="8"/>', "nerfpp: unknown parameter(s) fg_sample"),
    ('<string name="fg_samples" value="abc"/>',
     "nerfpp: parameter 'fg_samples' must be given as <integer name=\"fg_samples\""),
    ('<integer name="fg_samples" value="0"/>', "parameter 'fg_samples' must be >= 1, got 0"),
    ('<integer name="fg_samples" value="-3"/>', "parameter 'fg_samples' must be >= 1, got -3"),
    ('<integer name="chunk_rays" value="0"/>', "parameter 'chunk_rays' must be >= 1, got 0"),
    ('<float name="near" value="nan"/>', "parameter 'near' is NaN"),
])
def test_bad_integrator_parameters(capsys, tmp_path, integrator, message):
    status, _, err = render_xml(capsys, tmp_path, integrator)
    line = one_clear_line(err)
    assert status == 1 and message in line and 'scene.xml' in line
    assert not (tmp_path / 'out.exr').exists()


def test_missing_checkpoint_shows_where_it_was_looked_for(capsys, tmp_path):
    status, _, err = render_xml(capsys, tmp_path, '<string name="checkpoint" value="m.npz"/>')
    line = one_clear_line(err)
    assert status == 1 and "checkpoint 'm.npz' not found" in line
    assert str(tmp_path / 'scene' / 'm.npz') in line


def test_sample_count_zero_is_refused_not_a_crash(capsys, tmp_path):
    status, _, err = render_xml(capsys, tmp_path, spp=0)
    assert status == 1 and 'sample_count 0' in one_clear_line(err)


def test_film_beyond_the_budget_is_refused_before_allocating(capsys, tmp_path):
    t0 = time.perf_counter()
    status, _, err = render_xml(capsys, tmp_path, w=20000, h=20000)
    line = one_clear_line(err)
    assert status == 1 and '20000x20000 film' in line and 'max_samples=16777216' in line
    assert time.perf_counter() - t0 < 30
    status, _, err = render_xml(capsys, tmp_path, '<integer name="max_samples" value="10"/>')
    assert status == 1 and 'more than max_samples=10' in one_clear_line(err)


def test_malformed_scene_file_is_one_line(capsys, tmp_path):
    scene = tmp_path / 'bad.xml'
    scene.write_text('<scene version="3.0.0"><integrator type="nerfpp">')
    status, _, err = run_cli(capsys, 'render', scene, '-o', tmp_path / 'out.exr')
    assert status == 1 and one_clear_line(err).startswith('error: render: ')


def test_render_output_that_is_a_folder_is_refused(capsys, tmp_path):
    scene = tmp_path / 'scene.xml'
    scene.write_text(SCENE.format(integrator='', spp=1, w=4, h=3))
    status, _, err = run_cli(capsys, 'render', scene, '-o', tmp_path)
    assert status == 1 and 'is a folder: give a file name' in one_clear_line(err)


def test_a_define_without_value_is_one_line(capsys, tmp_path):
    status, _, err = render_xml(capsys, tmp_path, '', 1, 4, 3, '-D', 'spp')
    assert status == 1 and one_clear_line(err) == (
        "error: render: -D expects name=value, got 'spp'")
