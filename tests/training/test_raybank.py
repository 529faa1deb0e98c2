"""The training ray bank (mi_nerfpp.training.raybank.RayBank): rays built per batch from the cameras and
the compact image store equal the rays precomputed for every pixel before issue 34, exactly -
origins, directions, colours and image indices - and training on them takes the same steps,
with pose refinement on and off."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.core.rays import Rays
from mi_nerfpp.training import train
from mi_nerfpp.core.arrays import owned
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.data import Camera, Split, load_dataset, pixel_rays
from mi_nerfpp.data.storage import StoredImages, store, to_float
from mi_nerfpp.training.raybank import RayBank
from mi_nerfpp.training.train import Trainer
from tests.helpers import one_thread, orbit_camera


class PrecomputedRayBank:
    """The ray bank before issue 34, as it was: every pixel's ray (float64 through
    :func:`pixel_rays`, then float32), its colour (float32) and its image index, precomputed.
    The interface is today's (``arrays``/``from_arrays`` of a dict), so a Trainer runs on it."""

    def __init__(self, split, masks=False):       # (the capture has no masks)
        o, d, c, image = [], [], [], []
        for k, (cam, img) in enumerate(zip(split.cameras, split.images)):
            h, w = img.shape[:2]
            py, px = np.mgrid[0:h, 0:w] + 0.5
            oi, di = pixel_rays(cam, px, py)
            o.append(oi)
            d.append(di)
            c.append(img.reshape(-1, 3))
            image.append(np.full(h * w, k, np.uint32))
        o, d, c = (np.concatenate(a).astype(np.float32) for a in (o, d, c))
        self.size = len(c)
        self.o = mi.Point3f(*[owned(o[:, i], mi.Float) for i in range(3)])
        self.d = mi.Vector3f(*[owned(d[:, i], mi.Float) for i in range(3)])
        self.rgb = mi.Color3f(*[owned(c[:, i], mi.Float) for i in range(3)])
        self.image = owned(np.concatenate(image), mi.UInt32)

    def arrays(self):
        return {'o': self.o, 'd': self.d, 'rgb': self.rgb, 'image': self.image}

    @classmethod
    def from_arrays(cls, arrays):
        bank = cls.__new__(cls)
        bank.o, bank.d, bank.rgb, bank.image = (arrays[k] for k in ('o', 'd', 'rgb', 'image'))
        bank.size = dr.width(bank.rgb)
        return bank

    def batch(self, index, footprint=False):       # (antialias off: no footprints)
        i = mi.UInt32(index)
        return (Rays(dr.gather(mi.Point3f, self.o, i), dr.gather(mi.Vector3f, self.d, i),
                     image=self.images(index)), dr.gather(mi.Color3f, self.rgb, i))

    def images(self, index):
        return dr.gather(mi.UInt32, self.image, mi.UInt32(index))


def cameras(n, width, height):
    """Cameras with all that K may hold: skew, fx != fy, an off-centre principal point."""
    result = []
    for i in range(n):
        cam = orbit_camera(0.7 * i, 0.1 + 0.05 * i, 2.0 + 0.1 * i, width, height)
        cam.K[0, 1] = 0.4 * (i % 2)
        cam.K[1, 1] *= 1.0 + 0.05 * i
        cam.K[:2, 2] += (1.3 * i, -0.7 * i)
        result.append(cam)
    return result


def split_of(raw, factor=1):
    """A split of the images ``raw`` (as read_stored_image returns them) stored as a dataset
    keeps them, downscaled by ``factor``, with :func:`cameras` to match."""
    h, w = raw[0].shape[:2]
    cams = [c.downscaled(factor) for c in cameras(len(raw), w, h)]
    return Split(cams, [f'{i}.png' for i in range(len(raw))],
                 StoredImages.unify([store(a, factor) for a in raw]))


def assert_same_rays(bank, reference):
    index = np.arange(reference.size, dtype=np.uint32)
    assert bank.size == reference.size
    for ours, theirs in zip(parts(bank, index), parts(reference, index)):
        np.testing.assert_array_equal(np.array(ours), np.array(theirs))
    np.testing.assert_array_equal(np.array(bank.images(index)), np.array(reference.images(index)))


def parts(bank, index):
    """``(o, d, colour, image)`` of a batch of rays."""
    rays, rgb = bank.batch(index)
    return rays.o, rays.d, rgb, rays.image


def random_levels(n, dtype, shape=(30, 40, 3), seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, np.iinfo(dtype).max + 1, shape).astype(dtype) for _ in range(n)]


STORES = {
    '8-bit': lambda: split_of(random_levels(5, np.uint8)),
    '16-bit': lambda: split_of(random_levels(4, np.uint16)),
    '8-bit downscaled 2 (box sums in 16 bits)': lambda: split_of(random_levels(3, np.uint8), 2),
    '16-bit downscaled 3': lambda: split_of(random_levels(3, np.uint16), 3),
    'EXR in float16': lambda: split_of([np.random.default_rng(i).exponential(
        2.0, (30, 40, 3)).astype(np.float32) for i in range(3)]),
    'EXR beyond float16 (float32)': lambda: split_of([np.random.default_rng(i).exponential(
        2.0, (30, 40, 3)).astype(np.float32) * 1e4 for i in range(3)]),
}


@pytest.mark.parametrize('name', list(STORES))
def test_rays_built_per_batch_equal_the_precomputed_rays_for_every_pixel(name):
    split = STORES[name]()
    expected = {'8-bit': 'uint8', '16-bit': 'uint16', 'EXR in float16': 'float16',
                'EXR beyond float16 (float32)': 'float32'}.get(name, 'uint16')
    assert split.images.dtype.name == expected
    assert_same_rays(RayBank(split), PrecomputedRayBank(split))


def test_a_batch_in_any_order_is_the_same_rays():
    split = STORES['8-bit']()
    bank, reference = RayBank(split), PrecomputedRayBank(split)
    index = np.random.default_rng(0).integers(0, bank.size, 5000).astype(np.uint32)
    for ours, theirs in zip(parts(bank, index), parts(reference, index)):
        np.testing.assert_array_equal(np.array(ours), np.array(theirs))


def test_the_step_converts_every_stored_value_as_the_split_does():
    """Every 8-bit and 16-bit level, and every box sum of 8-bit values downscaled by 2 and by
    16, converted to float by the step (Dr.Jit) and by the split's accessor (NumPy): equal."""
    cases = [(np.arange(256, dtype=np.uint8), 255.0), (np.arange(65536), 65535.0),
             (np.arange(4 * 255 + 1), 255.0 * 4), (np.arange(256 * 255 + 1), 255.0 * 256)]
    for values, scale in cases:
        stored = values.astype(np.uint8 if values.dtype == np.uint8 else np.uint16)
        pixels = np.resize(stored, 3 * 2 * ((len(values) + 5) // 6)).reshape(2, -1, 3)
        split = Split([Camera(np.eye(3), np.eye(4), pixels.shape[1], 2)], ['x.png'],
                      StoredImages([pixels], scale))
        _, rgb = RayBank(split).batch(np.arange(pixels.shape[0] * pixels.shape[1]))
        np.testing.assert_array_equal(np.array(rgb).T.reshape(pixels.shape),
                                      to_float(pixels, scale))


def test_the_bank_keeps_a_few_bytes_per_pixel():
    split = STORES['8-bit']()
    bank = RayBank(split)
    pixels = bank.size
    assert dr.width(bank.pixels) == 3 * pixels and type(bank.pixels).__name__ == 'UInt8'
    assert sum(dr.width(a) for a in bank.cameras) == len(split) * (5 + 9 + 3)


@pytest.mark.parametrize('refine', [False, True])
def test_training_takes_the_same_steps_as_on_precomputed_rays(capture, tmp_path, monkeypatch,
                                                              refine):
    """Four steps from the same seed on the per-batch rays and on the precomputed ones (one
    thread, so that both runs are deterministic): the same losses and parameters, bit for bit;
    with pose refinement from the first step, the corrected rays too (and the appearance
    transforms take the image index of each ray). The precomputed rays have no footprints
    and no pyramid: the fields look up points (``antialias`` off) at full size, as before
    issue 34; and no image layout, so the rays are drawn uniformly (``error_rays`` 0)."""
    dataset = load_dataset(capture)
    config = TrainConfig.from_options(
        iterations=4, batch_rays=512, fg_samples=8, bg_samples=8, fine_samples=8,
        checkpoint_every=0, preview_every=0, refine_poses=refine, poses_start=0.0,
        appearance=refine, antialias=False, pyramid=(), error_rays=0)
    runs = {}
    for name, bank in (('per batch', RayBank), ('precomputed', PrecomputedRayBank)):
        monkeypatch.setattr(train, 'RayBank', bank)
        with one_thread():
            trainer = Trainer(dataset, str(tmp_path / name.replace(' ', '_')), config)
            trainer.run()
        assert isinstance(trainer.rays, bank)
        runs[name] = trainer
    ours, theirs = runs['per batch'], runs['precomputed']
    # The history without the seconds: (iteration, loss, batch PSNR).
    assert [h[:1] + h[2:] for h in ours.history] == [h[:1] + h[2:] for h in theirs.history]
    assert sorted(ours.opt.keys()) == sorted(theirs.opt.keys())
    assert ('poses' in ours.opt.keys()) == refine
    for key in ours.opt.keys():
        np.testing.assert_array_equal(np.array(ours.opt[key]), np.array(theirs.opt[key]))
    if refine:   # the refinement did move the cameras
        assert np.any(np.array(ours.opt['poses'])[1:] != 0)


# ----------------------------------------------------------------------------- image pyramid

@pytest.mark.parametrize('factor', [2, 4])
@pytest.mark.parametrize('name', ['8-bit', '16-bit downscaled 3', 'EXR in float16'])
def test_a_pyramid_level_is_the_box_filtered_downsample(name, factor):
    """The rays of level F: the pixels of the images box-filtered by F (NumPy's block means of
    the float images, a remainder cropped) seen by the cameras downscaled by F - the rays a
    split downscaled by F would give, within float32 rounding."""
    from mi_nerfpp.data.images import downscale_image
    split = STORES[name]()
    small = Split([c.downscaled(factor) for c in split.cameras], split.image_paths,
                  [downscale_image(np.asarray(img, np.float64), factor).astype(np.float32)
                   for img in split.images])
    bank, reference = RayBank(split).level(factor), PrecomputedRayBank(small)
    h, w = split.images.stored[0].shape[:2]
    assert bank.size == reference.size == len(split) * (h // factor) * (w // factor)
    index = np.arange(reference.size, dtype=np.uint32)
    (o, d, rgb, _), (o_ref, d_ref, rgb_ref, _) = parts(bank, index), parts(reference, index)
    np.testing.assert_array_equal(np.array(o), np.array(o_ref))
    np.testing.assert_allclose(np.array(d), np.array(d_ref), atol=2e-7)
    np.testing.assert_allclose(np.array(rgb), np.array(rgb_ref), rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(np.array(bank.images(index)), np.array(reference.images(index)))


def test_the_coarsest_level_keeps_a_pixel():
    split = STORES['8-bit']()                      # 30 x 40 images
    bank = RayBank(split)
    assert bank.max_factor() == 16
    assert bank.level(16).size == len(split) * 1 * 2
    with pytest.raises(ValueError, match='leaves no pixel'):
        bank.level(32)


def test_footprints_are_those_mitsuba_measures_on_the_same_camera():
    """The bank's pixel footprints at levels 1 and 2 against :func:`pixel_footprint` of the ray
    differentials of a Mitsuba perspective sensor built from the camera (square pixels and no
    skew, as Mitsuba's cameras have): within 2 % over the image. The bank's is the pixel's
    solid angle at its centre, Mitsuba's a forward difference to the next pixel, which is off
    by O(1/f): 1.3 % at most here, with a focal length of 28 pixels (0.1 % at 1,000)."""
    from mi_nerfpp.data.cameras import mitsuba_sensor_dict
    from mi_nerfpp.core.geometry import pixel_footprint
    cam = orbit_camera(0.3, 0.2, 2.5, 40, 30, focal=0.7)
    cam.K[:2, 2] += (2.0, -1.5)
    img = np.zeros((30, 40, 3), np.uint8)
    split = Split([cam], ['x.png'], StoredImages([img], 255.0))
    sensor = mi.load_dict(mitsuba_sensor_dict(cam))
    for factor in (1, 2):
        bank = RayBank(split).level(factor)
        index = np.arange(bank.size, dtype=np.uint32)
        ours = np.array(bank.footprint(index))
        w, h = 40 // factor, 30 // factor
        py, px = np.mgrid[0:h, 0:w] + 0.5
        pos = mi.Point2f(mi.Float((px / w).ravel()), mi.Float((py / h).ravel()))
        ray, _ = sensor.sample_ray_differential(0.0, 0.5, pos, mi.Point2f(0.5))
        # Mitsuba's differentials are per pixel of its film (40 x 30): F of them per pixel here.
        theirs = factor * np.array(pixel_footprint(ray))
        np.testing.assert_allclose(ours, theirs, rtol=2e-2)
        assert ours.max() / ours.min() > 1.05        # the corners' pixels are narrower


def test_training_follows_the_image_pyramid(capture, tmp_path):
    """``--pyramid 0.25 0.5``: the first quarter of the run trains at 1/4 of the image size,
    the second at 1/2, the rest at full size; each level's rays are drawn from its own size."""
    dataset = load_dataset(capture)
    config = TrainConfig.from_options(
        iterations=8, batch_rays=64, fg_samples=4, bg_samples=4, fine_samples=4,
        checkpoint_every=0, preview_every=0, pyramid=(0.25, 0.5))
    trainer = Trainer(dataset, str(tmp_path / 'run'), config)
    factors = []
    while not trainer.done():
        factors.append(trainer.pyramid.level(trainer.progress()).factor)
        trainer.step()
    assert factors == [4, 4, 2, 2, 1, 1, 1, 1]
    assert trainer.pyramid.level(trainer.progress()).size == trainer.rays.size
    h, w = trainer.train.images.stored[0].shape[:2]
    assert trainer.rays.level(4).size == len(trainer.train) * (h // 4) * (w // 4)


def test_each_new_phase_or_level_gets_a_fresh_frozen_step(capture, tmp_path):
    """The frozen step is made anew when the Python values it is recorded for change (here
    the pyramid's level), and kept while they stay (issue 49, item 5)."""
    dataset = load_dataset(capture)
    config = TrainConfig.from_options(
        iterations=4, batch_rays=32, fg_samples=4, bg_samples=4, fine_samples=4,
        grid_levels=(4, 8), checkpoint_every=0, preview_every=0, pyramid=(0.5,))
    trainer = Trainer(dataset, str(tmp_path / 'run'), config)
    seen = []
    while not trainer.done():
        trainer.step()
        seen.append((trainer._recorded[2], id(trainer._compute)))
    assert [factor for factor, _ in seen] == [2, 2, 1, 1]
    assert seen[0][1] == seen[1][1] != seen[2][1] == seen[3][1]


def test_a_pyramid_that_moves_level_after_many_replays_trains(capture, tmp_path):
    """--pyramid 0.5 0.6 0.7 0.8 on 32x24 images crashed the process (SIGSEGV) at the move to
    the next level, in Dr.Jit's frozen step re-recorded after six replays (issue 49, item 5):
    run in a child process, it ends with status 0. (Since issue 63 --pyramid takes at most
    three fractions: 0.6 0.7 0.8 moves level after the same six replays.)"""
    import subprocess
    import sys
    out = tmp_path / 'run'
    r = subprocess.run(
        [sys.executable, '-m', 'mi_nerfpp', 'optimize', capture, '--out', str(out),
         '--iterations', '10', '--samples', '4', '4', '4', '--grid-levels', '4', '8',
         '--preview-every', '0', '--checkpoint-every', '0', '--pyramid', '0.6', '0.7', '0.8'],
        capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, (r.returncode, r.stderr[-2000:])
    assert (out / 'model.npz').exists()
