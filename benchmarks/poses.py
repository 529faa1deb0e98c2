"""Held-out PSNR and pose errors of pose refinement on perturbed poses, against true poses.

    python benchmarks/poses.py DATA OUT [--degrees D] [--fraction F] [--iterations N | --minutes M]
                               [--cases true given refine ...] [--name poses]
                               [any optimize training option]

Copies the NeRF++-layout capture ``DATA`` to ``OUT/perturbed`` with perturbed training poses
(:func:`mi_nerfpp.data.synth.perturb_poses`: each training camera but image 0 rotated by
``--degrees`` about a random axis and moved by ``--fraction`` of the scene radius; held-out
poses exact) and trains, each from scratch with the same options, the ``--cases``:

- ``true``: the true poses (``DATA`` itself), no refinement: what refinement should reach;
- ``given``: the perturbed poses, no refinement;
- ``refine``: the perturbed poses with ``--refine-poses`` at today's defaults (coarse to fine);
- ``refine-flat``: the same without coarse to fine, corrections learned from a quarter of the
  run (``--poses-blur 0 --poses-start 0.25``: the defaults before it);
- ``refine-unpinned``: ``refine`` with the cameras free to drift together by a similarity (as
  before the gauge was pinned, :func:`mi_nerfpp.core.poses.gauge_basis`).

For each it prints the held-out PSNR (test views rendered at their exact poses, in the frame of
training image 0, which refinement keeps as given), the held-out PSNR with each test view's camera
first fitted alone against the model (BARF's test-time pose optimisation,
:func:`mi_nerfpp.training.pose_check.registered`: what the model renders, apart from where its
refinement left the capture's frame) and the training cameras' rotation (degrees)
and translation (fraction of the scene radius) errors against the true poses, mean and max over
the perturbed cameras, and the rotation error left after the similarity that best aligns the
camera centres with the true ones (each camera against the others). Results: ``benchmarks/results/<--name>.json``.
"""
import argparse
import os

import numpy as np
from skimage.transform import SimilarityTransform

import mi_nerfpp  # noqa: F401
from mi_nerfpp.jobs import bench, run
from mi_nerfpp.training.evaluate import evaluate_split
from mi_nerfpp.training.pose_check import registered
from mi_nerfpp.core import poses
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.jobs.console import ConsoleObserver
from mi_nerfpp.data import load_dataset
from mi_nerfpp.training.options import add_options, values
from mi_nerfpp.data.synth import perturb_poses


def errors(c2w, record):
    """(rotation errors in degrees, translation errors / radius) of cameras 1.. (0 is exact)."""
    rot, trans = poses.pose_errors(c2w, record['true'])
    return rot[1:], trans[1:] / record['radius']


def aligned_rotation_errors(c2w, record):
    """Rotation errors (degrees) of cameras 1.. after the similarity that best maps their
    centres onto the true ones (Umeyama, as BARF evaluates): each camera's error against the
    others, without a drift they share."""
    centres = np.stack([np.asarray(m)[:3, 3] for m in c2w])
    truth = np.stack([np.asarray(m)[:3, 3] for m in record['true']])
    turn = SimilarityTransform.from_estimate(centres, truth).params[:3, :3]
    turn = turn / np.cbrt(np.linalg.det(turn))
    rot, _ = poses.pose_errors([np.block([[turn @ np.asarray(m)[:3, :3], np.zeros((3, 1))],
                                          [np.zeros((1, 4))]]) for m in c2w],
                               [np.asarray(m) for m in record['true']])
    return rot[1:]


CASES = {'true': {}, 'given': {}, 'refine': {'refine_poses': True},
         'refine-flat': {'refine_poses': True, 'poses_blur': 0.0, 'poses_start': 0.25},
         'refine-unpinned': {'refine_poses': True}}


def main():
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('data')
    p.add_argument('out')
    p.add_argument('--degrees', type=float, default=1.0)
    p.add_argument('--fraction', type=float, default=0.01)
    p.add_argument('--cases', nargs='+', choices=list(CASES), default=list(CASES))
    p.add_argument('--name', default='poses')
    add_options(p, TrainConfig)
    args = p.parse_args()
    options = dict(values(args, TrainConfig), checkpoint_every=0, preview_every=0)
    if not options.get('minutes'):
        options['iterations'] = options['iterations'] or 300
    for key in ('refine_poses', 'poses_blur', 'poses_start'):
        options.pop(key, None)
    perturbed = os.path.join(args.out, 'perturbed')
    record = perturb_poses(args.data, perturbed, args.degrees, args.fraction, seed=1)
    rot, trans = errors(record['given'], record)
    print(f'given poses: rotation error mean {rot.mean():.3f}° max {rot.max():.3f}°, '
          f'translation error mean {trans.mean():.4f} max {trans.max():.4f} of the radius',
          flush=True)
    rows = [['given poses (before training)', '-', '-', '-', rot.mean(), rot.max(), trans.mean(),
             trans.max(), aligned_rotation_errors(record['given'], record).mean()]]
    for case in args.cases:
        cfg = TrainConfig.from_options(**options, **CASES[case])
        dataset = load_dataset(args.data if case == 'true' else perturbed)
        folder = os.path.join(args.out, case)
        run.check_run_folder(folder, resume=False, overwrite=True)
        observer = ConsoleObserver('train')
        trainer = run.start(run.RunInputs(dataset.root, dataset, cfg, folder), observer=observer)
        if case == 'refine-unpinned':
            trainer.gauge = None        # the cameras may drift together (before 2026-11-28)
        run.train(trainer, observer)
        r = evaluate_split(trainer.model, trainer.test, os.path.join(folder, 'test'))
        fitted = evaluate_split(trainer.model, registered(trainer.model, trainer.test),
                                os.path.join(folder, 'test_registered'))['psnr']
        refined = poses.world_poses(trainer.model, trainer.train.cameras)
        rot, trans = errors(refined, record)
        aligned = aligned_rotation_errors(refined, record) if case != 'true' else rot
        print(f'{case}: {trainer.iteration} steps: held-out PSNR {r["psnr"]:.2f} dB ({fitted:.2f} '
              f'with the test cameras registered); rotation '
              f'error mean {rot.mean():.3f}° max {rot.max():.3f}°, translation error mean '
              f'{trans.mean():.4f} max {trans.max():.4f} of the radius; after a similarity '
              f'alignment, rotation error mean {aligned.mean():.3f}°', flush=True)
        rows.append([case, trainer.iteration, r['psnr'], fitted, rot.mean(), rot.max(), trans.mean(),
                     trans.max(), aligned.mean()])
    bench.write_results(args.name, 'Camera pose refinement on perturbed poses', [
        bench.table('Held-out PSNR and training-camera pose errors',
                    ['case', 'steps', 'held-out PSNR (dB)',
                     'held-out PSNR, test cameras registered (dB)', 'rotation error mean (°)',
                     'rotation error max (°)', 'translation error mean (of radius)',
                     'translation error max (of radius)',
                     'rotation error mean after a similarity alignment (°)'], rows)],
        notes=f'Training cameras but image 0 rotated by {args.degrees:g}° about a random axis '
              f'and moved by {args.fraction:g} of the scene radius; held-out poses exact; '
              f'"true" trains on the true poses.')


if __name__ == '__main__':
    main()
