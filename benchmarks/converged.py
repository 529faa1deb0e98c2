"""How far a trained model is from the truth, without the capture's Monte Carlo noise.

    python benchmarks/converged.py RUN [--spp 1024] [--train-every 8]

A synthetic capture's images are 64-spp renders: a model scored against them loses points to
their noise too (``benchmarks/noise_ceiling.py``). For a run of a synthetic capture (a folder
written by ``optimize``), this renders every test view and every ``--train-every``-th training
view of the ground-truth scene at ``--spp`` samples per pixel (close to converged; cached next
to the capture in ``DATA/converged/``, keyed by camera, scene file and spp), and prints per view,
in the 8-bit sRGB encoding of the capture:

* ``capture``: PSNR of the capture's image against the converged one (its noise);
* ``model``: PSNR of the model's render against the converged image, also over the pixels
  inside and outside the true foreground mask (``gt/*.exr``'s ``fg.A``);
* ``blur``: the standard deviation, in pixels, of the Gaussian blur of the converged image
  that scores the same PSNR as the model (``mi_nerfpp.training.metrics.equivalent_blur``: how blurred
  the reconstruction is, as one number; ``inf`` where errors other than blur dominate);
* ``far`` and ``near``: where the background is, over the pixels outside the true mask whose
  ray hits a surface (not the sky): the share whose rendered ``depth.Z`` is more than
  ``FAR``x the true depth (content painted at infinity) and the share within ``NEAR`` of it.

Results: ``benchmarks/results/converged.json``.
"""
import argparse
import glob
import hashlib
import json
import os

import numpy as np

import mi_nerfpp  # noqa: F401
import mitsuba as mi
from mi_nerfpp.jobs import bench
from mi_nerfpp.jobs.bench import render_encoded
from mi_nerfpp.files.exr import read_exr
from mi_nerfpp.training.metrics import equivalent_blur, masked_psnr, psnr
from mi_nerfpp.jobs.run import open_run
from mi_nerfpp.output.views import ViewRenderer, encoded_rgb

FAR = 4.0      # a depth more than this many times the truth counts as 'at infinity'
NEAR = 0.25    # relative depth error that counts as 'right'


def converged(scene, scene_sha, world_camera, spp, cache):
    """The view rendered at ``spp`` (8-bit sRGB as float), cached under its key in ``cache``."""
    key = hashlib.sha256(json.dumps([scene_sha, spp, world_camera.K.tolist(),
                                     world_camera.c2w.tolist(), world_camera.width,
                                     world_camera.height]).encode()).hexdigest()[:16]
    path = os.path.join(cache, f'{key}.npy')
    if os.path.isfile(path):
        return np.load(path)
    image = render_encoded(scene, world_camera, spp, seed=104729)
    os.makedirs(cache, exist_ok=True)
    tmp = path + '.tmp.npy'
    np.save(tmp, image)
    os.replace(tmp, path)
    return image


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('run', help='run folder written by optimize on a synthetic capture')
    ap.add_argument('--spp', type=int, default=1024)
    ap.add_argument('--train-every', type=int, default=8)
    a = ap.parse_args()
    model, _, _, dataset = open_run(a.run)
    data = dataset.root
    try:
        with open(os.path.join(data, 'capture.json')) as f:
            capture = json.load(f)
    except OSError:
        raise SystemExit(f'{data}: no capture.json; this benchmark needs a capture written by '
                         f'`python -m mi_nerfpp synth`') from None
    scene = mi.load_file(capture['scene_path'])
    renderer = ViewRenderer(model)       # with the model's render settings
    cache = os.path.join(data, 'converged')
    print(f'{"view":>10} {"capture":>8} {"model":>6} {"fg":>6} {"bg":>6} {"blur px":>7} '
          f'{"far":>5} {"near":>5}')
    rows, table_rows, means = {}, [], []
    for split, step in (('train', a.train_every), ('test', 1)):
        views = getattr(dataset, split)
        gts = sorted(glob.glob(os.path.join(data, split, 'gt', '*.exr')))
        for i in range(0, len(views), step):
            camera = views.cameras[i]
            truth = converged(scene, capture['scene_sha256'],
                              dataset.normalization.to_world_camera(camera), a.spp, cache)
            layers = renderer.render(camera)
            pred = np.clip(encoded_rgb(layers, model.color_space), 0, 1)
            gt = read_exr(gts[i])
            inside = gt['fg.A'] > 0.5
            row = [psnr(views.images[i], truth), psnr(pred, truth), masked_psnr(pred, truth, inside),
                   masked_psnr(pred, truth, ~inside)]
            row.append(equivalent_blur(pred, truth))
            surface = ~inside & (gt['depth.Z'] > 0)
            true_z = gt['depth.Z'][surface]
            z = layers['depth.Z'][surface]
            row += [np.mean(z > FAR * true_z), np.mean(np.abs(z - true_z) < NEAR * true_z)]
            rows.setdefault(split, []).append(row)
            table_rows.append([split, i] + row)
            print(f'{split:>5} {i:4d} {row[0]:8.2f} {row[1]:6.2f} {row[2]:6.2f} {row[3]:6.2f} '
                  f'{row[4]:7.2f} {100 * row[5]:4.0f}% {100 * row[6]:4.0f}%', flush=True)
    for split, values in rows.items():
        m = np.nanmean(np.array(values), axis=0)
        print(f'{split} mean: capture {m[0]:.2f} dB, model {m[1]:.2f} dB (foreground {m[2]:.2f}, '
              f'background {m[3]:.2f}), as blurred as the converged image by a Gaussian of '
              f'{np.median([v[4] for v in values]):.2f} px (median); background depth: '
              f'{100 * m[5]:.0f} % of its surface pixels beyond {FAR:g}x the truth, '
              f'{100 * m[6]:.0f} % within {100 * NEAR:.0f} %')
        means.append([split] + list(m[:4]) + [np.median([v[4] for v in values])]
                     + [100 * m[5], 100 * m[6]])
    columns = ['capture PSNR (dB)', 'model PSNR (dB)', 'foreground (dB)', 'background (dB)',
               'blur (px)', f'far: beyond {FAR:g}x (%)', f'near: within {100 * NEAR:.0f} % (%)']
    bench.write_results('converged', 'Distance of a trained model from the converged truth', [
        bench.table('Mean per split (blur: median)', ['split'] + columns, means),
        bench.table('Per view', ['split', 'view'] + columns,
                    [r[:7] + [100 * r[7], 100 * r[8]] for r in table_rows])],
        notes=f'Run {a.run}; converged images rendered at {a.spp} spp; PSNR in the 8-bit sRGB '
              f'encoding of the capture.')


if __name__ == '__main__':
    main()
