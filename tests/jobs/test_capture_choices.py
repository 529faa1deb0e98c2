"""What a run chooses from the capture when the options leave it open (issue 34): the
resolution (the images' own unless they do not fit in memory, mi_nerfpp.core.budget) and the time
budget (mi_nerfpp.training.config.default_minutes), each announced in one line and respected."""
import re

import numpy as np
import pytest

from mi_nerfpp.core import budget
from mi_nerfpp.core.arrays import llvm_backend
from mi_nerfpp.jobs import run
from mi_nerfpp.training import choices
from mi_nerfpp.training.config import (DEFAULT_JOB_MINUTES, DEFAULT_MINUTES_RANGE, TrainConfig,
                                       default_minutes)
from mi_nerfpp.data import DatasetError, load_dataset
from mi_nerfpp.core.model import NeRFPPModel
from tests.jobs.test_run import Recorder


def test_the_default_capture_keeps_its_minutes_and_larger_ones_get_more_within_bounds():
    from mi_nerfpp.data.synth.capture import DEFAULT_RES, DEFAULT_TRAJECTORY, DEFAULT_VIEWS
    from mi_nerfpp.data.synth.trajectories import make_cameras
    train = make_cameras(DEFAULT_TRAJECTORY, DEFAULT_VIEWS, DEFAULT_RES)['train']
    pixels = len(train) * DEFAULT_RES[0] * DEFAULT_RES[1]
    assert default_minutes(pixels) == DEFAULT_JOB_MINUTES == 10
    assert default_minutes(4 * pixels) == 2 * DEFAULT_JOB_MINUTES      # the square root
    low, high = DEFAULT_MINUTES_RANGE
    assert default_minutes(118 * 1200 * 800) == high == 60         # the issue's photo set
    assert default_minutes(100 * 512 * 384) == 58
    assert default_minutes(1) == default_minutes(0) == low == 2
    sizes = np.geomspace(1e3, 1e9, 200).astype(int)
    minutes = [default_minutes(n) for n in sizes]
    assert minutes == sorted(minutes) and all(m == round(m) for m in minutes)


def notices_of(capture, tmp_path, **options):
    observer = Recorder()
    inputs = run.prepare(capture, TrainConfig.from_options(**options), str(tmp_path / 'run'),
                         observer=observer)
    return inputs, observer.of('notice')


def test_the_sparse_resolution_follows_the_pixel_footprint():
    # Twice the finest level, a multiple of the occupancy cells, when its cells (2/R) span two
    # pixels.
    assert budget.sparse_resolution(0.0018, 128, 64) == 256        # gt_plaza at 512x384
    assert budget.sparse_resolution(2 / 256 / 2, 128, 64) == 256   # exactly two pixels
    assert budget.sparse_resolution(2 / 256 / 2 * 1.01, 128, 64) is None
    assert budget.sparse_resolution(0.001, 100, 64) == 256          # 200 -> a multiple of 64
    assert budget.sparse_resolution(0.01, 8, 4) == 16


def test_the_sparse_level_is_chosen_from_the_capture_and_announced(capture, tmp_path):
    footprint = choices.centre_footprint(load_dataset(capture).train.cameras)
    cameras = load_dataset(capture).train.cameras
    assert footprint == pytest.approx(np.median(
        [np.linalg.norm(c.c2w[:3, 3]) / c.K[0, 0] for c in cameras]))
    # --occupancy-res 4: the level is twice the finest dense level; a finest
    # level whose doubled cells span two pixels gets one, one four times finer does not. A
    # finest level above one texel an occupancy cell (here 8 and more) whose cells span two
    # pixels goes into bricks itself.
    fits = max(int(1 / (2 * footprint)) // 2 * 2, 2)
    for finest, chosen in ((fits, 2 * fits), (4 * fits, None)):
        inputs, notices = notices_of(capture, tmp_path / str(finest), grid_levels=(4, finest),
                                     occupancy_res=4, iterations=1)
        spans = 2 / finest / footprint         # pixels a cell of the finest level spans
        moved = (finest,) if finest % 4 == 0 and finest > 4 and spans >= 2 else ()
        line = [n for n in notices if 'sparse foreground level' in n][0]
        assert inputs.config.model.grid_sparse == moved + ((chosen,) if chosen else ())
        assert inputs.config.model.grid_levels == ((4,) if moved else (4, finest))
        # The background's finest goes into bricks with the foreground's (colatitude cells of
        # the occupancy: 4 here).
        assert inputs.config.model.levels('inverted_sphere') == ((4,) if moved else (4, finest))
        assert inputs.config.model.bg_grid_sparse == moved
        if moved:
            assert f'foreground level {finest}³ stored in bricks where the surfaces are, the ' \
                   f'coarser 4 dense; --grid-sparse alone to keep it dense' in notices
            assert f'background level {finest} stored in bricks where the training rays take ' \
                   f'their colour from, the coarser 4 dense; --bg-grid-sparse alone to keep it ' \
                   f'dense' in notices
        if chosen:
            assert line.startswith(f'sparse foreground level {chosen}³ (a training pixel is '
                                   f'{footprint:.4f} of the unit ball wide at the centre')
        else:
            assert line.startswith(f'no {"finer " if moved else ""}sparse foreground level: a '
                                   f'training pixel is {footprint:.4f}')
    # Told: kept as told (none, or a resolution); the background's bricks come with the
    # foreground's choice, or as told.
    inputs, notices = notices_of(capture, tmp_path / 'told', grid_sparse=(), iterations=1)
    assert inputs.config.model.grid_sparse == () and not any('sparse' in n for n in notices)
    assert inputs.config.model.bg_grid_sparse == ()
    inputs, notices = notices_of(capture, tmp_path / 'bg', grid_levels=(4, fits),
                                 occupancy_res=4, bg_grid_sparse=(), iterations=1)
    assert inputs.config.model.levels('inverted_sphere') == (4, fits)
    assert inputs.config.model.bg_grid_sparse == () and not any('background' in n
                                                                for n in notices)


def test_the_finest_dense_level_goes_into_bricks_where_it_can():
    """The finest foreground level moves into bricks when a coarser one stays dense and it is
    a whole multiple of the occupancy cells above one texel a cell; the background keeps its
    dense levels (it took the foreground's before)."""
    moved, finest = choices.finest_in_bricks(TrainConfig())       # 32 128, occupancy 64
    assert finest == 128
    assert (moved.model.grid_levels, moved.model.bg_grid_levels) == ((32,), (32, 128))
    given = TrainConfig.from_options(grid_levels=(16, 64, 192), bg_grid_levels=(8, 24),
                                     occupancy_res=32)
    moved, finest = choices.finest_in_bricks(given)
    assert finest == 192 and moved.model.levels('inverted_sphere') == (8, 24)
    assert moved.model.grid_levels == (16, 64)
    for options in (dict(grid_levels=(128,)),                           # nothing stays dense
                    dict(grid_levels=(32, 96)),                          # not a multiple of 64
                    dict(grid_levels=(32, 128), occupancy_res=128)):    # one texel a cell
        config = TrainConfig.from_options(**options)
        assert choices.finest_in_bricks(config) == (config, None)


def test_the_background_finest_level_goes_into_bricks_where_it_can():
    """The background's finest level moves into bricks where a coarser one stays dense and it
    is a whole multiple of the occupancy's colatitude cells above one texel a cell, unless its
    sparse levels are given."""
    moved, finest = choices.background_in_bricks(TrainConfig())   # 32 128, occupancy 64: 32
    assert finest == 128
    assert (moved.model.levels('inverted_sphere'), moved.model.bg_grid_sparse) == ((32,), (128,))
    assert moved.model.grid_levels == (32, 128)
    for options in (dict(bg_grid_levels=(128,)),                        # nothing stays dense
                    dict(bg_grid_levels=(32, 80)),                       # not a multiple of 32
                    dict(bg_grid_levels=(16, 32)),                       # one texel a cell
                    dict(bg_grid_sparse=()), dict(bg_grid_sparse=(256,)),   # given
                    dict(bg_field='nerf')):
        config = TrainConfig.from_options(**options)
        assert choices.background_in_bricks(config) == (config, None)


def test_a_resumed_run_keeps_its_levels_and_its_allocation_schedule(capture, tmp_path):
    """A run resumed with the options left at their defaults takes the dense and sparse
    levels it was trained with (the chooser moved one, or had none to move) and its own
    --sparse-at / --sparse-entries, not today's defaults."""
    default = TrainConfig()
    trained = TrainConfig.from_options(grid_levels=(32,), bg_grid_levels=(32, 128),
                                       grid_sparse=(128,), bg_grid_sparse=(), sparse_at=(0.1, 0.3),
                                       sparse_entries=4_000_000).to_dict()
    config = choices.from_capture(default, load_dataset(capture), trained)
    assert (config.model.grid_levels, config.model.bg_grid_levels, config.model.grid_sparse) \
        == ((32,), (32, 128), (128,))
    assert (config.schedule.sparse_at, config.schedule.sparse_entries) == ((0.1, 0.3), 4_000_000)
    assert config.model.bg_grid_sparse == ()        # (its background dense, as trained)
    before = TrainConfig.from_options(grid_sparse=(256,), bg_grid_sparse=()).to_dict()  # older
    config = choices.from_capture(default, load_dataset(capture), before)
    assert (config.model.grid_levels, config.model.levels('inverted_sphere'),
            config.model.grid_sparse, config.model.bg_grid_sparse) == \
        ((32, 128), (32, 128), (256,), ())
    # Trained with the background's finest level in bricks: kept.
    today = TrainConfig.from_options(grid_levels=(32,), bg_grid_levels=(32,), grid_sparse=(128,),
                                     bg_grid_sparse=(128,)).to_dict()
    config = choices.from_capture(default, load_dataset(capture), today)
    assert (config.model.grid_levels, config.model.levels('inverted_sphere'),
            config.model.grid_sparse, config.model.bg_grid_sparse) == \
        ((32,), (32,), (128,), (128,))
    # Given on the command line: kept.
    told = TrainConfig.from_options(sparse_at=(0.2,), sparse_entries=1000)
    config = choices.from_capture(told, load_dataset(capture), trained)
    assert (config.schedule.sparse_at, config.schedule.sparse_entries) == ((0.2,), 1000)


def test_rays_are_uniform_unless_told_and_a_resumed_run_draws_as_it_did(capture, tmp_path):
    inputs, notices = notices_of(capture, tmp_path / 'default', iterations=1)
    assert inputs.config.schedule.error_rays == 0.0
    assert not any('training rays' in line for line in notices)
    assert run.start(inputs).error_map is None
    inputs, _ = notices_of(capture, tmp_path / 'told', error_rays=0.8, iterations=1)
    assert inputs.config.schedule.error_rays == 0.8
    trainer = run.start(inputs)
    assert trainer.error_map is not None
    trainer.run()
    inputs.lock.release()
    # Resumed without the option: the stored share, not today's default.
    resumed = run.prepare(capture, TrainConfig.from_options(iterations=2),
                          str(tmp_path / 'told' / 'run'), resume=True)
    assert resumed.config.schedule.error_rays == 0.8
    resumed.lock.release()


def test_the_chosen_resolution_and_budget_are_announced_and_respected(capture, tmp_path):
    inputs, notices = notices_of(capture, tmp_path)
    n = len(inputs.dataset.train)
    # (32x24: a cell of the 128 level spans 0.7 pixels, so it stays dense)
    resolution, sparse_line, schedule_line = notices
    assert sparse_line.startswith('no sparse foreground level: a training pixel is ')
    assert sparse_line.endswith('; --grid-sparse RES to add one')
    model = inputs.config.model
    assert (model.grid_levels, model.levels('inverted_sphere'), model.grid_sparse) == (
        (32, 128), (32, 128), ())
    assert inputs.config.schedule.error_rays == 0.0
    assert resolution.startswith(f"training at the images' own resolution, {n} views of "
                                 f'32x24 (images ')
    assert resolution.endswith('available; --downscale to shrink)')
    minutes = default_minutes(n * 32 * 24)
    assert schedule_line == (f'training for {minutes:g} minutes (chosen from {n} views of 32x24; '
                      f'--minutes to change)')
    config = inputs.config
    assert config.data.downscale == 1 and inputs.dataset.downscale == 1
    assert (config.schedule.minutes, config.schedule.iterations) == (minutes, None)
    trainer = run.start(inputs)
    assert trainer.rays.size == n * 32 * 24                      # every pixel, full size
    assert trainer.cfg.schedule.minutes == minutes
    trainer.elapsed = 60 * minutes - 0.01
    assert not trainer.done()
    trainer.elapsed = 60 * minutes
    assert trainer.done()


def test_a_trainer_given_no_budget_takes_the_default_one(capture, tmp_path):
    from mi_nerfpp.training.train import Trainer
    dataset = load_dataset(capture)
    trainer = Trainer(dataset, str(tmp_path), TrainConfig())
    pixels = len(dataset.train) * 32 * 24
    assert trainer.cfg.schedule.minutes == default_minutes(pixels)
    assert trainer.cfg.schedule.iterations is None


@pytest.mark.parametrize('options, downscale, schedule', [
    ({'minutes': 3.5, 'downscale': 2, 'grid_sparse': (), 'error_rays': 0.0,
      'appearance': False, 'refine_poses': True}, 2, (None, 3.5)),
    ({'iterations': 7, 'downscale': 1, 'grid_sparse': (16,), 'occupancy_res': 4,
      'error_rays': 0.5, 'appearance': True, 'refine_poses': False}, 1, (7, None))])
def test_given_options_are_kept_and_nothing_is_announced(capture, tmp_path, options, downscale,
                                                        schedule):
    inputs, notices = notices_of(capture, tmp_path, **options)
    assert notices == []
    assert inputs.config.data.downscale == inputs.dataset.downscale == downscale
    assert inputs.dataset.train.cameras[0].width == 32 // downscale
    assert (inputs.config.schedule.iterations, inputs.config.schedule.minutes) == schedule
    assert inputs.config.model.grid_sparse == options['grid_sparse']
    assert inputs.config.schedule.error_rays == options['error_rays']
    assert inputs.config.model.appearance is options['appearance']
    assert inputs.config.model.refine_poses is options['refine_poses']


def test_photos_learn_their_exposure_and_poses_unless_rendered_or_told_and_a_resumed_run_keeps_them(
        capture, tmp_path):
    import shutil
    from mi_nerfpp.data.synth.capture import CAPTURE_FILE
    # The test capture is rendered (its capture.json, as synth writes one): off, nothing said.
    inputs, notices = notices_of(capture, tmp_path / 'rendered', iterations=1)
    assert inputs.config.model.appearance is False and inputs.config.model.refine_poses is False
    assert not [line for line in notices if 'appearance' in line or 'pose' in line]
    trainer = run.start(inputs)
    assert trainer.model.appearance is None and trainer.model.poses is None
    inputs.lock.release()
    # The same images as photos (a NeRF++-layout folder without capture.json): on, said.
    photos = str(tmp_path / 'photos_data')
    shutil.copytree(capture, photos, ignore=shutil.ignore_patterns(CAPTURE_FILE))
    inputs, notices = notices_of(photos, tmp_path / 'photos', iterations=1)
    assert inputs.config.model.appearance is True and inputs.config.model.refine_poses is True
    assert [line for line in notices if line.startswith('per-photo appearance on: ')]
    assert [line for line in notices if line.startswith('pose refinement on: ')]
    trainer = run.start(inputs)
    assert trainer.model.appearance_images == len(inputs.dataset.train)
    assert trainer.model.pose_images == len(inputs.dataset.train)
    trainer.run()
    inputs.lock.release()
    # A resumed run keeps what it chose.
    resumed = run.prepare(photos, TrainConfig.from_options(iterations=2),
                          str(tmp_path / 'photos' / 'run'), resume=True)
    assert resumed.config.model.appearance is True and resumed.config.model.refine_poses is True
    resumed.lock.release()
    # A Trainer made directly chooses as the command does.
    from mi_nerfpp.training.train import Trainer
    direct = Trainer(load_dataset(photos), str(tmp_path / 'direct'),
                     TrainConfig.from_options(iterations=1))
    assert direct.model.appearance is not None and direct.model.poses is not None
    # Told: --no-appearance --no-refine-poses on photos.
    inputs, notices = notices_of(photos, tmp_path / 'told', iterations=1, appearance=False,
                                 refine_poses=False)
    assert inputs.config.model.appearance is False and inputs.config.model.refine_poses is False
    assert not [line for line in notices if 'appearance' in line or 'pose' in line]
    inputs.lock.release()


def test_a_capture_too_large_for_the_memory_is_downscaled_and_the_message_says_why(
        capture, tmp_path, monkeypatch):
    dataset = load_dataset(capture)
    n, held_out = len(dataset.train), len(dataset.validation) + len(dataset.test)
    # 8-bit images, the training ones counted twice: at 32x24 3 bytes per pixel, at 16x12
    # 6 (exact box sums): half the memory.
    full = (2 * n + held_out) * 32 * 24 * 3
    step = budget.plan(TrainConfig().sizing()).total
    available = int((step + 0.75 * full) / budget.USABLE_FRACTION) + 1
    monkeypatch.setattr(budget, 'available_bytes', lambda: available)
    inputs, (resolution, minutes) = notices_of(capture, tmp_path, grid_sparse=(),
                                               error_rays=0.0)
    size = run.bytes_text
    assert resolution == (
        f'downscale 2 chosen: {n} views of 16x12, because at their own 32x24 the images would '
        f'take {size(full)} + training ~{size(step)}, more than the '
        f'{size(budget.USABLE_FRACTION * available)} usable of {size(available)} available '
        f'(--downscale to choose)')
    assert inputs.config.data.downscale == inputs.dataset.downscale == 2
    assert minutes.startswith(f'training for {default_minutes(n * 16 * 12):g} minutes (chosen '
                             f'from {n} views of 16x12;')
    assert run.start(inputs).rays.size == n * 16 * 12           # trained at what it chose
    # Memory for the images at their own size: kept.
    monkeypatch.setattr(budget, 'available_bytes', lambda: available + full)
    assert notices_of(capture, tmp_path)[0].config.data.downscale == 1
    # No memory left for any size: refused, unless a downscale is given.
    monkeypatch.setattr(budget, 'available_bytes', lambda: step)
    with pytest.raises(DatasetError, match=re.escape('choose a --downscale to train anyway')):
        notices_of(capture, tmp_path)
    assert notices_of(capture, tmp_path, downscale=1)[0].dataset.downscale == 1


@pytest.mark.parametrize('options', [{}, {'grid_levels': (16, 64), 'bg_s_ratio': (0.5,)},
                                     {'model': 'nerf'}, {'bg_field': 'nerf'}])
def test_the_estimate_counts_the_parameters_of_the_model(options):
    import drjit as dr
    config = TrainConfig.from_options(**options)
    m = config.model
    model = NeRFPPModel.create(background=m.kind == 'nerfpp',
                               fg_config=config.field_config(m.field, 'ball'),
                               bg_config=config.field_config(m.bg_field or m.field,
                                                             'inverted_sphere'))
    actual = sum(dr.width(v) for v in model.parameters().values())
    plan = budget.plan(config.sizing())
    estimate = plan.entries['grids']
    assert estimate <= actual < estimate * 1.001 + 200_000     # the colour MLPs, an MLP field
    threads = dr.thread_count() if llvm_backend() else 0   # no per-thread copies on CUDA
    assert plan.machine.threads == threads
    assert plan.total == (
        budget.BASE_BYTES + 4 * estimate * (budget.PARAMETER_COPIES + threads)
        + budget.OCCUPANCY_BYTES_PER_CELL * plan.entries['occupancy']
        + budget.TRAIN_BYTES_PER_SAMPLE * config.schedule.batch_rays * config.samples_per_ray)


def test_the_available_memory_is_what_the_machine_has():
    with open('/proc/meminfo') as f:
        total = next(int(line.split()[1]) * 1024 for line in f if line.startswith('MemTotal'))
    assert 0 < budget.available_bytes() <= total
    assert budget.images_budget(10, available=1000) == 790
    assert budget.images_budget(10 ** 9, available=1000) == 0


def test_a_resumed_run_keeps_the_resolution_it_was_trained_at(capture, tmp_path, monkeypatch):
    out = str(tmp_path / 'run')
    tiny = dict(iterations=2, batch_rays=64, fg_samples=4, bg_samples=4, fine_samples=4,
                checkpoint_every=0, preview_every=0)
    inputs = run.prepare(capture, TrainConfig.from_options(**tiny), out)
    assert inputs.config.data.downscale == 1
    run.train(run.start(inputs))
    # Too little memory now for the images at any size: a new run is refused, the resumed one
    # goes on as it was trained.
    needed = budget.plan(inputs.config.sizing()).total
    monkeypatch.setattr(budget, 'available_bytes', lambda: needed + 1000)
    observer = Recorder()
    config = TrainConfig.from_options(**dict(tiny, iterations=3))
    resumed = run.prepare(capture, config, out, resume=True, observer=observer)
    assert observer.of('notice') == []
    assert resumed.config.data.downscale == resumed.dataset.downscale == 1
    trainer = run.start(resumed, resume=True)
    assert trainer.iteration == 2 and trainer.rays.size == len(resumed.dataset.train) * 32 * 24
    with pytest.raises(DatasetError, match='choose a --downscale'):
        run.prepare(capture, config, str(tmp_path / 'new'), observer=observer)
