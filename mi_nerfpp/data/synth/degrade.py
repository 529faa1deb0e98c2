"""Degraded copies of a capture, for the tests and benchmarks of robust training.

:func:`vary_exposure` gives each image its own exposure and white balance (the test of
``--appearance``, :mod:`mi_nerfpp.core.appearance`); :func:`perturb_poses` perturbs the training
poses as an imperfect structure from motion would (the test of ``--refine-poses``,
:mod:`mi_nerfpp.core.poses`). Each copies a NeRF++-layout capture to a new folder and records what
it changed next to it.
"""
from __future__ import annotations

import json
import os
import shutil

import imageio.v3 as iio
import numpy as np

from mi_nerfpp.core.color import srgb_eotf, to_srgb8
from mi_nerfpp.core.poses import corrected_c2w
from mi_nerfpp.data.nerfpp import _read_matrix, _write_matrix
from mi_nerfpp.files.atomic import atomic_write_path
from mi_nerfpp.files.readers import read_image

APPEARANCE_FILE = 'appearance.json'


def _capture_copy_paths(src, out, needs: str, writer: str) -> tuple[str, str]:
    """``(src, out)`` as strings for a modified copy of a NeRF++ capture; refuses a source
    without ``train/<needs>`` and an ``out`` that already exists."""
    src, out = os.fspath(src), os.fspath(out)
    if not os.path.isdir(os.path.join(src, 'train', needs)):
        raise FileNotFoundError(f'{src}: not a NeRF++ capture (no train/{needs} folder)')
    if os.path.exists(out):
        raise FileExistsError(f'{out}: already exists; {writer} writes a new folder')
    return src, out


def vary_exposure(src, out, stops: float = 0.5, white_balance: float = 0.1, seed: int = 0,
                  splits=('train', 'test')) -> dict:
    """Copy the NeRF++-layout capture ``src`` to ``out`` with a different exposure and white
    balance per image, as a camera on auto-exposure would record it.

    Each image of ``splits`` gets per-channel gains ``2^(e + w_c)`` (``e`` uniform in
    ``±stops``, ``w_c`` uniform in ``±white_balance`` stops), applied in linear light, then
    clipped and sRGB-encoded to 8 bits again; training image 0 too, as a camera's first photo
    has no special exposure (the learned transforms estimate the gains relative to their mean,
    :mod:`mi_nerfpp.core.appearance`). The true gains are written to ``out/appearance.json``
    (``{split: [[r, g, b], ...]}`` in file order) and returned.
    """

    src, out = _capture_copy_paths(src, out, 'rgb', 'vary_exposure')
    if not (stops >= 0 and white_balance >= 0):
        raise ValueError(f'stops and white_balance must be >= 0, got {stops}, {white_balance}')
    shutil.copytree(src, out)
    rng = np.random.default_rng(seed)
    gains = {}
    for split in splits:
        folder = os.path.join(out, split, 'rgb')
        names = sorted(os.listdir(folder)) if os.path.isdir(folder) else []
        gains[split] = []
        for name in names:
            g = 2.0 ** (rng.uniform(-stops, stops) + rng.uniform(-white_balance, white_balance, 3))
            path = os.path.join(folder, name)
            image = read_image(path, what='capture image', remedy='write the capture '
                               'again')[..., :3].astype(np.float64) / 255.0
            iio.imwrite(path, to_srgb8(np.clip(srgb_eotf(image) * g, 0.0, 1.0)))
            gains[split].append([float(v) for v in g])
    with atomic_write_path(os.path.join(out, APPEARANCE_FILE)) as tmp, open(tmp, 'w') as f:
        json.dump({'gains': gains, 'stops': stops, 'white_balance': white_balance,
                   'seed': seed}, f, indent=2)
    return gains


POSES_FILE = 'poses.json'


def perturb_poses(src, out, degrees: float = 1.0, fraction: float = 0.01, seed: int = 0) -> dict:
    """Copy the NeRF++-layout capture ``src`` to ``out`` with perturbed *training* poses, as an
    imperfect structure-from-motion would give them (the test of ``--refine-poses``).

    Every training camera but image 0 (the reference of the learned corrections,
    :mod:`mi_nerfpp.core.poses`) is rotated about its centre by ``degrees`` about a random axis and
    its centre moved by ``fraction`` of the scene radius (the largest distance of a training
    camera from their mean centre) in a random direction. Images and held-out poses are
    unchanged. ``out/poses.json`` records ``{'true': [4x4 c2w, ...], 'given': [...],
    'radius': r, ...}`` (training cameras in file order, world frame), which is returned.
    """

    src, out = _capture_copy_paths(src, out, 'pose', 'perturb_poses')
    if not (degrees >= 0 and fraction >= 0):
        raise ValueError(f'degrees and fraction must be >= 0, got {degrees}, {fraction}')
    shutil.copytree(src, out)
    folder = os.path.join(out, 'train', 'pose')
    names = sorted(n for n in os.listdir(folder) if n.lower().endswith('.txt'))
    true = [_read_matrix(os.path.join(folder, n)) for n in names]
    centers = np.stack([c[:3, 3] for c in true])
    radius = float(np.max(np.linalg.norm(centers - centers.mean(axis=0), axis=1)))
    rng = np.random.default_rng(seed)

    def unit():
        v = rng.normal(size=3)
        return v / np.linalg.norm(v)

    given = []
    for i, (name, c2w) in enumerate(zip(names, true)):
        if i > 0:
            c2w = corrected_c2w(c2w, np.concatenate([np.radians(degrees) * unit(),
                                                     fraction * radius * unit()]))
            _write_matrix(os.path.join(folder, name), c2w)
        given.append(c2w)
    record = {'true': [m.tolist() for m in true], 'given': [m.tolist() for m in given],
              'radius': radius, 'degrees': degrees, 'fraction': fraction, 'seed': seed}
    with atomic_write_path(os.path.join(out, POSES_FILE)) as tmp, open(tmp, 'w') as f:
        json.dump(record, f)
    return record
