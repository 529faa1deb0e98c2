"""Tests for multi-layer EXR I/O (mi_nerfpp.files.exr) and PNG previews (mi_nerfpp.files.preview)."""
from __future__ import annotations

import os

import imageio.v3 as iio
import numpy as np
import OpenEXR
import pytest

from mi_nerfpp.core import color
from mi_nerfpp.files import exr, preview
from mi_nerfpp.core.layers import FULL_PRECISION_CHANNELS, LAYERS

H, W = 5, 7


def layer_channels(seed=0):
    rng = np.random.default_rng(seed)
    channels = {name: rng.uniform(0.0, 2.0, (H, W)).astype(np.float32)
                for name in LAYERS}
    channels['depth.Z'] = rng.uniform(0.5, 3000.0, (H, W)).astype(np.float32)
    channels['distance.Y'] = rng.uniform(0.5, 3000.0, (H, W)).astype(np.float32)
    return channels


# --- EXR ---------------------------------------------------------------------

def test_layers_layout(tmp_path):
    assert LAYERS == ('R', 'G', 'B', 'A', 'fg.R', 'fg.G', 'fg.B', 'fg.A',
                          'bg.R', 'bg.G', 'bg.B', 'depth.Z', 'distance.Y',
                          'obj.R', 'obj.G', 'obj.B', 'obj.A', 'obj_depth.Z',
                          'shadow.R', 'shadow.G', 'shadow.B')
    # The names are what a nerfpp render writes, each on the channel that holds its content:
    # a wrong name or order breaks the compositing identity or the alpha/depth checks.
    import mitsuba as mi

    from mi_nerfpp.output.views import render_to_files
    from tests.helpers import scene_dict, tiny_model
    scene = mi.load_dict(scene_dict())
    scene.integrator().set_model(tiny_model())
    render_to_files(scene, tmp_path / 'r.exr', progress=False)
    with OpenEXR.File(str(tmp_path / 'r.exr'), header_only=True) as f:
        assert {channel.name for channel in f.header()['channels']} == set(LAYERS)
    c = exr.read_exr(tmp_path / 'r.exr')
    for ch in 'RGB':
        np.testing.assert_allclose(c[ch], c[f'fg.{ch}'] + (1 - c['fg.A']) * c[f'bg.{ch}'],
                                   atol=2e-6)
    assert np.all(c['A'] == 1) and np.all((c['fg.A'] > 0) & (c['fg.A'] < 1))
    assert np.all(c['depth.Z'] > 0) and np.all(c['distance.Y'] > 0)


def test_round_trip_float32_is_exact(tmp_path):
    channels = layer_channels()
    path = tmp_path / 'render.exr'
    exr.write_exr(path, channels)
    back = exr.read_exr(path)
    assert set(back) == set(LAYERS)
    for name in LAYERS:
        assert back[name].dtype == np.float32
        assert back[name].shape == (H, W)
        np.testing.assert_array_equal(back[name], channels[name], err_msg=name)


def test_round_trip_half_within_half_precision(tmp_path):
    channels = layer_channels()
    path = tmp_path / 'render.exr'
    exr.write_exr(path, channels, half=True)
    back = exr.read_exr(path)
    for name in LAYERS:
        assert back[name].dtype == np.float32
        if name in FULL_PRECISION_CHANNELS:
            np.testing.assert_array_equal(back[name], channels[name])
        else:
            np.testing.assert_allclose(back[name], channels[name], rtol=2 ** -11, err_msg=name)


def test_half_stores_half_pixels_but_full_float_depth(tmp_path):
    path = tmp_path / 'render.exr'
    exr.write_exr(path, layer_channels(), half=True)
    with OpenEXR.File(str(path), separate_channels=True) as f:
        types = {name: channel.type() for name, channel in f.channels().items()}
    assert types.pop('depth.Z') == OpenEXR.FLOAT
    assert types.pop('distance.Y') == OpenEXR.FLOAT
    assert types.pop('obj_depth.Z') == OpenEXR.FLOAT
    assert set(types.values()) == {OpenEXR.HALF}


def test_channel_names_seen_by_openexr(tmp_path):
    path = tmp_path / 'render.exr'
    exr.write_exr(path, layer_channels())
    with OpenEXR.File(str(path), header_only=True) as f:
        names = {channel.name for channel in f.header()['channels']}
        assert len(f.parts) == 1
        assert f.header()['type'] == OpenEXR.scanlineimage
        assert f.header()['compression'] == OpenEXR.ZIP_COMPRESSION
    assert names == set(LAYERS)


def test_compression_option(tmp_path):
    path = tmp_path / 'render.exr'
    exr.write_exr(path, layer_channels(), compression='piz')
    with OpenEXR.File(str(path), header_only=True) as f:
        assert f.header()['compression'] == OpenEXR.PIZ_COMPRESSION
    with pytest.raises(ValueError, match='compression'):
        exr.write_exr(path, layer_channels(), compression='jpeg')


def test_input_dict_and_arrays_untouched(tmp_path):
    channels = layer_channels()
    copies = {name: pixels.copy() for name, pixels in channels.items()}
    exr.write_exr(tmp_path / 'render.exr', channels, half=True)
    assert set(channels) == set(copies)
    for name, pixels in channels.items():
        np.testing.assert_array_equal(pixels, copies[name])


def test_non_contiguous_and_float64_input(tmp_path):
    image = np.random.default_rng(1).uniform(size=(H, W, 3))
    channels = exr.split_channels(image, ['R', 'G', 'B'])
    path = tmp_path / 'rgb.exr'
    exr.write_exr(path, channels)
    back = exr.read_exr(path)
    for i, name in enumerate('RGB'):
        np.testing.assert_array_equal(back[name], image[..., i].astype(np.float32))


@pytest.mark.parametrize('bad', [np.nan, np.inf, -np.inf])
def test_non_finite_names_channel(tmp_path, bad):
    channels = layer_channels()
    channels['bg.G'][2, 3] = bad
    path = tmp_path / 'render.exr'
    with pytest.raises(ValueError, match=r"'bg\.G'"):
        exr.write_exr(path, channels)
    assert not path.exists()


def test_half_overflow_names_channel(tmp_path):
    channels = layer_channels()
    channels['R'][0, 0] = 1e6
    with pytest.raises(ValueError, match="'R'.*float16"):
        exr.write_exr(tmp_path / 'render.exr', channels, half=True)
    channels['depth.Z'][0, 0] = 1e6
    channels['R'][0, 0] = 1.0
    exr.write_exr(tmp_path / 'render.exr', channels, half=True)


def test_shape_mismatch(tmp_path):
    channels = layer_channels()
    channels['depth.Z'] = np.ones((H, W + 1), np.float32)
    with pytest.raises(ValueError, match=r"'depth\.Z'.*shape"):
        exr.write_exr(tmp_path / 'render.exr', channels)
    with pytest.raises(ValueError, match='H x W'):
        exr.write_exr(tmp_path / 'render.exr', {'R': np.ones((H, W, 1))})
    with pytest.raises(ValueError, match='no channels'):
        exr.write_exr(tmp_path / 'render.exr', {})


def test_atomic_write_leaves_no_temp_files(tmp_path):
    path = tmp_path / 'nested' / 'dir' / 'render.exr'
    exr.write_exr(path, layer_channels(0))
    exr.write_exr(path, layer_channels(1))  # overwrite in place
    assert os.listdir(path.parent) == ['render.exr']
    np.testing.assert_array_equal(exr.read_exr(path)['R'], layer_channels(1)['R'])


def test_written_files_get_umask_permissions(tmp_path):
    umask = os.umask(0o022)
    try:
        exr.write_exr(tmp_path / 'render.exr', layer_channels())
        preview.write_linear_png(tmp_path / 'preview.png', np.zeros((2, 2, 3)))
    finally:
        os.umask(umask)
    for name in ('render.exr', 'preview.png'):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o644


def test_failed_write_keeps_old_file_and_no_temp(tmp_path, monkeypatch):
    path = tmp_path / 'render.exr'
    exr.write_exr(path, layer_channels(0))

    def broken_replace(src, dst):
        raise OSError('disk full')

    monkeypatch.setattr(exr.os, 'replace', broken_replace)
    with pytest.raises(OSError, match='disk full'):
        exr.write_exr(path, layer_channels(1))
    monkeypatch.undo()
    assert os.listdir(tmp_path) == ['render.exr']
    np.testing.assert_array_equal(exr.read_exr(path)['R'], layer_channels(0)['R'])


def test_read_missing_file(tmp_path):
    path = tmp_path / 'missing.exr'
    with pytest.raises(ValueError, match='missing.exr'):
        exr.read_exr(path)


def test_read_garbage_file(tmp_path):
    path = tmp_path / 'garbage.exr'
    path.write_bytes(b'this is not an EXR file at all')
    with pytest.raises(ValueError, match='garbage.exr'):
        exr.read_exr(path)


def test_read_truncated_file(tmp_path):
    path = tmp_path / 'truncated.exr'
    exr.write_exr(path, layer_channels())
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ValueError, match='truncated.exr'):
        exr.read_exr(path)


def test_split_channels():
    image = np.arange(2 * 3 * 4, dtype=np.float32).reshape(2, 3, 4)
    parts = exr.split_channels(image, ['R', 'G', 'B', 'A'])
    assert list(parts) == ['R', 'G', 'B', 'A']
    np.testing.assert_array_equal(parts['B'], image[..., 2])
    with pytest.raises(ValueError, match='shape'):
        exr.split_channels(image, ['R', 'G', 'B'])
    with pytest.raises(ValueError, match='duplicate'):
        exr.split_channels(image, ['R', 'G', 'G', 'A'])


# --- PNG previews -------------------------------------------------------------

def test_write_linear_png_round_trip(tmp_path):
    rgb = np.random.default_rng(2).uniform(size=(H, W, 3))
    path = tmp_path / 'out' / 'preview.png'
    preview.write_linear_png(path, rgb)
    np.testing.assert_array_equal(iio.imread(path), color.to_srgb8(rgb))
    assert os.listdir(path.parent) == ['preview.png']


def test_write_linear_png_uint8_written_as_is(tmp_path):
    pixels = np.arange(H * W * 3, dtype=np.uint8).reshape(H, W, 3)
    path = tmp_path / 'depth.png'
    preview.write_linear_png(path, pixels)
    np.testing.assert_array_equal(iio.imread(path), pixels)


def test_depth_to_png_inverse_depth_ramp():
    depth = np.array([[1.0, 2.0, 4.0]])
    gray = preview.depth_to_png(depth)
    assert gray.shape == (1, 3, 3) and gray.dtype == np.uint8
    # inverse depths 1, 0.5, 0.25 normalised to [0, 1]: 1, 1/3, 0
    assert gray[0, :, 0].tolist() == [255, 85, 0]
    assert np.all(gray == gray[..., :1])


def test_depth_to_png_explicit_range_and_invalid_pixels():
    depth = np.array([[0.5, 1.0, 2.0, np.inf, np.nan, 0.0, -1.0, 100.0]])
    gray = preview.depth_to_png(depth, near=1.0, far=2.0)[0, :, 0]
    assert gray.tolist() == [255, 255, 0, 0, 0, 0, 0, 0]


def test_depth_to_png_degenerate_ranges():
    assert np.all(preview.depth_to_png(np.full((2, 2), 3.0)) == 255)
    assert np.all(preview.depth_to_png(np.full((2, 2), np.inf)) == 0)
    # an explicit near beyond all depths widens the default far
    assert np.all(preview.depth_to_png(np.full((2, 2), 3.0), near=5.0) == 255)
    with pytest.raises(ValueError, match='near'):
        preview.depth_to_png(np.ones((2, 2)), near=2.0, far=1.0)
    with pytest.raises(ValueError, match='H x W'):
        preview.depth_to_png(np.ones((2, 2, 1)))
