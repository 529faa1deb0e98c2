"""Deep EXR output (issue 35): samples along each pixel whose flattening is the flat beauty,
at the right depth for a compositor's deep merge, read back by OpenEXR and by oiiotool."""
import subprocess
import sys

import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.core.coverage import CoverageFill
from mi_nerfpp.output import deep
from mi_nerfpp.files import exr
from mi_nerfpp.core.model import NeRFPPModel
from mi_nerfpp.output.views import render_to_files
from tests.helpers import AnalyticField, scene_dict, tiny_model
from tests.output.test_compositing import _oiiotool, sphere_field


def _rgb(layers):
    return np.stack([layers[c] for c in 'RGB'], axis=-1)


def _oiio_flatten(tool, src, out):
    subprocess.run([tool, str(src), '--flatten', '-d', 'float', '-o', str(out)], check=True,
                   capture_output=True, text=True)
    return exr.read_exr(out)


@pytest.mark.parametrize('fill', [False, True])
def test_deep_exr_flattens_to_the_flat_beauty_in_oiiotool(tmp_path, fill):
    """Target: oiiotool --flatten of the deep file equals the flat render within 2e-3 (the
    deep render takes the positions of a non-jittered stratified sampler at the same spp);
    also where a coverage fill paints the background (here every direction: no view saw
    any), whose colour the background's samples then carry."""
    tool = _oiiotool()
    scene = mi.load_dict(scene_dict(width=20, height=14, spp=4, jitter=False))
    model = tiny_model()
    if fill:
        model.coverage = CoverageFill(np.zeros((16, 32)), np.full((16, 32, 3), 0.7))
    scene.integrator().set_model(model)
    counts, samples, beauty = deep.render_deep_to_file(scene, tmp_path / 'd.exr',
                                                        progress=False)
    flat = render_to_files(scene, tmp_path / 'f.exr', progress=False)
    np.testing.assert_allclose(beauty, _rgb(flat), atol=2e-3)
    flattened = _oiio_flatten(tool, tmp_path / 'd.exr', tmp_path / 'df.exr')
    assert set(flattened) >= {'R', 'G', 'B', 'A', 'Z', 'ZBack'}
    assert np.abs(_rgb(flattened) - _rgb(flat)).max() <= 2e-3
    np.testing.assert_allclose(flattened['A'], 1.0, atol=1e-4)   # the background is opaque
    # Merged: fewer samples than the quadrature's 4 x (8 + 8 + 2·8) per pixel.
    assert counts.max() < 4 * 32 and counts.min() >= 1
    # OpenEXR reads back what was written; the samples are sorted and do not overlap.
    back_counts, back = deep.read_deep_exr(tmp_path / 'd.exr')
    np.testing.assert_array_equal(back_counts, counts)
    for ch in deep.DEEP_CHANNELS:
        np.testing.assert_array_equal(back[ch], samples[ch])
    assert np.all(samples['Z'] <= samples['ZBack'])
    first = np.r_[0, np.cumsum(counts.ravel())][:-1]
    later = np.setdiff1d(np.arange(len(samples['Z'])), first)
    assert np.all(samples['Z'][later] >= samples['ZBack'][later - 1])
    assert np.all((samples['A'] >= 0) & (samples['A'] <= 1))
    header = exr.read_header(tmp_path / 'd.exr')
    assert 'worldToCamera' in header and 'camera-space z' in header['depthConvention']


def test_deep_samples_sit_at_the_surface_and_deep_merge_with_cg(tmp_path):
    """An opaque sphere over a far background: the pixel's opaque sample starts at the
    sphere's camera z (as the flat depth.Z); a CG card deep-merged in front of it covers it,
    behind it is hidden, with no holdout matte (oiiotool --deepmerge)."""
    tool = _oiiotool()
    desc = scene_dict(width=16, height=12, origin=(0.0, 0.1, 0.9), spp=1, jitter=False,
                      fg_samples=256, bg_samples=16, fine_samples=64)
    scene = mi.load_dict(desc)
    scene.integrator().set_model(NeRFPPModel(sphere_field(0.4, (0.9, 0.2, 0.1)),
                                             AnalyticField(1.0, (0.1, 0.3, 0.8)),
                                             color_space='linear'))
    counts, samples, beauty = deep.render_deep_to_file(scene, tmp_path / 'd.exr',
                                                        progress=False)
    flat = render_to_files(scene, tmp_path / 'f.exr', progress=False)
    on = flat['fg.A'] == 1.0
    assert on.sum() > 20
    first = np.r_[0, np.cumsum(counts.ravel())][:-1].reshape(counts.shape)
    # The sphere's pixels: the first sample is the opaque surface, at the flat depth.Z.
    np.testing.assert_allclose(samples['A'][first[on]], 1.0, atol=1e-4)
    np.testing.assert_allclose(samples['Z'][first[on]], flat['depth.Z'][on], atol=0.01)
    # A green CG card, one opaque sample per pixel, 0.05 in front of / behind the sphere.
    h, w = counts.shape
    for offset, expect_green in ((-0.05, True), (0.05, False)):
        z = (flat['depth.Z'] + offset).astype(np.float32)
        card = {'R': np.zeros(h * w, np.float32), 'G': np.ones(h * w, np.float32),
                'B': np.zeros(h * w, np.float32), 'A': np.ones(h * w, np.float32),
                'Z': z.ravel(), 'ZBack': z.ravel()}
        deep.write_deep_exr(tmp_path / 'cg.exr', np.ones((h, w), np.int64), card)
        subprocess.run([tool, str(tmp_path / 'd.exr'), str(tmp_path / 'cg.exr'),
                        '--deepmerge', '--flatten', '-d', 'float', '-o',
                        str(tmp_path / 'm.exr')], check=True, capture_output=True, text=True)
        merged = exr.read_exr(tmp_path / 'm.exr')
        if expect_green:
            np.testing.assert_allclose(merged['G'][on], 1.0, atol=1e-4)
        else:
            np.testing.assert_allclose(merged['R'][on], flat['R'][on], atol=1e-3)
            assert np.all(merged['G'][on] < 0.5)


def test_deep_render_with_objects_and_a_shadow_catcher(tmp_path):
    """Objects (the mirror) and the catcher's shadow are in the deep samples: flattening in
    oiiotool gives the beauty of the same rays within 2e-3, and the mirror's sample is opaque
    at its surface."""
    tool = _oiiotool()
    from tests.integrator.test_scene_objects import CATCHER, ground_fields
    fg, bg = ground_fields()
    desc = scene_dict(width=20, height=15, origin=(0.0, 0.35, 0.75), target=(0, -0.3, 0),
                      spp=1, jitter=False, fg_samples=64, bg_samples=16, fine_samples=16,
                      shadow_catchers='catcher', catcher_samples=16)
    desc.update(CATCHER, ball={'type': 'sphere', 'center': [0, -0.1, 0], 'radius': 0.12,
                               'bsdf': {'type': 'conductor', 'material': 'none'}})
    scene = mi.load_dict(desc)
    scene.integrator().set_model(NeRFPPModel(fg, bg, color_space='linear'))
    counts, samples, beauty = deep.render_deep_to_file(scene, tmp_path / 'd.exr',
                                                        progress=False)
    flattened = _oiio_flatten(tool, tmp_path / 'd.exr', tmp_path / 'df.exr')
    assert np.abs(_rgb(flattened) - beauty).max() <= 2e-3
    flat = render_to_files(scene, tmp_path / 'f.exr', progress=False)
    assert (flat['shadow.R'] < 0).sum() > 4 and flat['obj.A'].max() == 1.0
    mirror = flat['obj.A'] == 1.0
    # Where the mirror covers the pixel the deep samples end in an opaque one at its depth
    # (one ray per pixel: the flat obj_depth.Z is that ray's).
    last = np.cumsum(counts.ravel()).reshape(counts.shape) - 1
    np.testing.assert_allclose(samples['A'][last[mirror]], 1.0, atol=1e-4)
    np.testing.assert_allclose(samples['Z'][last[mirror]], flat['obj_depth.Z'][mirror],
                               rtol=1e-4)


def test_render_command_writes_a_deep_exr(tmp_path):
    from mi_nerfpp.data.synth import scene_file
    out = tmp_path / 'deep.exr'
    r = subprocess.run([sys.executable, '-m', 'mi_nerfpp', 'render',
                        scene_file('render_random.xml'), '-o', str(out), '--deep',
                        '-D', 'res_x=12', '-D', 'res_y=8'],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    import OpenEXR
    with OpenEXR.File(str(out)) as f:
        header = f.header()
        assert header['type'] == OpenEXR.deepscanline
        assert {c.name for c in header['channels']} == set(deep.DEEP_CHANNELS)
