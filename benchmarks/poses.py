"""Held-out PSNR and pose errors without and with ``--refine-poses`` on perturbed poses.

    python benchmarks/poses.py DATA OUT [--degrees D] [--fraction F] [--iterations N]
                               [any optimize training option]

Copies the NeRF++-layout capture ``DATA`` to ``OUT/perturbed`` with perturbed training poses
(:func:`mi_nerfpp.data.synth.perturb_poses`: each training camera but image 0 rotated by
``--degrees`` about a random axis and moved by ``--fraction`` of the scene radius; held-out
poses exact), trains ``--iterations`` steps (default 300) from scratch without and with
``--refine-poses`` (otherwise the same options), and prints for each the held-out PSNR (test
views rendered at their given, exact poses: the training loss never refines them) and the
training cameras' rotation (degrees) and translation (fraction of the scene radius) errors
against the true poses, mean and max over the perturbed cameras. Results:
``benchmarks/results/poses.json``.
"""
import argparse
import os

import mi_nerfpp  # noqa: F401
from mi_nerfpp.jobs import bench
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


def main():
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('data')
    p.add_argument('out')
    p.add_argument('--degrees', type=float, default=1.0)
    p.add_argument('--fraction', type=float, default=0.01)
    add_options(p, TrainConfig)
    args = p.parse_args()
    options = dict(values(args, TrainConfig), checkpoint_every=0, preview_every=0, minutes=None)
    options['iterations'] = options['iterations'] or 300
    options.pop('refine_poses', None)
    cfg = TrainConfig.from_options(**options)
    perturbed = os.path.join(args.out, 'perturbed')
    record = perturb_poses(args.data, perturbed, args.degrees, args.fraction, seed=1)
    rot, trans = errors(record['given'], record)
    print(f'given poses: rotation error mean {rot.mean():.3f}° max {rot.max():.3f}°, '
          f'translation error mean {trans.mean():.4f} max {trans.max():.4f} of the radius',
          flush=True)
    rows = [['given poses', '-', '-', rot.mean(), rot.max(), trans.mean(), trans.max()]]
    dataset = load_dataset(perturbed)
    for on, run, tr, r in bench.without_and_with(dataset, cfg, args.out, 'refine_poses',
                                                 observer=ConsoleObserver('train')):
        rot, trans = errors(poses.world_poses(tr.model, tr.train.cameras), record)
        print(f'refine_poses={on!s:5} {run.schedule.iterations} steps: held-out PSNR '
              f'{r["psnr"]:.2f} dB; rotation error mean {rot.mean():.3f}° max {rot.max():.3f}°, '
              f'translation error mean {trans.mean():.4f} max {trans.max():.4f} of the radius',
              flush=True)
        rows.append([f'--{"" if on else "no-"}refine-poses', run.schedule.iterations,
                     r['psnr'], rot.mean(), rot.max(), trans.mean(), trans.max()])
    bench.write_results('poses', 'Camera pose refinement on perturbed poses', [
        bench.table('Held-out PSNR and training-camera pose errors',
                    ['poses', 'iterations', 'held-out PSNR (dB)', 'rotation error mean (°)',
                     'rotation error max (°)', 'translation error mean (of radius)',
                     'translation error max (of radius)'], rows)],
        notes=f'Training cameras but image 0 rotated by {args.degrees:g}° about a random axis '
              f'and moved by {args.fraction:g} of the scene radius; held-out poses exact.')


if __name__ == '__main__':
    main()
