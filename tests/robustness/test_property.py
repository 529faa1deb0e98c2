"""Property-style probes, seeded and fast: random bytes and random numbers fed to the dataset
readers, the checkpoint reader, the scene reader and the optimize option parser. Whatever the
input, a reader raises its own error (never another exception), and the command ends with one
line and status 1, writing nothing.

Each case starts from a valid tiny input and damages one file: random bytes in its place, the
file cut short, bytes flipped, or (text files) a number replaced by a random one - zero,
negative, huge, NaN, inf. An input that still reads is left out of the command check (it would
train); the seeds make every run draw the same cases.
"""
import json
import os
import random
import re
import shutil
import struct
import warnings

import numpy as np
import pytest
from PIL import Image

from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.data import DatasetError, load_dataset
from mi_nerfpp.training.options import option_name, options_of
from tests.robustness.common import TINY, one_clear_line, run_cli

CASES = 24             # damaged inputs per format
EDGE_NUMBERS = ['0', '-1', '-0.0', '1e-45', '3', '2147483648', '4294967296', '1e30', '1e308',
                '-1e308', 'nan', 'inf', '-inf', '18446744073709551616']


def _images(folder, names, size=(8, 6)):
    folder.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        Image.fromarray(np.full((size[1], size[0], 3), 60 + 30 * i, np.uint8)).save(folder / name)


def _pose(i):
    pose = np.eye(4)
    pose[:3, 3] = [i - 1.0, 0.2 * i, 3.0]
    return pose


def make_blender(root):
    _images(root, [f'{i}.png' for i in range(3)])
    frames = [{'file_path': f'{i}.png', 'transform_matrix': _pose(i).tolist()} for i in range(3)]
    (root / 'transforms.json').write_text(json.dumps({'camera_angle_x': 0.8, 'frames': frames},
                                                     indent=1))


def make_nerfpp(root):
    for split, n in (('train', 3), ('test', 1)):
        names = [f'{i:03d}' for i in range(n)]
        _images(root / split / 'rgb', [f'{n}.png' for n in names])
        for folder in ('pose', 'intrinsics'):
            (root / split / folder).mkdir(parents=True)
        for i, name in enumerate(names):
            (root / split / 'pose' / f'{name}.txt').write_text(
                ' '.join(f'{v:g}' for v in _pose(i).ravel()))
            K = np.eye(4)
            K[:3, :3] = [[10, 0, 4], [0, 10, 3], [0, 0, 1]]
            (root / split / 'intrinsics' / f'{name}.txt').write_text(
                ' '.join(f'{v:g}' for v in K.ravel()))


def make_llff(root):
    _images(root / 'images', [f'{i:03d}.png' for i in range(3)])
    rows = []
    for i in range(3):
        pose = np.zeros((3, 5))
        pose[:, :3] = np.eye(3)
        pose[:, 3] = [i, 0, 0]
        pose[:, 4] = [6, 8, 10.0]
        rows.append(np.concatenate([pose.ravel(), [1.0, 10.0]]))
    np.save(root / 'poses_bounds.npy', np.array(rows))


def make_colmap_text(root):
    _images(root / 'images', [f'{i}.png' for i in range(3)])
    (root / 'sparse' / '0').mkdir(parents=True)
    (root / 'sparse' / '0' / 'cameras.txt').write_text('1 PINHOLE 8 6 10 10 4 3\n')
    (root / 'sparse' / '0' / 'images.txt').write_text(
        ''.join(f'{i + 1} 1 0 0 0 {i - 1} 0.{i} 3 1 {i}.png\n\n' for i in range(3)))


def make_colmap_binary(root):
    _images(root / 'images', [f'{i}.png' for i in range(3)])
    model = root / 'sparse' / '0'
    model.mkdir(parents=True)
    (model / 'cameras.bin').write_bytes(struct.pack('<Q', 1) + struct.pack('<iiQQ', 1, 1, 8, 6)
                                        + struct.pack('<4d', 10, 10, 4, 3))
    data = struct.pack('<Q', 3)
    for i in range(3):
        data += (struct.pack('<idddddddi', i + 1, 1, 0, 0, 0, i - 1, 0.1 * i, 3, 1)
                 + f'{i}.png'.encode() + b'\0' + struct.pack('<Q', 0))
    (model / 'images.bin').write_bytes(data)


FORMATS = {'blender': make_blender, 'nerfpp': make_nerfpp, 'llff': make_llff,
           'colmap-text': make_colmap_text, 'colmap-binary': make_colmap_binary}


def damage(path, rng):
    """Damage one file in place (see the module docstring); returns how."""
    data = path.read_bytes()
    how = rng.choice(['random bytes', 'cut short', 'flipped bytes', 'random number'])
    if how == 'random bytes':
        data = bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 200)))
    elif how == 'cut short':
        data = data[:rng.randrange(0, max(len(data), 1))]
    elif how == 'flipped bytes' and data:
        data = bytearray(data)
        for _ in range(rng.randrange(1, 8)):
            data[rng.randrange(len(data))] = rng.getrandbits(8)
        data = bytes(data)
    else:
        text = data.decode('latin-1')
        numbers = list(re.finditer(r'-?\d+(?:\.\d+)?(?:e[-+]?\d+)?', text))
        if numbers:
            m = rng.choice(numbers)
            text = text[:m.start()] + rng.choice(EDGE_NUMBERS) + text[m.end():]
        data = text.encode('latin-1')
    path.write_bytes(data)
    return how


@pytest.mark.parametrize('fmt', FORMATS)
def test_damaged_datasets_are_refused_in_one_line(capsys, tmp_path, fmt):
    rng = random.Random(f'issue-37 {fmt}')
    template = tmp_path / 'template'
    FORMATS[fmt](template)
    assert len(load_dataset(str(template), downscale=1).train) > 0    # the template reads
    files = sorted(p for p in template.rglob('*') if p.is_file())
    refused = 0
    for case in range(CASES):
        data = tmp_path / f'case{case}'
        shutil.copytree(template, data)
        target = data / rng.choice(files).relative_to(template)
        how = damage(target, rng)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')        # e.g. a frame skipped for its missing image
            try:
                load_dataset(str(data), downscale=1)
                continue                           # still a dataset: not a refusal to check
            except DatasetError:
                pass
            out = tmp_path / f'run{case}'
            status, _, err = run_cli(capsys, 'optimize', data, '--out', out, '--downscale', '1',
                                     *TINY)
        line = one_clear_line(err)
        assert status == 1 and line.startswith('error: optimize: '), (how, target, line)
        assert not out.exists(), (how, target)
        refused += 1
    assert refused >= CASES // 2        # most damage is refused (the rest still reads)


def test_damaged_checkpoints_are_refused_in_one_line(capsys, tmp_path):
    from mi_nerfpp.files.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
    from tests.helpers import tiny_model
    rng = random.Random('issue-37 checkpoints')
    good = tmp_path / 'good.npz'
    save_checkpoint(good, tiny_model())
    for case in range(CASES):
        run = tmp_path / f'run{case}'
        run.mkdir()
        path = run / 'model.npz'
        shutil.copy(good, path)
        how = damage(path, rng)
        try:
            load_checkpoint(path)
            continue
        except CheckpointError:
            pass
        status, _, err = run_cli(capsys, 'evaluate', run)
        assert status == 1 and one_clear_line(err).startswith(f'error: evaluate: {path}: '), how
        assert os.listdir(run) == ['model.npz'], how


def test_random_scene_files_are_refused_in_one_line(capsys, tmp_path):
    rng = random.Random('issue-37 scenes')
    template = ('<scene version="3.0.0"><integrator type="nerfpp"><integer name="fg_samples" '
                'value="4"/></integrator><sensor type="perspective"><film type="hdrfilm">'
                '<integer name="width" value="4"/><integer name="height" value="3"/></film>'
                '</sensor></scene>')
    for case in range(CASES):
        scene = tmp_path / f'scene{case}.xml'
        scene.write_text(template)
        how = damage(scene, rng)
        out = tmp_path / f'out{case}.exr'
        status, _, err = run_cli(capsys, 'render', scene, '-o', out)
        if status == 0:                         # the damage left a renderable scene
            continue
        assert status == 1 and one_clear_line(err).startswith('error: render: '), (how, err)
        assert not out.exists()


def _numeric_options():
    """``[(flag, element type, values per use)]`` of the optimize options that take numbers."""
    out = []
    for _, f in options_of(TrainConfig):
        meta, default = f.metadata, f.default
        if 'choices' in meta or isinstance(default, bool) or 'joint' in meta:
            continue
        kind = meta.get('type') or (type(default[0]) if isinstance(default, tuple) and default
                                    else type(default))
        if kind not in (int, float):
            continue
        count = 1 if not (isinstance(default, tuple) or meta.get('nargs')) else 2
        out.append((meta.get('flag', '--' + f.name.replace('_', '-')), kind, count,
                    option_name(f)))
    out.append(('--samples', int, 3, None))
    return out


def test_random_numbers_to_the_options_are_refused_in_one_line(capsys, tmp_path, monkeypatch):
    """For every numeric option, random values (edge numbers of its type): those the config
    refuses end the command with one line naming the option, status 1, and nothing
    written. The memory budget is fixed (16 GiB), so that every machine draws and refuses the
    same cases."""
    from mi_nerfpp.core import budget
    monkeypatch.setattr(budget, 'memory_bytes', lambda: 16 * budget.GIB)
    rng = random.Random('issue-37 options')
    ints = [v for v in EDGE_NUMBERS if re.fullmatch(r'-?\d+', v)] + ['65536', '100000000']
    refused = 0
    for flag, kind, count, name in _numeric_options():
        for _ in range(3):
            values = [rng.choice(ints if kind is int else EDGE_NUMBERS) for _ in range(count)]
            if count > 1:      # argparse takes '-inf' after --flag for another option
                values = [v if re.fullmatch(r'-?\d+|[^-].*', v) else v[1:] for v in values]
            try:
                parsed = [kind(v) for v in values]
            except ValueError:
                continue
            options = ({'fg_samples': parsed[0], 'bg_samples': parsed[1],
                        'fine_samples': parsed[2]} if flag == '--samples'
                       else {name: tuple(parsed) if count > 1 else parsed[0]})
            try:
                config = TrainConfig.from_options(**options)
                budget.check(budget.plan(config.sizing()))
                continue                        # a value it accepts: not a refusal to check
            except (ValueError, TypeError):
                pass
            out = tmp_path / 'run'
            argv = [f'{flag}={values[0]}'] if count == 1 else [flag, *values]
            status, _, err = run_cli(capsys, 'optimize', tmp_path, '--out', out, *argv)
            line = one_clear_line(err)
            assert status == 1 and line.startswith('error: optimize: '), (flag, values, line)
            shown = flag if flag != '--samples' else '--samples'
            assert shown in line or 'a run takes about' in line, (flag, values, line)
            assert not out.exists()
            refused += 1
    assert refused > 40


def test_random_sizes_are_refused_before_work_naming_the_largest_that_fits(monkeypatch):
    """Issue 49, item 5: random values of the options whose bound depends on the command's
    inputs - --color-width (the colour MLP's arrays and memory), --lr-poses, video --frames
    (frames of a random size held in memory) and --downscale (of a random image size) - are
    either accepted, or refused naming the option and the largest value that fits, which is
    itself accepted. Memory is fixed, so every machine draws the same cases."""
    from mi_nerfpp.commands.video import check_frames
    from mi_nerfpp.core import budget, poses
    from mi_nerfpp.data.dataset import MIN_IMAGE_SIZE, _check_downscale
    from mi_nerfpp.data.errors import DatasetError
    monkeypatch.setattr(budget, 'memory_bytes', lambda: 16 * budget.GIB)
    monkeypatch.setattr(budget, 'available_bytes', lambda: 12 * budget.GIB)
    machine = budget.Machine(16 * budget.GIB, 12 * budget.GIB, 2)
    rng = random.Random('issue-49 sizes')
    widths = set()
    for _ in range(CASES):
        width = int(2 ** rng.uniform(0, 34))
        config = TrainConfig.from_options(color_width=width, batch_rays=rng.choice([32, 1024]),
                                          color_layers=rng.choice([1, 2, 8]))
        plan = budget.plan(config.sizing(), machine)
        if plan.exceeded is None:
            continue
        assert plan.exceeded[0] == 'color_width', (width, plan.exceeded)
        with pytest.raises(ValueError, match=rf'^--color-width {width} is too large: .*'
                                             rf'at most {plan.largest:,} fits$'):
            budget.check(plan)
        assert budget.plan(config.replace(color_width=plan.largest).sizing(),
                           machine).exceeded is None
        widths.add(width)
    assert len(widths) > CASES // 4

    for _ in range(CASES):
        lr = 10 ** rng.uniform(-6, 20)
        if lr <= poses.MAX_LR_POSES:
            assert TrainConfig.from_options(lr_poses=lr).optimizer.lr_poses == lr
            continue
        with pytest.raises(ValueError, match=rf'^--lr-poses must be at most '
                                             rf'{poses.MAX_LR_POSES:g} '):
            TrainConfig.from_options(lr_poses=lr)

    for _ in range(CASES):
        w, h = rng.randint(1, 4000), rng.randint(1, 4000)
        frames = int(10 ** rng.uniform(0, 12))
        most = budget.video_frames_limit(w, h)
        if frames <= most:
            check_frames(frames, w, h, f'--frames {frames}')
            continue
        with pytest.raises(ValueError, match=rf'^--frames {frames}: .* at most {most:,} '
                                             rf'frames of {w}x{h} fit$'):
            check_frames(frames, w, h, f'--frames {frames}')
        check_frames(most, w, h, f'--frames {most}')

    for _ in range(CASES):
        w, h = rng.randint(1, 5000), rng.randint(1, 5000)
        factor = int(2 ** rng.uniform(0, 14))
        largest = min(w, h) // MIN_IMAGE_SIZE
        if factor <= largest:
            _check_downscale('x.png', w, h, factor)
            continue
        fix = (f'the largest --downscale that fits is {largest}' if largest else
               'the image is too small at any --downscale')
        after = rf' after --downscale {factor} \(of {w}x{h}\)' if factor > 1 else ''
        with pytest.raises(DatasetError, match=rf'^x\.png: image is {w // factor}x{h // factor} '
                                               rf'pixels{after}; .*{fix}'):
            _check_downscale('x.png', w, h, factor)
        if largest:
            _check_downscale('x.png', w, h, largest)


def test_random_model_options_are_what_a_checkpoint_of_them_says(tmp_path):
    """Issue 49, item 2: for random model-shaping options, the options read back from the
    weights of a model built with them (:func:`weight_options`) are the options' effective
    values, a config read from a checkpoint that stores none of them describes the weights,
    and a resume asking for other random options is refused naming exactly those that
    differ."""
    from mi_nerfpp.training.config import weight_options
    rng = random.Random('issue-49 resume')

    def draw():
        return dict(model=rng.choice(['nerfpp', 'nerf']), field=rng.choice(['grid', 'nerf']),
                    bg_field=rng.choice([None, 'grid', 'vanilla']),
                    color=rng.choice(['deferred', 'sample']),
                    bg_color=rng.choice(['deferred', 'sample']),
                    antialias=rng.random() < 0.5, grid_channels=rng.randint(2, 6),
                    color_width=rng.choice([8, 16, 32]), color_layers=rng.randint(1, 3),
                    dir_octaves=rng.randint(0, 4),
                    grid_planes=tuple(rng.sample([8, 16, 32], rng.randint(0, 2))),
                    bg_grid_planes=rng.choice([None, (), (16,)]),
                    fg_warp=rng.choice([0.0, 0.5]), density_bias=rng.choice([0.0, -1.0]),
                    appearance=rng.random() < 0.5, refine_poses=rng.random() < 0.5)

    def weights(config):
        m = config.model
        return {'fg': config.field_config(m.field, 'ball'),
                'bg': (config.field_config(m.bg_field, 'inverted_sphere')
                       if m.kind == 'nerfpp' else None),
                'color_space': 'srgb', 'composite': 'linear',
                'appearance_images': 3 if m.appearance else 0,
                'pose_images': 3 if m.refine_poses else 0}

    for _ in range(CASES):
        config = TrainConfig.from_options(**draw())
        fixed = weight_options(weights(config))
        assert fixed and all(config.effective(k) == v for k, v in fixed.items())
        read = TrainConfig.from_stored({}, weights=weights(config))
        assert all(read.effective(k) == v for k, v in fixed.items())
        assert config.resume_conflicts({}, weights(config)) == []
        other = TrainConfig.from_options(**draw())
        lines = other.resume_conflicts({}, weights(config))
        differ = [k for k, v in fixed.items() if other.effective(k) != v]
        assert [line.split(':')[0] for line in lines] == [other.flag(k) for k in differ]


def test_random_counts_to_the_commands_are_bounded_by_their_parsers(capsys):
    """Issue 49, items 5 and 6: random whole numbers (and edge numbers) to the count options of
    colmap, whose values go to COLMAP's C ints, are accepted within their range and otherwise
    refused by the command line, naming the option and its range - never by pycolmap's
    "incompatible function arguments"."""
    from mi_nerfpp.commands.arguments import max_threads
    from mi_nerfpp.commands.cli import build_parser
    from mi_nerfpp.data.sfm import COLMAP_MAX_INT, COLMAP_MINIMUMS
    parser = build_parser()
    rng = random.Random('issue-49 counts')
    ranges = {f'--{name.replace("_", "-")}': (low, COLMAP_MAX_INT)
              for name, low in COLMAP_MINIMUMS.items()}
    ranges['--threads'] = (1, max_threads())     # bounded by the machine (issue 63)
    checked = 0
    for flag, (low, high) in ranges.items():
        for _ in range(CASES):
            value = rng.choice([rng.randint(-10, 100), int(2 ** rng.uniform(0, 70)),
                                -int(2 ** rng.uniform(0, 70)), low - 1, low, high, high + 1])
            argv = ['colmap', 'photos', '--out', 'data', f'{flag}={value}']
            if low <= value <= high or (flag == '--threads' and value == -1):
                assert getattr(parser.parse_args(argv), flag[2:].replace('-', '_')) == value
                continue
            with pytest.raises(SystemExit):
                parser.parse_args(argv)
            line = capsys.readouterr().err.strip().splitlines()[-1]
            assert f'argument {flag}: expects ' in line and f'to {high}' in line, line
            checked += 1
    assert checked > CASES
