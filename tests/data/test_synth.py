"""Synthetic captures (`python -m mi_nerfpp synth`): layout, ground truth, caching, trajectories."""
import json
import os
import re

import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.data import synth
from mi_nerfpp.commands.cli import main
from mi_nerfpp.data import load_dataset, pixel_rays
from mi_nerfpp.data.cameras import Camera
from mi_nerfpp.files.exr import read_exr

GARDEN = synth.scene_file('gt_garden.xml')
TINY = dict(views=6, res=(16, 12), spp=4, progress=False)


@pytest.fixture(scope='module')
def garden(tmp_path_factory):
    """A tiny orbit capture of the garden scene (6 views, 16x12, 4 spp)."""
    out = tmp_path_factory.mktemp('garden')
    info = synth.synthesize(GARDEN, out, **TINY)
    return out, info


def gt_files(out):
    return sorted(str(p) for p in out.glob('*/gt/*.exr'))


def test_orbit_capture_loads_as_nerfpp_dataset(garden):
    out, info = garden
    assert not info['cached']
    ds = load_dataset(out)
    assert ds.format == 'nerfpp' and ds.color_space == 'srgb'
    assert (len(ds.train), len(ds.validation), len(ds.test)) == (4, 1, 1)
    for split in (ds.train, ds.validation, ds.test):
        for cam, img in zip(split.cameras, split.images):
            assert np.linalg.norm(cam.center) < 1.0
            assert img.shape == (12, 16, 3)
            assert cam.width == 16 and cam.height == 12
            assert cam.fov_x == pytest.approx(50.0)
    # The reader's normalization is the one that defines the foreground sphere of fg.A.
    norm = info['normalization']
    np.testing.assert_allclose(ds.normalization.center, norm['center'], rtol=1e-9)
    assert ds.normalization.scale == pytest.approx(norm['scale'], rel=1e-9)
    assert norm['world_radius'] == pytest.approx(1.0 / norm['scale'])
    # Images are not blank: the scene is lit and has colour.
    assert 0.05 < np.mean(ds.train.images) < 0.95


def test_capture_json_describes_the_capture(garden):
    out, _ = garden
    with open(out / 'capture.json') as f:
        info = json.load(f)
    assert info['complete'] is True
    assert info['scene'] == GARDEN and info['trajectory'] == 'orbit'
    assert info['views'] == {'train': 4, 'validation': 1, 'test': 1}
    assert info['resolution'] == [16, 12] and info['spp'] == 4 and info['seed'] == 0
    assert info['mitsuba'] == mi.__version__ == '3.9.1'
    assert set(info['normalization']) == {'center', 'scale', 'world_radius'}
    assert len(info['names']['train']) == 4
    assert info['params']['views'] == 6


def test_ground_truth_layers(garden):
    out, info = garden
    files = gt_files(out)
    assert len(files) == 6
    masks = []
    for path in files:
        layers = read_exr(path)
        assert {'R', 'G', 'B', 'depth.Z', 'fg.A'} <= set(layers)
        depth, fg = layers['depth.Z'], layers['fg.A']
        assert depth.shape == (12, 16)
        assert np.all(np.isfinite(depth)) and np.all(depth >= 0)
        hit = depth > 0
        assert hit.mean() > 0.5                       # the lawn fills most of every view
        assert np.all(depth[hit] > 0.5) and np.all(depth[hit] < 500)
        assert set(np.unique(fg)) <= {0.0, 1.0}
        assert np.all(fg[~hit] == 0)                  # the environment is background
        masks.append(fg)
    masks = np.stack(masks)
    assert masks.min() == 0 and masks.max() == 1      # foreground objects and distant scenery
    # The PNG is the sRGB encoding of the linear layers.
    from mi_nerfpp.core.color import to_srgb8
    import imageio.v3 as iio
    png = iio.imread(out / 'train' / 'rgb' / '000000.png')
    layers = read_exr(out / 'train' / 'gt' / '000000.exr')
    linear = np.stack([layers[c] for c in 'RGB'], axis=-1)
    np.testing.assert_array_equal(png, to_srgb8(linear))


def test_depth_matches_ray_intersection_at_image_centre(garden):
    out, info = garden
    pose = np.loadtxt(out / 'train' / 'pose' / '000001.txt')
    K = np.loadtxt(out / 'train' / 'intrinsics' / '000001.txt')[:3, :3]
    camera = Camera(K, pose, 16, 12)
    layers = read_exr(out / 'train' / 'gt' / '000001.exr')
    scene = mi.load_file(GARDEN)
    # The pixel whose centre is (8.5, 6.5), and one off the axis in the lower corner (lawn).
    for row, col in ((10, 1), (6, 8)):
        origin, direction = pixel_rays(camera, col + 0.5, row + 0.5)
        si = scene.ray_intersect(mi.Ray3f(mi.Point3f(origin.T), mi.Vector3f(direction.T)))
        assert bool(si.is_valid()[0])
        t = float(si.t[0])
        # depth.Z is camera-space z, as in renders: the ray distance times the cosine to the
        # view axis (0.9 for the corner pixel, so a ray distance would be off by 10 %).
        cos = float(np.ravel(direction) @ pose[:3, 2]) / float(np.linalg.norm(direction))
        assert cos < 0.95 if col == 1 else cos > 0.999
        assert layers['depth.Z'][row, col] == pytest.approx(t * cos, rel=1e-3)
    hit = np.array(si.p).ravel()
    norm = info['normalization']
    inside = np.linalg.norm(hit - norm['center']) <= norm['world_radius']
    assert layers['fg.A'][row, col] == float(inside)


def test_second_call_is_cached_and_changes_rerender(tmp_path):
    out = tmp_path / 'cap'
    kw = dict(views=3, res=(8, 6), spp=1, progress=False)
    first = synth.synthesize(synth.scene_file('gt_bounded.xml'), out, **kw)
    assert not first['cached']
    files = sorted(out.rglob('*.*'))
    mtimes = {p: p.stat().st_mtime_ns for p in files}
    again = synth.synthesize(synth.scene_file('gt_bounded.xml'), out, **kw)
    assert again['cached']
    assert {p: p.stat().st_mtime_ns for p in sorted(out.rglob('*.*'))} == mtimes
    # A missing file, or other parameters, re-render over the earlier capture.
    os.remove(out / 'test' / 'gt' / '000000.exr')
    assert not synth.synthesize(synth.scene_file('gt_bounded.xml'), out, **kw)['cached']
    assert (out / 'test' / 'gt' / '000000.exr').is_file()
    changed = synth.synthesize(synth.scene_file('gt_bounded.xml'), out,
                               **dict(kw, views=4))
    assert not changed['cached'] and changed['views'] == {'train': 2, 'validation': 1, 'test': 1}
    assert len(load_dataset(out).train) == 2


def test_truck_trajectory(tmp_path):
    out = tmp_path / 'truck'
    info = synth.synthesize(synth.scene_file('gt_bounded.xml'), out, trajectory='truck',
                            views=6, res=(20, 12), spp=1, progress=False)
    assert info['trajectory'] == 'truck'
    assert all(name.startswith('truck_train_') for name in info['names']['train'])
    ds = load_dataset(out)
    assert (len(ds.train), len(ds.validation), len(ds.test)) == (4, 1, 1)
    for cam in ds.train.cameras + ds.test.cameras:
        assert np.linalg.norm(cam.center) < 1.0
        assert cam.fov_x == pytest.approx(2 * np.degrees(np.arctan(490 / 581.7877197265625)))
        assert cam.K[0, 0] == pytest.approx(cam.K[1, 1])
    # Placed upright around the origin: image-down points down the world's Y axis.
    cams = synth.truck_cameras(60, (20, 12))
    world = [c for split in cams.values() for c in split]
    assert np.mean([c.c2w[1, 1] for c in world]) < -0.9
    horizontal = np.median([np.hypot(c.center[0], c.center[2]) for c in cams['train']])
    assert horizontal == pytest.approx(synth.DEFAULT_RADIUS, rel=0.05)


def test_orbit_cameras_are_deterministic_and_outside_the_foreground():
    a = synth.orbit_cameras(40, (16, 12), seed=3)
    b = synth.orbit_cameras(40, (16, 12), seed=3)
    c = synth.orbit_cameras(40, (16, 12), seed=4)
    assert [cam.name for cam in a['test']] == [cam.name for cam in b['test']]
    np.testing.assert_array_equal(a['train'][0].c2w, b['train'][0].c2w)
    assert not np.allclose(a['train'][0].c2w, c['train'][0].c2w)
    assert {k: len(v) for k, v in a.items()} == {'train': 32, 'validation': 4, 'test': 4}
    for cam in sum(a.values(), []):
        centre = cam.center
        assert 3.0 < np.linalg.norm(centre) < 4.0 and centre[1] > 0.2


def _angles(cameras):
    """(distance, azimuth from +Z towards +X, elevation) of camera centres, degrees."""
    centres = np.array([cam.center for cam in cameras])
    distance = np.linalg.norm(centres, axis=1)
    azimuth = np.degrees(np.arctan2(centres[:, 0], centres[:, 2]))
    elevation = np.degrees(np.arcsin(centres[:, 1] / distance))
    return distance, azimuth, elevation


def _assert_on_sphere_looking_at_origin(cameras, radius):
    for cam in cameras:
        assert np.linalg.norm(cam.center) == pytest.approx(radius, rel=1e-12)
        axis = cam.c2w[:3, 2]
        np.testing.assert_allclose(axis, -cam.center / radius, atol=1e-12)  # through the origin
        assert abs(cam.c2w[1, 0]) < 1e-12                # image x horizontal: no roll
        assert cam.c2w[1, 1] < 0                         # image down points down
        assert cam.fov_x == pytest.approx(synth.DEFAULT_FOV)


@pytest.mark.parametrize('trajectory', ['hemisphere', 'arc'])
def test_new_trajectories_are_deterministic_per_seed(trajectory):
    a = synth.make_cameras(trajectory, 40, (16, 12), seed=3)
    b = synth.make_cameras(trajectory, 40, (16, 12), seed=3)
    c = synth.make_cameras(trajectory, 40, (16, 12), seed=4)
    for split in a:
        assert [cam.name for cam in a[split]] == [cam.name for cam in b[split]]
        for x, y in zip(a[split], b[split]):
            np.testing.assert_array_equal(x.c2w, y.c2w)
            np.testing.assert_array_equal(x.K, y.K)
    assert not np.allclose(a['train'][0].c2w, c['train'][0].c2w)
    assert not np.allclose(a['test'][0].c2w, c['test'][0].c2w)
    names = [cam.name for split in a.values() for cam in split]
    assert len(set(names)) == 40 and all(n.startswith(f'{trajectory}_') for n in names)
    assert {k: len(v) for k, v in a.items()} == {'train': 32, 'validation': 4, 'test': 4}


def test_hemisphere_cameras():
    radius = 3.2
    cams = synth.hemisphere_cameras(200, (16, 12), seed=1, radius=radius)
    assert {k: len(v) for k, v in cams.items()} == synth.split_counts(200)
    world = sum(cams.values(), [])
    _assert_on_sphere_looking_at_origin(world, radius)
    _, azimuth, elevation = _angles(world)
    lo, hi = synth.HEMISPHERE_ELEVATION
    assert (lo, hi) == (5.0, 75.0)
    assert elevation.min() >= lo - 1e-9 and elevation.max() <= hi + 1e-9
    # Uniform over the band's area: sin(elevation) uniform, so its mean is the middle.
    s = np.sin(np.radians(elevation))
    middle = (np.sin(np.radians(lo)) + np.sin(np.radians(hi))) / 2
    assert abs(s.mean() - middle) < 0.06
    assert abs(np.mean(elevation < 45) - 0.70) < 0.1           # 70 % of the area lies below 45
    # Azimuth covers the whole circle (every quadrant populated).
    assert set(np.floor((azimuth % 360) / 90).astype(int)) == {0, 1, 2, 3}
    # The held-out views are a random subset, not always the same indices.
    held = {c.name for c in cams['validation'] + cams['test']}
    other = synth.hemisphere_cameras(200, (16, 12), seed=2, radius=radius)
    assert held != {c.name for c in other['validation'] + other['test']}
    assert {k: len(v) for k, v in synth.hemisphere_cameras(2, (8, 6)).items()} == \
        {'train': 1, 'validation': 0, 'test': 1}


def test_arc_cameras_interpolation_and_extrapolation():
    radius = 3.7
    cams = synth.arc_cameras(40, (16, 12), seed=5, radius=radius)
    assert {k: len(v) for k, v in cams.items()} == {'train': 32, 'validation': 4, 'test': 4}
    _assert_on_sphere_looking_at_origin(sum(cams.values(), []), radius)
    lo, hi = synth.ARC_ELEVATION
    assert synth.ARC_AZIMUTH == 50 and (lo, hi) == (10, 40)
    assert synth.ARC_EXTRAPOLATION == (65, 90)
    for split in ('train', 'validation'):                      # interpolation: inside the range
        _, azimuth, elevation = _angles(cams[split])
        assert np.all(np.abs(azimuth) <= 50 + 1e-9)
        assert np.all((elevation >= lo - 1e-9) & (elevation <= hi + 1e-9))
    _, azimuth, elevation = _angles(cams['train'])
    assert azimuth.min() < -45 and azimuth.max() > 45           # the train arc spans the range
    assert np.all(np.diff(azimuth) > 0)                         # evenly spaced, in order
    _, azimuth, elevation = _angles(cams['test'])               # extrapolation: outside it
    assert np.all((np.abs(azimuth) >= 65 - 1e-9) & (np.abs(azimuth) <= 90 + 1e-9))
    assert np.any(azimuth > 0) and np.any(azimuth < 0)
    assert np.all((elevation >= lo - 1e-9) & (elevation <= hi + 1e-9))
    # Smallest counts: one view per split.
    small = synth.arc_cameras(3, (8, 6))
    assert {k: len(v) for k, v in small.items()} == {'train': 1, 'validation': 1, 'test': 1}
    for views in (1, 2):
        with pytest.raises(ValueError, match='arc trajectory needs at least 3 views'):
            synth.make_cameras('arc', views, (8, 6))


def test_make_cameras_dispatches_every_trajectory():
    assert synth.TRAJECTORIES == ('orbit', 'truck', 'hemisphere', 'arc')
    for trajectory in synth.TRAJECTORIES:
        cams = synth.make_cameras(trajectory, 10, (16, 12), seed=1)
        assert {k: len(v) for k, v in cams.items()} == synth.split_counts(10)
        assert cams['train'][0].name.startswith(f'{trajectory}_')
    np.testing.assert_array_equal(synth.make_cameras('arc', 10, (16, 12), seed=1)['test'][0].c2w,
                                  synth.arc_cameras(10, (16, 12), seed=1)['test'][0].c2w)
    np.testing.assert_array_equal(
        synth.make_cameras('hemisphere', 10, (16, 12), seed=1)['train'][0].c2w,
        synth.hemisphere_cameras(10, (16, 12), seed=1)['train'][0].c2w)


def test_split_counts():
    assert synth.split_counts(60) == {'train': 48, 'validation': 6, 'test': 6}
    assert synth.split_counts(3) == {'train': 1, 'validation': 1, 'test': 1}
    assert synth.split_counts(2) == {'train': 1, 'validation': 0, 'test': 1}
    assert synth.split_counts(1) == {'train': 1, 'validation': 0, 'test': 0}


def test_bad_inputs_raise_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match='missing.xml: scene file not found'):
        synth.synthesize(tmp_path / 'missing.xml', tmp_path / 'o')
    with pytest.raises(ValueError, match="unknown trajectory 'spiral'"):
        synth.synthesize(GARDEN, tmp_path / 'o', trajectory='spiral')
    for res in ('128', '128x', 'axb', '0x5'):
        with pytest.raises(ValueError, match='resolution'):
            synth.synthesize(GARDEN, tmp_path / 'o', res=res)
    with pytest.raises(ValueError, match='views must be a positive integer'):
        synth.synthesize(GARDEN, tmp_path / 'o', views=0)
    with pytest.raises(ValueError, match='at most 254 views'):
        synth.synthesize(GARDEN, tmp_path / 'o', trajectory='truck', views=400)
    busy = tmp_path / 'busy'
    busy.mkdir()
    (busy / 'notes.txt').write_text('mine')
    with pytest.raises(FileExistsError, match='not empty'):
        synth.synthesize(GARDEN, busy, **TINY)
    assert (busy / 'notes.txt').read_text() == 'mine'
    assert synth.parse_res('320x240') == (320, 240)


def test_command_line(tmp_path, capsys):
    out = tmp_path / 'cli'
    assert main(['synth', synth.scene_file('gt_plaza.xml'), '--out', str(out),
                 '--views', '3', '--res', '8x6', '--spp', '1', '--seed', '2']) == 0
    assert 'wrote 3 views' in capsys.readouterr().out
    assert json.loads((out / 'capture.json').read_text())['seed'] == 2
    arc = tmp_path / 'arc'
    assert main(['synth', synth.scene_file('gt_bounded.xml'), '--out', str(arc),
                 '--views', '3', '--res', '4x3', '--spp', '1', '--trajectory', 'arc']) == 0
    info = json.loads((arc / 'capture.json').read_text())
    assert info['trajectory'] == 'arc' and info['names']['test'] == ['arc_002']
    assert len(load_dataset(arc).test) == 1
    capsys.readouterr()
    assert main(['synth', synth.scene_file('gt_bounded.xml'), '--out', str(tmp_path / 'a2'),
                 '--views', '2', '--res', '4x3', '--spp', '1', '--trajectory', 'arc']) == 1
    assert re.search(r'^error: synth: .*at least 3 views', capsys.readouterr().err)
    from mi_nerfpp.commands.cli import build_parser
    args = build_parser().parse_args(['synth', GARDEN, '--out', str(out),
                                      '--trajectory', 'hemisphere'])
    assert args.trajectory == 'hemisphere'
    assert main(['synth', str(tmp_path / 'nope.xml'), '--out', str(out)]) == 1
    assert re.search(r'^error: synth: .*scene file not found', capsys.readouterr().err)
    with pytest.raises(SystemExit):
        main(['synth', GARDEN, '--out', str(out), '--res', '8by6'])
    assert 'resolution must be WxH' in capsys.readouterr().err


def test_trajectory_data_ships_with_licence():
    from importlib import resources
    folder = resources.files('mi_nerfpp') / 'trajectories'
    for name in synth.TRUCK_FILES.values():
        assert (folder / name).is_file()
    assert 'BSD' in (folder / 'LICENSE-nerfplusplus-BSD-2').read_text()


def test_scenes_are_a_top_level_folder_and_the_cache_is_per_user(monkeypatch, tmp_path):
    # The scenes a user opens are in the repository's scenes/, found from the checkout (an
    # installed wheel carries them as package data: tests/test_wheel.py).
    folder = os.path.join(
        os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), 'scenes')
    for name in ('gt_garden.xml', 'gt_plaza.xml', 'gt_bounded.xml', 'render_random.xml',
                 'insert_objects.xml', 'envmaps/forest_slope_1k.hdr', 'textures/paving.png'):
        assert os.path.isfile(os.path.join(folder, name)), name
    assert synth.scenes_dir() == folder
    assert synth.scene_file(synth.DEFAULT_SCENE) == os.path.join(folder, 'gt_garden.xml')
    monkeypatch.delenv('MI_NERFPP_CACHE', raising=False)
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'xdg'))
    assert synth.cache_dir() == str(tmp_path / 'xdg' / 'mi-nerfpp')
    monkeypatch.setenv('MI_NERFPP_CACHE', str(tmp_path / 'mine'))
    assert synth.cache_dir() == str(tmp_path / 'mine')


def test_object_masks_are_the_ground_truth_foreground(garden, tmp_path):
    import shutil
    out = tmp_path / 'g'
    shutil.copytree(garden[0], out)
    assert synth.capture.write_object_masks(str(out)) == 6
    ds = load_dataset(out)
    gt = read_exr(out / 'test' / 'gt' / '000000.exr')['fg.A']
    np.testing.assert_array_equal(ds.test.masks[0] > 127, gt > 0.5)
    assert 0 < np.mean(gt > 0.5) < 1


def test_synth_writes_object_masks_on_request(garden, tmp_path, capsys):
    import shutil
    out = tmp_path / 'g'
    shutil.copytree(garden[0], out)
    assert main(['synth', GARDEN, '--out', str(out), '--views', '6', '--res', '16x12',
                 '--spp', '4', '--object-masks']) == 0
    assert 'wrote 6 object masks' in capsys.readouterr().out
    assert load_dataset(out).train.masks is not None
