"""Paper §3, Figure 4 / Table 1: NeRF's MLP structure versus a vanilla MLP, and the same with grids.

    python experiments/mlp_structure.py [--mlp-iterations 2000] [--grid-iterations 2000]

The capture (DTU-like): ``scenes/gt_bounded.xml`` (a still life on black) from a front arc of
cameras (``synth --trajectory arc``: distance 3.5, 128x96 pixels, 30 degree field of view,
64 spp). 46 views: 36 train cameras spread over azimuth -50..50 degrees and elevation
10..40 degrees; **interpolation** test views: 5 random views inside that range (the capture's
validation split); **extrapolation** test views: 5 views at |azimuth| 65..90 degrees on either
side, same elevations (its test split).

The models, all trained from scratch with NeRF++ (``mi_nerfpp.training.train.Trainer``), the background
volume a grid field in every run so that only the foreground field differs:

* pure MLPs (depth 4, width 64), ``--mlp-iterations`` steps each:
  NeRF-MLP (σ and a feature from a γ^10(x) trunk, γ^4(d) injected at a one-layer colour head)
  versus vanilla (same σ trunk; colour from a separate 4-layer MLP with γ^10(x) and γ^10(d)
  at its input);
* grid + MLP fields, ``--grid-iterations`` steps each: the late-injection colour head (grid
  features and γ^4(d) into one hidden layer of 32; the default until 2026-11-25, γ^2(d) since),
  the same head with γ^10(d), and a vanilla-style head (features and γ^10(d) into 4 hidden
  layers of 64).

Same batch (512 rays), samples (32 coarse + 32 fine per volume), learning rates and seed for
all. Reported: PSNR / SSIM over the full images and PSNR over the object's pixels (ground-truth
mask; the paper masks the background out) on both test splits, plus 5 training views. Writes
``FIGURES/mlp_structure.{md,json,png}`` (default FIGURES: docs/results). About 17 minutes of
training on a 2-core CPU at the defaults, plus evaluation.
"""
import os

import common   # experiments/common.py, next to this script (on sys.path when it runs)

RUNS = [
    # name, family, TrainConfig options
    ('NeRF-MLP', 'mlp', dict(field='nerf', bg_field='grid')),
    ('vanilla MLP', 'mlp', dict(field='vanilla', bg_field='grid')),
    ('grid, γ^4(d) late (default until 2026-11-25)', 'grid', dict(dir_octaves=4)),
    ('grid, γ^10(d) late', 'grid', dict(dir_octaves=10)),
    ('grid, vanilla colour MLP', 'grid', dict(dir_octaves=10, color_layers=4, color_width=64)),
]


def main():
    ap = common.parser(__doc__, 'mlp_structure')
    ap.add_argument('--mlp-iterations', type=int, default=2000,
                    help='training steps of each pure-MLP model (default 2000)')
    ap.add_argument('--grid-iterations', type=int, default=2000,
                    help='training steps of each grid model (default 2000)')
    ap.add_argument('--lr-mlp', type=float, default=5e-3, help='MLP learning rate (default 5e-3)')
    ap.add_argument('--views', type=int, default=46, help='views of the capture (default 46: '
                    '36 train, 5 interpolation, 5 extrapolation)')
    ap.add_argument('--res', default='128x96', help='image size (default 128x96)')
    ap.add_argument('--spp', type=int, default=64, help='samples per pixel of the capture')
    ap.add_argument('--only', choices=['mlp', 'grid'], help='run one family only')
    a = ap.parse_args()

    import numpy as np

    from mi_nerfpp.data import load_dataset
    from mi_nerfpp.training.metrics import psnr
    from mi_nerfpp.training.config import TrainConfig

    data = common.capture(a.data_cache, 'arc', views=a.views, res=a.res, fov=30.0, spp=a.spp,
                          trajectory='arc', seed=0)
    ds = load_dataset(data)
    train_views = list(range(0, len(ds.train), 8))
    splits = {'interpolation': ds.validation, 'extrapolation': ds.test,
              'train': common.subset(ds.train, train_views)}
    masks = {'interpolation': common.object_masks(data, 'validation'),
             'extrapolation': common.object_masks(data, 'test'),
             'train': [common.object_masks(data, 'train')[i] for i in train_views]}

    results, images = {}, {}
    for name, family, options in RUNS:
        if a.only and family != a.only:
            continue
        iterations = a.mlp_iterations if family == 'mlp' else a.grid_iterations
        cfg = TrainConfig.from_options(iterations=iterations, preview_every=0,
                                       checkpoint_every=0, lr_mlp=a.lr_mlp, **options)
        slug = name.split(' (')[0].replace(',', '').replace('^', '').replace(' ', '_')
        trainer = common.train(ds, os.path.join(a.out, slug), cfg)
        preds = {s: common.render_views(trainer.model, splits[s]) for s in splits}
        r = {s: common.score(preds[s], splits[s].images, masks[s]) for s in splits}
        r.update(family=family, iterations=iterations, seconds=round(trainer.elapsed, 1),
                 parameters=trainer.model.n_parameters(), options=options)
        results[name], images[name] = r, preds
        print(f"{name}: interpolation {r['interpolation']['psnr']:.2f} dB, extrapolation "
              f"{r['extrapolation']['psnr']:.2f} dB, train {r['train']['psnr']:.2f} dB "
              f"({trainer.elapsed:.0f} s of training)")

    # What predicting black everywhere scores (the scene's background is black).
    blank = {s: common.score([0 * g for g in splits[s].images], splits[s].images, masks[s])
             for s in splits}
    rows = []
    for name, r in results.items():
        i, e, tr = r['interpolation'], r['extrapolation'], r['train']
        rows.append([name, f"{i['psnr']:.2f} / {e['psnr']:.2f}",
                     f"{i['psnr_object']:.2f} / {e['psnr_object']:.2f}",
                     f"{i['ssim']:.3f} / {e['ssim']:.3f}", f"{tr['psnr']:.2f}",
                     r['iterations'], f"{r['seconds']:.0f}", f"{r['parameters'] / 1e6:.2f} M"])
    rows.append(['black image (reference)',
                 f"{blank['interpolation']['psnr']:.2f} / {blank['extrapolation']['psnr']:.2f}",
                 '-', f"{blank['interpolation']['ssim']:.3f} / {blank['extrapolation']['ssim']:.3f}",
                 f"{blank['train']['psnr']:.2f}", '-', '-', '-'])
    table = common.markdown_table(
        ['foreground field', 'PSNR interp. / extrap.', 'object PSNR interp. / extrap.',
         'SSIM interp. / extrap.', 'train PSNR', 'iterations', 'training time (s)', 'parameters'], rows)
    print('\n' + table)
    suffix = f'_{a.only}' if a.only else ''
    common.write_results(os.path.join(a.figures, f'mlp_structure{suffix}.json'),
                         {'capture': os.path.relpath(data, common.ROOT), 'black_image': blank,
                          'train_views': train_views, 'results': results})
    with open(os.path.join(a.figures, f'mlp_structure{suffix}.md'), 'w') as f:
        f.write(table + '\n')

    # Figure: one interpolated and one extrapolated view per model (the worst-scoring of each
    # split under the first model, where the differences show most).
    first = next(iter(results))
    pick = {s: int(np.argmin([psnr(np.clip(p, 0, 1), g) for p, g in
                              zip(images[first][s], splits[s].images)]))
            for s in ('interpolation', 'extrapolation')}
    panels = []
    for s in ('interpolation', 'extrapolation'):
        gt = splits[s].images[pick[s]]
        row = [(gt, 'ground truth')]
        for name in results:
            p = images[name][s][pick[s]]
            row.append((p, f'{psnr(np.clip(p, 0, 1), gt):.1f} dB'))
        panels.append(row)
    common.figure(panels, ['interpolation', 'extrapolation'], ['ground truth'] + list(results),
                  os.path.join(a.figures, f'mlp_structure{suffix}.png'))
    print(f"wrote {a.figures}/mlp_structure{suffix}.md, .json, .png")


if __name__ == '__main__':
    main()
