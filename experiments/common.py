"""What the paper-reproduction scripts share: captures, training, scoring, tables, figures."""
from __future__ import annotations

import dataclasses
import json
import os
import time

import numpy as np

import mi_nerfpp  # noqa: F401  (libLLVM, variant, plugin registration)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FIGURES = os.path.join(ROOT, 'docs', 'results')


def parser(doc, name):
    """Command line of an experiment: its docstring as help, ``--out`` and ``--figures``."""
    import argparse
    ap = argparse.ArgumentParser(description=doc,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--out', default=os.path.join(ROOT, 'runs', 'experiments', name),
                    help=f'where the training runs go (default runs/experiments/{name})')
    ap.add_argument('--figures', default=FIGURES,
                    help='where the table, JSON and figure go (default docs/results)')
    ap.add_argument('--data-cache', default=os.path.join(ROOT, 'data_cache', 'experiments'),
                    help='where the capture is rendered (default data_cache/experiments)')
    return ap


def capture(cache, name, **synth):
    """Render (or reuse) the capture ``name`` of the bounded still life under ``cache``."""
    from mi_nerfpp.data.synth import scene_file, synthesize
    out = os.path.join(cache, name)
    synthesize(scene_file('gt_bounded.xml'), out, **synth)
    return out


def subset(split, indices):
    """The views ``indices`` of a split."""
    return dataclasses.replace(split, cameras=[split.cameras[i] for i in indices],
                               image_paths=[split.image_paths[i] for i in indices],
                               images=[split.images[i] for i in indices])


def object_masks(data, split_name):
    """Per-view ground-truth masks of the still life (``fg.A`` of the synthetic capture)."""
    from mi_nerfpp.files.exr import read_exr
    folder = os.path.join(data, split_name, 'gt')
    return [read_exr(os.path.join(folder, f))['fg.A'] > 0.5 for f in sorted(os.listdir(folder))]


def score(preds, images, masks=None):
    """Mean PSNR / SSIM over views; ``masks``: also PSNR over the object's pixels only."""
    from mi_nerfpp.training.metrics import psnr, ssim
    preds = [np.clip(p, 0.0, 1.0) for p in preds]
    out = {'psnr': float(np.mean([psnr(p, g) for p, g in zip(preds, images)])),
           'ssim': float(np.mean([ssim(p, g) for p, g in zip(preds, images)])),
           'views': len(preds)}
    if masks is not None:
        out['psnr_object'] = float(np.mean([psnr(p[m][None], g[m][None]) for p, g, m in
                                            zip(preds, images, masks)]))
    return out


def train(dataset, out, cfg):
    """Train a NeRF++ model (:mod:`mi_nerfpp.jobs.run`) with a progress bar; returns the Trainer.

    A finished run of the same configuration in ``out`` is reused (its checkpoint is loaded,
    nothing is trained), so a script re-run only re-evaluates; ``trainer.elapsed`` is the
    training time either way. An unfinished or different run there is trained afresh.
    """
    from mi_nerfpp.jobs import run
    from mi_nerfpp.files.checkpoint import load_checkpoint
    from mi_nerfpp.jobs.console import ConsoleObserver
    path = os.path.join(out, 'model.npz')
    reuse = False
    if os.path.exists(path):
        _, meta, _ = load_checkpoint(path)
        reuse = (meta.get('config') == cfg.to_dict()
                 and meta.get('iteration') == cfg.schedule.iterations)
    inputs = run.RunInputs(dataset.root, dataset, cfg, out)
    if reuse:
        print(f'{out}: reusing the finished run ({cfg.schedule.iterations} iterations)')
        return run.start(inputs, resume=True)
    observer = ConsoleObserver(desc=os.path.basename(out))
    trainer = run.start(inputs, observer=observer)
    run.train(trainer, observer)
    return trainer


def render_views(model, split):
    """RGB renders of every view of a split through the ``nerfpp`` integrator (with the
    model's render settings: the sample counts it was trained with), in the encoding of the
    model's training images (comparable with them)."""
    from mi_nerfpp.output.views import ViewRenderer, encoded_rgb
    renderer = ViewRenderer(model)
    return [encoded_rgb(renderer.render(cam), model.color_space) for cam in split.cameras]


def markdown_table(header, rows):
    lines = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    lines += ['| ' + ' | '.join(str(c) for c in row) + ' |' for row in rows]
    return '\n'.join(lines)


def figure(panels, row_labels, col_labels, path, scale=1.6):
    """A grid of images (rows of (image, caption)) with row and column labels."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    n_rows, n_cols = len(panels), len(panels[0])
    h, w = panels[0][0][0].shape[:2]
    fig, axes = plt.subplots(n_rows, n_cols, squeeze=False,
                             figsize=(scale * n_cols * w / h + 0.8, scale * n_rows + 0.5))
    for r, row in enumerate(panels):
        for c, (img, caption) in enumerate(row):
            ax = axes[r][c]
            ax.imshow(np.clip(img, 0, 1), interpolation='nearest')
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_xlabel(caption, fontsize=8)
            if r == 0:
                ax.set_title(col_labels[c], fontsize=9)
            if c == 0:
                ax.set_ylabel(row_labels[r], fontsize=9)
    fig.tight_layout()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_results(path, results):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, 'w') as f:
        json.dump(results, f, indent=2)


class Timer:
    def __enter__(self):
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.t0
