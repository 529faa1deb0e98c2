"""Compositing-grade EXR output: scene-linear colour, one alpha, fixed channels, camera
metadata, a surface depth, and a real compositor (oiiotool) reproducing the beauty."""
import os
import shutil
import subprocess

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.files import exr
from mi_nerfpp.core.color import REC709_CHROMATICITIES
from mi_nerfpp.data import Camera, mitsuba_sensor_dict
from mi_nerfpp.core.layers import LAYERS
from mi_nerfpp.core.model import NeRFPPModel
from mi_nerfpp.core.render import HIDDEN_WEIGHT
from mi_nerfpp.output.views import camera_attributes, render_to_files
from tests.helpers import AnalyticField, scene_dict, tiny_model

OIIOTOOL_OPT_OUT = 'MI_NERFPP_NO_OIIOTOOL'


def sphere_field(radius, color):
    """An opaque sphere of constant colour at the origin (a closed-form scene)."""
    return AnalyticField(
        lambda x: dr.select(dr.norm(mi.Vector3f(x[0], x[1], x[2])) < radius, 1e5, 0.0), color)


def sphere_scene(radius=0.4, color=(0.5, 0.5, 0.5), color_space='linear', **kwargs):
    desc = scene_dict(**dict(dict(width=16, height=12, origin=(0.0, 0.1, 0.9), jitter=False,
                                  background=False, fg_samples=256, fine_samples=64), **kwargs))
    scene = mi.load_dict(desc)
    scene.integrator().set_model(NeRFPPModel(sphere_field(radius, color), None,
                                             color_space=color_space))
    return scene


def render(scene, tmp_path, **kwargs):
    return render_to_files(scene, tmp_path / 'r.exr', progress=False, **kwargs)


def test_header_declares_scene_linear_rec709_and_depth_convention(tmp_path, tiny_scene):
    render(tiny_scene, tmp_path)
    header = exr.read_header(tmp_path / 'r.exr')
    np.testing.assert_allclose(header['chromaticities'], REC709_CHROMATICITIES, atol=1e-6)
    assert header['oiio:ColorSpace'] == 'linear'
    assert 'camera-space z' in header['depthConvention']
    assert header['software'].startswith('mi-nerfpp ')
    assert header['fovX'] == pytest.approx(60.0, abs=1e-3)
    assert header['clipNear'] == pytest.approx(0.01)


@pytest.mark.parametrize('pixel_format', ['rgb', 'rgba'])
def test_channels_do_not_depend_on_the_film_pixel_format(tmp_path, pixel_format):
    desc = scene_dict()
    desc['sensor']['film']['pixel_format'] = pixel_format
    scene = mi.load_dict(desc)
    scene.integrator().set_model(tiny_model())
    render(scene, tmp_path)
    assert set(exr.read_exr(tmp_path / 'r.exr')) == set(LAYERS)
    assert 'alpha.Y' not in LAYERS


def test_foreground_only_render_carries_the_foreground_alpha(tmp_path):
    c = render(sphere_scene(), tmp_path)
    np.testing.assert_array_equal(c['A'], c['fg.A'])
    assert c['fg.A'].min() == 0.0 and c['fg.A'].max() == 1.0
    assert np.all((c['fg.A'] >= 0) & (c['fg.A'] <= 1))


def _project(attributes, point, width, height):
    """Pixel position and camera-space point of a world point from the EXR matrices, as
    ImfStandardAttributes.h defines them: row vectors; NDC (0, 0) the upper-left and (1, 1)
    the lower-right corner of the display window; camera +x right, +y up, +z forward."""
    p = np.append(point, 1.0)
    cam = p @ attributes['worldToCamera'].astype(np.float64)
    ndc = p @ attributes['worldToNDC'].astype(np.float64)
    ndc = ndc[:3] / ndc[3]
    return np.array([ndc[0] * width, ndc[1] * height]), cam[:3]


def _mitsuba_pixel(sensor, point):
    it = dr.zeros(mi.Interaction3f)
    it.p = mi.Point3f(*[float(v) for v in point])
    ds, _ = sensor.sample_direction(it, mi.Point2f(0.5))
    return np.array(ds.uv, dtype=np.float64).reshape(2)


@pytest.mark.parametrize('principal', [(0.5, 0.5), (0.42, 0.61)])
def test_camera_matrices_reproject_a_known_point(tmp_path, principal):
    width, height = 96, 72
    K = np.array([[35.0, 0, principal[0] * width], [0, 35.0, principal[1] * height], [0, 0, 1]])
    c2w = np.eye(4)
    angle = 0.3
    c2w[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    c2w[:3, 3] = [1.0, -2.0, 3.0]
    camera = Camera(K, c2w, width, height)
    sensor = mi.load_dict(mitsuba_sensor_dict(camera))
    point = c2w[:3, :3] @ np.array([0.7, -0.4, 5.0]) + c2w[:3, 3]    # in front of the camera
    # Written and read back through OpenEXR.
    exr.write_exr(tmp_path / 'c.exr', {'R': np.zeros((height, width), np.float32)},
                  attributes=camera_attributes(sensor))
    attributes = exr.read_header(tmp_path / 'c.exr')
    # Points all over the view, the corners included.
    rng = np.random.default_rng(3)
    for local in [np.array([0.7, -0.4, 5.0])] + [
            np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
            for u, v, z in zip(rng.uniform(0, width, 20), rng.uniform(0, height, 20),
                               rng.uniform(0.5, 50, 20))]:
        point = c2w[:3, :3] @ local + c2w[:3, 3]
        pixel, cam = _project(attributes, point, width, height)
        # Target (issue 35): within 0.01 px of Mitsuba's own projection and of OpenCV's.
        np.testing.assert_allclose(pixel, _mitsuba_pixel(sensor, point),
                                   atol=1e-2)
        x_cam = np.linalg.inv(c2w) @ np.append(point, 1.0)     # OpenCV: x right, y down
        np.testing.assert_allclose(pixel, (K @ x_cam[:3])[:2] / x_cam[2], atol=1e-2)
        # The standard's camera space: +x right, +y up, +z forward (in front: z > 0).
        np.testing.assert_allclose(cam, [x_cam[0], -x_cam[1], x_cam[2]], rtol=1e-5, atol=1e-4)
    assert cam[2] > 0


def test_depth_is_camera_z_of_an_opaque_sphere(tmp_path):
    radius = 0.4
    scene = sphere_scene(radius)
    c = render(scene, tmp_path)
    attributes = exr.read_header(tmp_path / 'r.exr')
    sensor = scene.sensors()[0]
    w2c = attributes['worldToCamera'].T.astype(np.float64)
    center = np.linalg.inv(w2c)[:3, 3]
    forward = np.linalg.inv(w2c)[:3, 2]
    hits = 0
    for y in range(12):
        for x in range(16):
            ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((x + 0.5) / 16, (y + 0.5) / 12),
                                       mi.Point2f(0.5))
            d = np.array(ray.d, dtype=np.float64).reshape(3)
            b = center @ d
            disc = b * b - (center @ center - radius ** 2)
            if disc <= 1e-3:          # misses (or grazes) the sphere
                assert c['fg.A'][y, x] < 0.5 or disc > -1e-3
                continue
            hit = center + (-b - np.sqrt(disc)) * d
            z = (w2c @ np.append(hit, 1.0))[2]         # +z: the viewing direction
            assert z == pytest.approx((hit - center) @ forward)
            # The quadrature places a sample's interval at the sample: 256 coarse samples
            # along a chord of at most 2 units leave less than 0.008 units.
            assert c['depth.Z'][y, x] == pytest.approx(z, abs=0.008), (x, y)
            hits += 1
    assert hits > 40


def test_srgb_model_renders_linear_radiance(tmp_path):
    """A field fitted to sRGB photos outputs encoded colour; the EXR holds it decoded."""
    c = render(sphere_scene(color=(0.5, 0.2, 0.9), color_space='srgb'), tmp_path)
    centre = c['fg.A'] == 1.0
    expected = [0.21404114, 0.03310477, 0.78741229]     # the sRGB EOTF of (0.5, 0.2, 0.9)
    for ch, value in zip('RGB', expected):
        # Within the early termination's bound: the sphere's skipped samples hold < 1e-4.
        np.testing.assert_allclose(c[ch][centre], value, rtol=0, atol=HIDDEN_WEIGHT)


def _oiiotool():
    tool = shutil.which('oiiotool')
    if tool is None:
        if os.environ.get(OIIOTOOL_OPT_OUT):
            pytest.skip(f'oiiotool not installed and {OIIOTOOL_OPT_OUT} is set')
        pytest.fail('oiiotool (OpenImageIO) is not installed: run scripts/setup.sh --test (apt '
                    f'package openimageio-tools), or set {OIIOTOOL_OPT_OUT}=1 to skip this check')
    return tool


def test_oiiotool_composites_fg_over_bg_to_the_beauty(tmp_path, tiny_scene):
    tool = _oiiotool()
    c = render(tiny_scene, tmp_path)
    src, out = str(tmp_path / 'r.exr'), str(tmp_path / 'comp.exr')
    subprocess.run([tool, src, '--ch', 'R=fg.R,G=fg.G,B=fg.B,A=fg.A',
                    src, '--ch', 'R=bg.R,G=bg.G,B=bg.B,A=1.0', '--over', '-d', 'float',
                    '-o', out], check=True, capture_output=True, text=True)
    comp = exr.read_exr(out)
    for ch in 'RGB':
        np.testing.assert_allclose(comp[ch], c[ch], atol=1e-6)
    info = subprocess.run([tool, '--info', '-v', src], check=True, capture_output=True,
                          text=True).stdout
    assert 'oiio:ColorSpace: "linear"' in info and 'chromaticities' in info


def test_oiiotool_converts_from_the_declared_colour_space(tmp_path, tiny_scene):
    """oiiotool's built-in colour config resolves the file's colour space: --tocolorspace
    sRGB applies the sRGB curve to the linear beauty."""
    from mi_nerfpp.core.color import srgb_oetf
    tool = _oiiotool()
    c = render(tiny_scene, tmp_path)
    src, out = str(tmp_path / 'r.exr'), str(tmp_path / 'srgb.exr')
    subprocess.run([tool, src, '--ch', 'R,G,B', '--tocolorspace', 'sRGB', '-d', 'float',
                    '-o', out], check=True, capture_output=True, text=True)
    converted = exr.read_exr(out)
    for ch in 'RGB':
        np.testing.assert_allclose(converted[ch], srgb_oetf(np.clip(c[ch], 0, 1)), atol=2e-3)


def test_oiiotool_composite_over_a_linear_plate(tmp_path):
    """The foreground merged over a linear plate in oiiotool is the linear-light composite."""
    tool = _oiiotool()
    c = render(sphere_scene(color=(0.5, 0.2, 0.9), color_space='srgb'), tmp_path)
    plate = (0.25, 0.5, 0.125)
    src, out = str(tmp_path / 'r.exr'), str(tmp_path / 'comp.exr')
    subprocess.run([tool, src, '--ch', 'R=fg.R,G=fg.G,B=fg.B,A=fg.A',
                    '--pattern', f'constant:color={plate[0]},{plate[1]},{plate[2]},1', '16x12', '4',
                    '--over', '-d', 'float', '-o', out], check=True, capture_output=True, text=True)
    comp = exr.read_exr(out)
    for ch, p in zip('RGB', plate):
        np.testing.assert_allclose(comp[ch], c[f'fg.{ch}'] + (1 - c['fg.A']) * p, atol=1e-6)
    assert comp['R'][6, 8] == pytest.approx(0.21404114, rel=1e-5)     # the decoded sphere


def test_checkpoint_from_before_linear_compositing_renders_as_trained(tmp_path):
    """Older sRGB checkpoints summed encoded colour: they render as trained, decoded after."""
    import json

    from mi_nerfpp.files.checkpoint import load_checkpoint, save_checkpoint
    from mi_nerfpp.core.color import srgb_oetf
    path = tmp_path / 'old.npz'
    save_checkpoint(path, tiny_model())
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    config = json.loads(str(arrays['config']))
    del config['composite']                              # as written before issue 11
    arrays['config'] = np.array(json.dumps(config))
    np.savez(path, **arrays)
    legacy, _, _ = load_checkpoint(path)
    assert legacy.composite == 'srgb' and load_checkpoint_composite(tmp_path) == 'linear'

    def beauty(model):
        scene = mi.load_dict(scene_dict(jitter=False))
        scene.integrator().set_model(model)
        return render(scene, tmp_path)
    trained = beauty(NeRFPPModel(legacy.fg, legacy.bg, color_space='linear'))  # no decoding
    c = beauty(legacy)
    for ch in 'RGB':
        np.testing.assert_allclose(srgb_oetf(c[ch]), trained[ch], atol=2e-5)
        np.testing.assert_allclose(srgb_oetf(c[f'bg.{ch}']), trained[f'bg.{ch}'], atol=2e-5)


def load_checkpoint_composite(tmp_path):
    """What a checkpoint written now records (for the test above)."""
    from mi_nerfpp.files.checkpoint import load_checkpoint, save_checkpoint
    save_checkpoint(tmp_path / 'new.npz', tiny_model())
    return load_checkpoint(tmp_path / 'new.npz')[0].composite


def _edge_scene(spp, rfilter, **integrator):
    """Hard edges everywhere: an opaque reconstructed sphere in front of a background that
    varies with direction, a diffuse ball and a camera-facing card inserted, and a shadow
    catcher under them; camera samples jittered over the pixel."""
    from tests.integrator.test_scene_objects import CATCHER, sky
    fg = sphere_field(0.15, (0.9, 0.3, 0.2))
    bg = AnalyticField(1.0, sky)
    z_card = -0.25
    shapes = dict(CATCHER, ball={'type': 'sphere', 'center': [0.25, -0.15, 0.1], 'radius': 0.1,
                                 'bsdf': {'type': 'diffuse'}},
                  card={'type': 'rectangle', 'to_world': mi.ScalarTransform4f()
                        .translate([-0.3, 0.05, z_card]).scale(0.12),
                        'bsdf': {'type': 'diffuse'}})
    desc = scene_dict(width=24, height=18, origin=(0.0, 0.0, 0.9), spp=spp,
                      **dict(dict(fg_samples=64, bg_samples=16, fine_samples=16,
                                  shadow_catchers='catcher', catcher_samples=8), **integrator))
    desc['sensor']['sampler'] = {'type': 'independent', 'sample_count': spp}
    desc['sensor']['film']['rfilter'] = {'type': rfilter}
    desc.update(shapes)
    scene = mi.load_dict(desc)
    scene.integrator().set_model(NeRFPPModel(fg, bg, color_space='linear'))
    return scene, 0.9 - z_card


@pytest.mark.parametrize('rfilter', ['box', 'gaussian'])
def test_layers_add_up_at_16_spp_with_objects(tmp_path, rfilter):
    """Issue 35's first target: at 16 samples per pixel, with soft edges of the foreground
    and of inserted objects, max |beauty - (fg + (1 - fg.A)·bg + obj + shadow)| <= 1e-4, in
    the file as written (and without objects the README's fg over bg)."""
    scene, card_z = _edge_scene(16, rfilter)
    c = render_to_files(scene, tmp_path / 'r.exr', progress=False)
    c = exr.read_exr(tmp_path / 'r.exr')
    edges_fg = (c['fg.A'] > 0.05) & (c['fg.A'] < 0.95)
    edges_obj = (c['obj.A'] > 0.05) & (c['obj.A'] < 0.95)
    assert edges_fg.sum() >= 8 and edges_obj.sum() >= 8       # the test sees soft edges
    assert (c['shadow.R'] < 0).sum() >= 4
    for ch in 'RGB':
        full = c[f'fg.{ch}'] + (1 - c['fg.A']) * c[f'bg.{ch}'] + c[f'obj.{ch}'] \
            + c[f'shadow.{ch}']
        assert np.abs(c[ch] - full).max() <= 1e-4, ch
    # The card faces the camera: its depth is one number, also where it covers part of a
    # pixel (a plain average would blend it with 0 there).
    card = (c['obj.A'] > 0) & (np.abs(c['obj_depth.Z'] - card_z) < 0.05)
    assert (card & (c['obj.A'] < 0.95)).sum() >= 4
    np.testing.assert_allclose(c['obj_depth.Z'][card], card_z, rtol=1e-4)
    assert np.all(c['obj_depth.Z'][c['obj.A'] == 0] == 0)
    # Without shapes the layers are the README's fg over bg, and oiiotool agrees.
    plain = sphere_scene(0.15, (0.9, 0.3, 0.2), background=True, width=24, height=18, spp=16)
    plain.integrator().set_model(NeRFPPModel(sphere_field(0.15, (0.9, 0.3, 0.2)),
                                             AnalyticField(1.0, _sky()), color_space='linear'))
    c = render(plain, tmp_path)
    assert ((c['fg.A'] > 0.05) & (c['fg.A'] < 0.95)).sum() >= 8
    for ch in 'RGB':
        assert np.abs(c[ch] - (c[f'fg.{ch}'] + (1 - c['fg.A']) * c[f'bg.{ch}'])).max() <= 1e-4


def _sky():
    from tests.integrator.test_scene_objects import sky
    return sky


def test_bg_of_an_opaque_pixel_is_the_plain_background_with_occluded_background(tmp_path):
    """Where the foreground is opaque in every sample, bg is the background's own average
    (occluded_background on) or 0 (off), and the identity holds either way."""
    for occluded in (True, False):
        scene = sphere_scene(0.4, (0.5, 0.5, 0.5), background=True, spp=4,
                             occluded_background=occluded)
        scene.integrator().set_model(NeRFPPModel(sphere_field(0.4, (0.5, 0.5, 0.5)),
                                                 AnalyticField(1.0, (0.2, 0.4, 0.6)),
                                                 color_space='linear'))
        c = render(scene, tmp_path)
        opaque = c['fg.A'] == 1.0
        assert opaque.sum() > 10
        np.testing.assert_allclose(c['bg.G'][opaque], 0.4 if occluded else 0.0, atol=1e-6)
        np.testing.assert_allclose(c['bg.G'][c['fg.A'] == 0], 0.4, atol=1e-6)
        for ch in 'RGB':
            assert np.abs(c[ch] - (c[f'fg.{ch}'] + (1 - c['fg.A']) * c[f'bg.{ch}'])).max() \
                <= 1e-4
