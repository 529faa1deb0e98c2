"""Options: every bad value is refused where it is read, with one line naming the option; the
options that size arrays are checked against Dr.Jit's 2^32-entry arrays and the memory before
Dr.Jit sees them, naming the largest value that fits; the command-line boundary turns any
error into one line (the traceback only with --debug)."""
import os
import re

import pytest

from mi_nerfpp.commands.arguments import THREADS_PER_CORE, max_threads
from mi_nerfpp.core import budget
from mi_nerfpp.training.config import MAX_SEED, TrainConfig
from tests.robustness.common import TINY, one_clear_line, run_cli

GIB = 1 << 30


@pytest.mark.parametrize('option, message', [
    (['--batch-rays', '0'], '--batch-rays must be at least 1, got 0'),
    (['--downscale', '0'], '--downscale must be at least 1, got 0'),
    (['--samples', '0', '0', '0'], '--samples must be at least 1, got 0'),
    (['--grid-levels', '0'], '--grid-levels must be one or more resolutions of at least 2'),
    (['--lr-grid', 'nan'], '--lr-grid must be a positive finite number, got nan'),
    (['--lr-mlp', '-0.01'], '--lr-mlp must be a positive finite number, got -0.01'),
    (['--checkpoint-every', '-5'], '--checkpoint-every must be 0 or more, got -5'),
    (['--minutes', '-1'], '--minutes must be a positive number of minutes, got -1.0'),
    (['--minutes', 'nan'], '--minutes must be a positive number of minutes, got nan'),
    (['--adam-beta2', '1'], '--adam-beta2 must be a number in (0, 1), got 1.0'),
    (['--fg-warp', '1'], '--fg-warp must be a radius in [0, 1), got 1.0'),
    (['--bg-s-ratio', '0'], '--bg-s-ratio must be one number in (0, 1], or one per background grid level, got 0.0'),
    (['--bg-s-ratio', '0.5', '0.5', '0.5'], 'one per background grid level, got 0.5 0.5 0.5'),
    (['--bg-grid-levels', '1'], '--bg-grid-levels must be one or more resolutions of at least 2'),
    # The seed seeds the background field with seed + 1, in Dr.Jit's 64-bit generators.
    (['--seed', str(2 ** 64)], f'--seed must be a whole number from 0 to {2 ** 64 - 2} (2^64 - 2), '
                               f'got {2 ** 64}'),
    (['--seed', '-1'], '--seed must be a whole number from 0 to 18446744073709551614'),
    (['--color-layers', '100000'], '--color-layers must be at most 64 (every layer is traced '
                                   'into the training kernels), got 100000'),
    (['--dir-octaves', '64'], '--dir-octaves must be 0 or more and at most 24 (frequencies 2^k '
                              'beyond float32 precision are noise), got 64'),
    # 1/256 of the images: each ray summed 256 x 256 stored pixels in the step's kernel, which
    # took minutes to compile (issue 63).
    (['--pyramid', '0.1', '0.2', '0.3', '0.4', '0.5', '0.6', '0.7', '0.8'],
     '--pyramid must be at most 3 fractions (the first level averages 2^n x 2^n stored pixels '
     'per ray inside the training step, whose compilation takes minutes beyond 8 x 8), got '
     '0.1 0.2 0.3 0.4 0.5 0.6 0.7 0.8'),
    # Crashed the process (SIGSEGV) once the corrections started (issue 49, item 5).
    (['--refine-poses', '--lr-poses', '1e10'], '--lr-poses must be at most 1 (an Adam step '
                                               'moves each camera correction by about the '
                                               'learning rate'),
])
def test_bad_optimize_options_are_refused(capsys, tmp_path, option, message):
    status, _, err = run_cli(capsys, 'optimize', tmp_path, '--out', tmp_path / 'run', *option)
    assert status == 1
    assert message in one_clear_line(err)
    assert not (tmp_path / 'run').exists()


def test_largest_seed_trains(capture, tmp_path, capsys):
    status, _, _ = run_cli(capsys, 'optimize', capture, '--out', tmp_path / 'run', *TINY,
                           '--iterations', '1', '--seed', MAX_SEED)
    assert status == 0


@pytest.mark.parametrize('option, flag, values', [
    (['--batch-rays', '200000000'], '--batch-rays 200000000', {'batch_rays': 200_000_000}),
    (['--grid-levels', '2048'], '--grid-levels 2048', {'grid_levels': (2048,)}),
    (['--occupancy-res', '4096'], '--occupancy-res 4096', {'occupancy_res': 4096}),
    (['--grid-channels', '100000'], '--grid-channels 100000', {'grid_channels': 100_000}),
    (['--bg-grid-levels', '4000'], '--bg-grid-levels 4000', {'bg_grid_levels': (4000,)}),
    # Blamed --grid-levels 32 128 (issue 49, item 6): the planes are sized on their own.
    (['--grid-planes', '100000'], '--grid-planes 100000', {'grid_planes': (100_000,)}),
    (['--bg-grid-planes', '60000'], '--bg-grid-planes 60000', {'bg_grid_planes': (60_000,)}),
    # Printed Dr.Jit's jit_var_counter text (issue 49, item 5).
    (['--color-width', '1000000000'], '--color-width 1000000000',
     {'color_width': 1_000_000_000}),
])
def test_options_that_size_arrays_name_the_largest_value_that_fits(capsys, tmp_path, option,
                                                                   flag, values):
    """Refused before Dr.Jit sees them (no jit_var_counter text), naming the option, why, and
    the largest value that fits; that value does fit and the next one does not."""
    status, _, err = run_cli(capsys, 'optimize', tmp_path, '--out', tmp_path / 'run', *option)
    line = one_clear_line(err)
    assert status == 1 and line.startswith(f'error: optimize: {flag} is too large: ')
    assert 'more than one Dr.Jit array holds (2^32 - 1 entries)' in line
    assert 'jit_var' not in line and 'invalid field config' not in line
    best = int(re.search(r'(?:at most|at resolution) ([\d,]+)', line).group(1).replace(',', ''))
    (name, value), = values.items()
    config = TrainConfig.from_options(**values)
    machine = budget.Machine.here()
    assert budget.largest_that_fits(config.sizing(), name, machine) == best and best >= 2
    size = (lambda v: (v,)) if isinstance(value, tuple) else (lambda v: v)
    assert budget.plan(config.replace(**{name: size(best)}).sizing(), machine).exceeded is None
    assert budget.plan(config.replace(**{name: size(best + 1)}).sizing(),
                       machine).exceeded is not None
    assert not (tmp_path / 'run').exists()


def test_samples_beyond_what_a_render_holds_are_refused(capsys, tmp_path):
    """--samples 8 8 1000000 took 7.6 GB and then failed with 'unsupported operand': renders of
    the model take the samples of a volume for a chunk of the integrator's rays at a time,
    within the integrator's entries per array - the same rule its render applies, so that a
    run is not trained to fail at its evaluation."""
    from mi_nerfpp.core.budget import MAX_CHUNK_ENTRIES, check_chunk_sizes
    status, _, err = run_cli(capsys, 'optimize', tmp_path, '--out', tmp_path / 'run',
                             '--samples', '8', '8', '1000000', '--batch-rays', '32')
    line = one_clear_line(err)
    per_volume = MAX_CHUNK_ENTRIES // budget.RENDER_CHUNK_RAYS
    assert status == 1 and line == (
        f'error: optimize: --samples 8 8 1000000 are too many: renders of the model take '
        f'1,000,008 samples per ray of a volume (coarse and fine) for 32,768 rays at a time, '
        f'more than the nerfpp integrator\'s {MAX_CHUNK_ENTRIES:,} entries per array; at most '
        f'{per_volume:,} samples per ray of a volume fit')
    assert not (tmp_path / 'run').exists()
    # At the boundary the config and the integrator agree: what one accepts the other renders.
    chunk = budget.RENDER_CHUNK_RAYS
    for fg, bg, fine in ((per_volume - 8, 8, 8), (8, per_volume - 8, 8), (1, 1, per_volume - 1)):
        config = TrainConfig.from_options(fg_samples=fg, bg_samples=bg, fine_samples=fine,
                                          batch_rays=32)
        assert budget.plan(config.sizing()).chunk_error is None
        check_chunk_sizes(chunk, config.render_sampling, 1, 1)
        for bigger in ((fg + 1, bg, fine), (fg, bg + 1, fine), (fg, bg, fine + 1)):
            config = TrainConfig.from_options(fg_samples=bigger[0], bg_samples=bigger[1],
                                              fine_samples=bigger[2], batch_rays=32)
            if max(bigger[0], bigger[1]) + bigger[2] <= per_volume:
                continue
            with pytest.raises(ValueError, match=r'^--samples .* are too many: renders'):
                budget.check(budget.plan(config.sizing()))
            with pytest.raises(ValueError, match=r'^nerfpp: parameter'):
                check_chunk_sizes(chunk, config.render_sampling, 1, 1)


def test_limits_against_a_memory_budget_in_closed_form():
    """The plan is a sum of entries x bytes per entry: on a machine of 4 GiB with 2 threads
    the default run fits, and the largest --batch-rays is what the memory leaves after the
    process, the grids and the occupancy grids, over 48 samples per ray x
    TRAIN_BYTES_PER_SAMPLE."""
    machine = budget.Machine(memory=4 * GIB, available=3 * GIB, threads=2)
    config = TrainConfig()
    grid_entries = (32 ** 3 + 128 ** 3) * 4 + (16 * 32 * 64 + 64 * 128 * 256) * 4
    # Each volume's colour MLP: 2 levels x 3 feature channels and the direction's 3 x (1 + 2 x 2)
    # encoded values in, with a bias, to 32 hidden units, and 32 + 1 to RGB.
    grid_entries += 2 * ((2 * 3 + 3 * 5 + 1) * 32 + (32 + 1) * 3)
    occupancy_cells = 64 ** 3 + 16 * 32 * 64
    per_entry = 4 * (budget.PARAMETER_COPIES + 2)
    fixed = (budget.BASE_BYTES + grid_entries * per_entry
             + occupancy_cells * budget.OCCUPANCY_BYTES_PER_CELL)
    plan = budget.plan(config.sizing(), machine)
    assert plan.entries == {'grids': grid_entries, 'occupancy': occupancy_cells,
                            'samples': config.schedule.batch_rays * 48}
    assert plan.bytes == {'process': budget.BASE_BYTES, 'grids': grid_entries * per_entry,
                          'occupancy': occupancy_cells * 16,
                          'step': config.schedule.batch_rays * 48
                          * budget.TRAIN_BYTES_PER_SAMPLE}
    assert plan.exceeded is None and plan.total == sum(plan.bytes.values())
    assert plan.images == int(0.8 * 3 * GIB) - plan.total
    budget.check(plan)
    best = (4 * GIB - fixed) // (48 * budget.TRAIN_BYTES_PER_SAMPLE)
    assert budget.largest_that_fits(config.sizing(), 'batch_rays', machine) == best
    big = config.replace(batch_rays=best + 1)
    big_plan = budget.plan(big.sizing(), machine)
    assert big_plan.exceeded[0] == 'batch_rays' and big_plan.largest == best
    with pytest.raises(ValueError) as e:
        budget.check(big_plan)
    step = (best + 1) * 48 * budget.TRAIN_BYTES_PER_SAMPLE
    text = budget.memory_text
    assert str(e.value) == (
        f'--batch-rays {best + 1} is too large: a run takes about '
        f'{text(fixed + step)} (process {text(budget.BASE_BYTES)}, grids and MLPs '
        f'{text(grid_entries * per_entry)}, occupancy {text(occupancy_cells * 16)}, training '
        f'step {text(step)}), more than this machine\'s 4 GiB; at most {best:,} fits')
    # More samples per ray with few rays: the samples are blamed, with the largest count
    # (within what the integrator's chunks hold).
    many = config.replace(batch_rays=64, fine_samples=1000)
    small = budget.Machine(memory=budget.BASE_BYTES + GIB // 4, available=GIB, threads=2)
    with pytest.raises(ValueError, match=r'^--samples 16 16 1000 are too many: .*at most '
                                         r'[\d,]+ samples per ray .* fit with --batch-rays 64'):
        budget.check(budget.plan(many.sizing(), small))


def test_a_wide_colour_mlp_is_sized_by_its_width_and_layers():
    """A step's bytes per sample grow with the colour MLP's hidden units beyond the measured
    32 x 1, and its weights count with the grids': on a 4 GiB machine a wide, deep MLP is
    refused naming --color-width and the largest width that fits, which does fit."""
    machine = budget.Machine(memory=4 * GIB, available=3 * GIB, threads=2)
    narrow = budget.plan(TrainConfig().sizing(), machine)
    wide = budget.plan(TrainConfig.from_options(color_width=64, color_layers=2).sizing(),
                       machine)
    assert wide.bytes['step'] == 4 * narrow.bytes['step']
    assert wide.entries['grids'] > narrow.entries['grids']
    config = TrainConfig.from_options(color_width=4096, color_layers=8)
    plan = budget.plan(config.sizing(), machine)
    assert plan.exceeded[0] == 'color_width'
    with pytest.raises(ValueError, match=rf'^--color-width 4096 is too large: .*at most '
                                         rf'{plan.largest:,} fits$'):
        budget.check(plan)
    assert budget.plan(config.replace(color_width=plan.largest).sizing(),
                       machine).exceeded is None
    assert budget.plan(config.replace(color_width=plan.largest + 1).sizing(),
                       machine).exceeded is not None


def test_stored_configs_are_not_refused_for_this_machine(capsys):
    """A checkpoint's config is read (evaluation, video) whatever this machine's memory: the
    limits are checked before training only."""
    stored = TrainConfig.from_options(batch_rays=200_000_000).to_dict()
    assert TrainConfig.from_stored(stored).schedule.batch_rays == 200_000_000


def test_sweep_refuses_options_beyond_the_limits_before_any_run(capture, tmp_path, capsys):
    status, _, err = run_cli(capsys, 'sweep', capture, '--out', tmp_path / 'sweep',
                             '--set', '--grid-levels 2048')
    assert status == 1 and one_clear_line(err).startswith(
        'error: sweep: --grid-levels 2048 is too large: ')
    assert not (tmp_path / 'sweep').exists()


@pytest.mark.parametrize('command', ['sweep', 'colmap'])
def test_out_naming_a_file_is_refused_by_name(capsys, capture, tmp_path, command):
    """Was the raw "[Errno 17] File exists"."""
    (tmp_path / 'file').write_text('precious')
    argv = ([capture] if command == 'sweep' else [f'{capture}/train/rgb'])
    status, _, err = run_cli(capsys, command, *argv, '--out', tmp_path / 'file')
    assert status == 1 and one_clear_line(err) == (
        f'error: {command}: --out {tmp_path / "file"} is an existing file, not a folder: '
        f'choose another --out')
    assert (tmp_path / 'file').read_text() == 'precious'


@pytest.mark.parametrize('option, message', [(['--frames', '0'], "--frames: expects a whole "
                                              "number of at least 1, got '0'"),
                                             (['--res', '0x0'], 'resolution must be positive')])
def test_video_bad_counts(capsys, tmp_path, option, message):
    status, _, err = run_cli(capsys, 'video', tmp_path, *option)
    assert status == 2 and message in err


def test_video_frames_beyond_memory_are_refused_naming_the_most_that_fit(capsys, tiny_run,
                                                                        tmp_path, monkeypatch):
    """``--frames 1e9`` ran 10 minutes to 7.7 GB making cameras (issue 49, item 5): a video
    holds each frame's camera and, as it is assembled, its pixels; refused before any camera
    is made, naming --frames and the most frames of that size that fit (also for
    --write-path, which makes the same cameras)."""
    from mi_nerfpp.core import budget
    monkeypatch.setattr(budget, 'available_bytes', lambda: 4 * GIB)
    most = budget.video_frames_limit(20, 10)
    assert most == (int(0.8 * 4 * GIB) - budget.BASE_BYTES) // (20 * 10 * 3
                                                                 + budget.VIDEO_CAMERA_BYTES)
    for extra in ([], ['--write-path', tmp_path / 'path.json']):
        status, _, err = run_cli(capsys, 'video', tiny_run, '-o', tmp_path / 'v.mp4',
                                 '--res', '20x10', '--frames', most + 1, *extra)
        assert status == 1 and one_clear_line(err) == (
            f'error: video: --frames {most + 1}: {most + 1:,} frames of 20x10 are too many: a '
            f"video holds each frame's camera and, while it is assembled, its pixels in "
            f'memory, more than the {budget.memory_text(budget.images_budget())} available; '
            f'at most {most:,} frames of 20x10 fit')
        assert list(tmp_path.iterdir()) == []


def test_a_downscale_that_leaves_no_image_names_the_largest_that_fits(capsys, capture,
                                                                       tmp_path):
    """The capture's 32x24 images keep 3x3 pixels (SSIM's window) up to --downscale 8."""
    from mi_nerfpp.data.dataset import MIN_IMAGE_SIZE
    largest = 24 // MIN_IMAGE_SIZE
    for factor in (largest + 1, 1000000000):
        status, _, err = run_cli(capsys, 'optimize', capture, '--out', tmp_path / 'run',
                                 '--downscale', factor, *TINY)
        line = one_clear_line(err)
        assert status == 1 and line.endswith(
            f'image is {32 // factor}x{24 // factor} pixels after --downscale {factor} (of '
            f'32x24); training and evaluation (SSIM) need at least 3x3: the largest '
            f'--downscale that fits is {largest}')
        assert not (tmp_path / 'run').exists()


def test_video_format_is_refused_before_rendering(capsys, tiny_run, tmp_path):
    status, _, err = run_cli(capsys, 'video', tiny_run, '-o', tmp_path / 'v.avi')
    assert status == 1 and one_clear_line(err) == (
        f'error: video: {tmp_path / "v.avi"}: video must be .mp4 or .gif')
    assert list(tmp_path.iterdir()) == []           # no frames were rendered


@pytest.mark.parametrize('args, message', [
    (['--res', '64x64', '--spp', '10000000'],
     'spp 10000000 is too large at 64x64: a view traces 40,960,000,000 rays, more than one '
     'Dr.Jit array holds (2^32 - 1); at most spp 1,048,575 fits at this resolution'),
])
def test_synth_sizes_are_checked_before_rendering(capsys, tmp_path, args, message):
    from mi_nerfpp.data import synth
    status, _, err = run_cli(capsys, 'synth', synth.scene_file('gt_plaza.xml'), '--out',
                             tmp_path / 'capture', *args)
    assert status == 1 and one_clear_line(err) == f'error: synth: {message}'
    assert not (tmp_path / 'capture').exists()


def test_synth_memory_limits_in_closed_form():
    from mi_nerfpp.data.synth.capture import check_capture_size
    per = budget.CAPTURE_BYTES_PER_PIXEL
    check_capture_size(100, 64, 64, 4, budget=GIB)
    with pytest.raises(ValueError) as e:
        check_capture_size(10 ** 6, 64, 64, 4, budget=GIB)
    assert str(e.value) == (f'views 1000000 are too many at 64x64: their images take about '
                            f'{budget.memory_text(10 ** 6 * 4096 * per)} while they are written, '
                            f'more than this machine\'s 1 GiB; at most {GIB // (4096 * per):,} '
                            f'views fit at this resolution')
    with pytest.raises(ValueError, match=r'^resolution 100000x100000 is too large: '
                                         r'10,000,000,000 pixels per image'):
        check_capture_size(1, 100000, 100000, 1, budget=GIB)


# ----------------------------------------------------------------------------- the boundary

def test_an_unexpected_error_is_one_line_naming_the_input(capsys, tmp_path, monkeypatch):
    """A bug (any exception the command did not expect) still ends with one line, naming what
    the command worked on; --debug (or MI_NERFPP_DEBUG=1) shows the traceback above it."""
    from mi_nerfpp.jobs import run

    def broken(*args, **kwargs):
        return 1 / 0
    monkeypatch.setattr(run, 'optimize', broken)
    status, _, err = run_cli(capsys, 'optimize', tmp_path, *TINY)
    assert status == 1 and one_clear_line(err) == (
        f'error: optimize: unexpected ZeroDivisionError while working on dataset {tmp_path}: '
        f'division by zero (a bug: rerun with --debug for the traceback and report it)')
    for argv, env in ((['--debug', 'optimize', tmp_path, *TINY], None),
                      (['optimize', tmp_path, *TINY, '--debug'], None),
                      (['optimize', tmp_path, *TINY], '1')):
        if env:
            monkeypatch.setenv('MI_NERFPP_DEBUG', env)
        status, _, err = run_cli(capsys, *argv)
        assert status == 1 and 'Traceback (most recent call last)' in err
        assert 'ZeroDivisionError: division by zero' in err
        assert err.rstrip().splitlines()[-1].startswith('error: optimize: unexpected ')


@pytest.mark.parametrize('name', TrainConfig.step_sizes())
def test_a_divergence_names_the_step_size_that_was_raised(name):
    """--lr-final 1e30 or --far-smoothness 1e30 made runs diverge with "lower --lr-grid,
    --lr-mlp" (issue 49, item 6): every learning rate and loss weight is a suspect, and the one
    raised is named."""
    from mi_nerfpp.core.poses import MAX_LR_POSES
    big = MAX_LR_POSES if name == 'lr_poses' else 1e30       # --lr-poses is bounded
    value = (big,) if isinstance(getattr(TrainConfig().losses, name, None), tuple) else big
    hint = TrainConfig().replace(**{name: value}).divergence_hint()
    flag = TrainConfig().flag(name)
    assert hint == f'Most likely {flag} {big:g} (above the default): lower it'


def test_the_step_sizes_are_every_learning_rate_and_loss_weight():
    assert {'lr_final', 'lr_grid', 'distortion', 'sparsity', 'mask_weight'} <= set(
        TrainConfig.step_sizes())
    assert 'near_gradient' not in TrainConfig.step_sizes()       # a radius, not a step size


@pytest.mark.parametrize('argv, message', [
    (['colmap', 'photos', '--out', 'data', '--threads', '-5'],
     f"--threads: expects -1 (every core) or a whole number from 1 to {max_threads()} "
     f"({THREADS_PER_CORE} per core of this machine's {os.cpu_count()}), got '-5'"),
    # 2147483647 fit COLMAP's C int, and the library allocated gigabytes before failing
    # (issue 63): the count is bounded by the machine.
    (['colmap', 'photos', '--out', 'data', '--threads', '2147483647'],
     f"--threads: expects -1 (every core) or a whole number from 1 to {max_threads()} "
     f"({THREADS_PER_CORE} per core of this machine's {os.cpu_count()}), got '2147483647'"),
    (['colmap', 'photos', '--out', 'data', '--threads', str(max_threads() + 1)],
     f"--threads: expects -1 (every core) or a whole number from 1 to {max_threads()} "),
    # A port beyond 65535 reached socket.bind's OverflowError, "a bug" (issue 63).
    (['view', 'run', '--port', '70000'],
     "argument --port: expects a whole number from 1 to 65535 (a TCP port), got '70000'"),
    (['view', 'run', '--port', '0'],
     "argument --port: expects a whole number from 1 to 65535 (a TCP port), got '0'"),
    (['optimize', '--view', '--view-port', '65536'],
     "argument --view-port: expects a whole number from 1 to 65535 (a TCP port), got '65536'"),
    (['export', 'run', '--out', 'x', '--density', '-1'],
     "--density: expects a finite number above 0, got '-1'"),
    (['export', 'run', '--out', 'x', '--density', 'nan'],
     "--density: expects a finite number above 0, got 'nan'"),
    (['export', 'run', '--out', 'x', '--resolution', '2'],
     "--resolution: expects a whole number of at least 8, got '2'"),
    # pycolmap's "incompatible function arguments" (issue 49, item 5): a C int.
    (['colmap', 'photos', '--out', 'data', '--overlap', '10000000000'],
     "--overlap: expects a whole number from 1 to 2147483647 (COLMAP's largest count), got "
     "'10000000000'"),
    (['colmap', 'photos', '--out', 'data', '--max-image-size', '10000000000'],
     "--max-image-size: expects a whole number from 16 to 2147483647"),
    # synth's numbers were checked by the Python API, whose messages named 'views', 'fov'...
    (['synth', 'scene.xml', '--out', 'data', '--views', '-3'],
     "argument --views: expects a whole number of at least 1, got '-3'"),
    (['synth', 'scene.xml', '--out', 'data', '--fov', '500'],
     "argument --fov: expects a number between 0 and 180 degrees, got '500'"),
    (['synth', 'scene.xml', '--out', 'data', '--radius', 'nan'],
     "argument --radius: expects a finite number above 0, got 'nan'"),
    (['synth', 'scene.xml', '--out', 'data', '--seed', '2147483648'],
     "argument --seed: expects a whole number from 0 to 2147483647, got '2147483648'"),
    (['synth', 'scene.xml', '--out', 'data', '--spp', '0'],
     "argument --spp: expects a whole number of at least 1, got '0'"),
    (['colmap', 'photos', '--out', 'data', '--hold', '-1'],
     "--hold: expects a whole number from 0 to 2147483647"),
])
def test_command_options_out_of_range_are_refused_by_argparse_naming_them(capsys, argv,
                                                                         message):
    """colmap --threads -5 and export --density -1 reached the libraries' own text; export
    --resolution 2 said "pass a lower --density" (issue 49, items 5 and 6)."""
    status, _, err = run_cli(capsys, *argv)
    assert status == 2 and message in err, err


def test_an_export_grid_beyond_the_memory_names_the_largest_resolution(capsys, tmp_path):
    """export --resolution 100000 said "lower --batch-rays, --samples..." (issue 49, item 5)."""
    from mi_nerfpp.jobs.export import BYTES_PER_POINT, largest_resolution
    status, _, err = run_cli(capsys, 'export', tmp_path / 'run', '--out', tmp_path / 'x',
                             '--resolution', '100000')
    line = one_clear_line(err)
    best = largest_resolution()
    assert status == 1 and line == (
        f"error: export: --resolution 100000 is too large: its grid of 1,000,000,000,000,000 "
        f"points takes more than this machine's {budget.memory_text()}; the largest that fits "
        f"is {best}")
    assert best ** 3 * BYTES_PER_POINT <= budget.memory_bytes() < \
        (best + 1) ** 3 * BYTES_PER_POINT


def test_a_video_frame_beyond_memory_names_res(capsys, tiny_run, tmp_path, monkeypatch):
    """Not even one frame of --res fits: the frame size is named, not --frames."""
    from mi_nerfpp.core import budget
    monkeypatch.setattr(budget, 'available_bytes', lambda: 4 * GIB)
    pixels = (budget.images_budget() - budget.VIDEO_CAMERA_BYTES) // 3
    status, _, err = run_cli(capsys, 'video', tiny_run, '-o', tmp_path / 'v.mp4', '--res',
                             '100000x100000', '--frames', '1')
    assert status == 1 and one_clear_line(err) == (
        f'error: video: --res 100000x100000: one frame of 100000x100000 takes '
        f'{budget.memory_text(3 * 10 ** 10)}, more than the '
        f'{budget.memory_text(budget.images_budget())} available; a frame fits with at most '
        f'{pixels:,} pixels')
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize('option, flag, brick', [
    (['--grid-sparse', '65536'], '--grid-sparse 65536', '1024x1024x1024'),
    (['--grid-sparse', '128', '8448'], '--grid-sparse 128 8448', '132x132x132'),
    (['--bg-grid-sparse', '131072'], '--bg-grid-sparse 131072', '4096x4096x4096'),
])
def test_a_sparse_level_whose_brick_outgrows_its_entries_names_the_largest(capsys, tmp_path,
                                                                           option, flag,
                                                                           brick):
    """A sparse level keeps one brick (an occupancy cell) however large, while the memory plan
    counted --sparse-entries: --grid-sparse 65536 made a brick of 1024^3 texels, 16 GB, before
    the first step (issue 63). Refused before any work, naming the largest resolution whose
    brick fits (a multiple of the occupancy cells)."""
    status, _, err = run_cli(capsys, 'optimize', tmp_path, '--out', tmp_path / 'run', *option)
    line = one_clear_line(err)
    assert status == 1, line
    assert line.startswith(f'error: optimize: {flag} is too large: one brick '), line
    entries = TrainConfig().schedule.sparse_entries
    assert f'holds {brick} texels' in line and f'more than --sparse-entries {entries}' in line
    best = int(re.search(r'fits at resolution ([\d,]+) at most$', line).group(1).replace(',', ''))
    cells = 64 if option[0] == '--grid-sparse' else 32       # --occupancy-res 64
    assert best % cells == 0
    # Behind, a brick spans R/32 texels of colatitude, 2R/64 of longitude and, along s, as a
    # dense level of --bg-s-ratio 0.5 has them over 16 cells: R/32.
    brick = (best // 64) ** 3 * 4 if option[0] == '--grid-sparse' else (best // 32) ** 3 * 4
    assert brick <= entries < (
        ((best + 64) // 64) ** 3 * 4 if option[0] == '--grid-sparse'
        else ((best + 32) // 32) ** 3 * 4)
    assert not (tmp_path / 'run').exists()


def test_a_sparse_level_is_planned_as_its_whole_bricks():
    """The plan counts a sparse level as the whole bricks that --sparse-entries holds (what
    SparseAllocation keeps), not --sparse-entries itself; the largest resolution fits."""
    from mi_nerfpp.core.budget import sparse_level_entries
    sizing = TrainConfig.from_options(grid_sparse=(640,), grid_levels=(4, 8),
                                      sparse_entries=9000).sizing()
    assert sparse_level_entries(sizing, 'ball') == [2 * 10 ** 3 * 4]  # two bricks of 10^3
    budget.check(budget.plan(TrainConfig.from_options(grid_sparse=(6400,),
                                                      grid_levels=(4, 8)).sizing()))
