"""Video in, end to end: the poses structure from motion finds for a rendered clip, and the
held-out PSNR of training on its frames against the same frames given with their true poses.

    python benchmarks/video_in.py OUT [--scene gt_plaza.xml] [--res 240x180] [--video-frames 144]
                                  [--frames 48] [--span 180] [--elevation 20] [--bob 5]
                                  [--radius 3.5] [--spp 16] [--blur 9] [--name video_in]
                                  [any optimize training option: --iterations 3000 (default), ...]

1. **clip**: renders ``--video-frames`` frames (24 fps) of a Mitsuba scene of
   :mod:`mi_nerfpp.data.synth` along an orbit looking at the origin (``--span`` degrees of
   azimuth at ``--radius``, the elevation ``--elevation`` +- ``--bob`` degrees, twice up and down
   per turn), with horizontal motion blur (a ``--blur``-pixel box along x, as the end-to-end test
   of ``tests/data/test_video_in.py``) on one frame of every other time window (in turn the first,
   second, ... of its window), and encodes them as H.264 (crf 8) into ``OUT/clip.mp4``, the true
   camera-to-world of every frame in ``OUT/clip.json`` (a second run with the same parameters
   renders nothing). The default half orbit is as wide as SfM registers reliably at 240x180
   (about 450 SIFT features a frame, neighbours matched only up to ~15 degrees apart): a full
   turn with 48 of 144 frames kept registered 26 of them (the chain of neighbours broke), and
   with 96 of 288 kept all 96 but drifted (sequential matching closes no loop: orientations up
   to 1.9 degrees off, centres up to 2.9 % of the radius);
2. **video**: ``colmap OUT/clip.mp4 --frames N --out OUT/video`` (the sharpest frame of each equal
   time window, one shared camera, sequential matching: what ``optimize.py clip.mp4`` runs);
3. **posed**: ``OUT/posed``, a NeRF++ layout of the same chosen frame images (the JPEGs of
   ``OUT/video/video_frames``) with their true poses and true intrinsics, split into train and
   held-out as the video dataset is (every ``hold``-th registered frame in name order held out,
   checked by name against ``OUT/video``);
4. trains each (``OUT/runs/{video,posed}``, from scratch) with one config: the training options
   given, the rest chosen by ``optimize``'s rules for the video dataset
   (:func:`mi_nerfpp.training.choices.from_capture`: for photos per-photo appearance and pose
   refinement on), and scores each on its own held-out views
   (:func:`~mi_nerfpp.training.evaluate.evaluate_split`, NeRF-W style with appearance on).

Printed and written to ``benchmarks/results/<--name>.json``: the frames chosen and how many of
them blurred, the frames registered, the orientation errors after the best rotation (as the test)
and after the rotation of the similarity below, the camera-centre errors after the best similarity
(Umeyama) as a fraction of the orbit's radius, the fitted focal length against the true one, and
the held-out PSNR / SSIM of the two runs, their gap and the PSNR of each held-out view.

Each run is scored on its own held-out images, and they differ: COLMAP's undistortion (of the
small radial term it fits) writes the video dataset's frames one pixel smaller with the principal
point moved by half a pixel, a bilinear resampling at half-pixel offsets that halves their
high-frequency content (Monte Carlo noise included: 0.030 against 0.058 RMS about a 1-pixel
Gaussian on two held-out views at the defaults). The video run's PSNR is against those smoother
targets, the posed run's against the frames as rendered (25.2 dB against clean renders).
"""
import argparse
import json
import os
import shutil

import numpy as np
from scipy import ndimage
from skimage.transform import SimilarityTransform

import mi_nerfpp  # noqa: F401
from mi_nerfpp.commands.cli import main as cli
from mi_nerfpp.data import load_dataset, video
from mi_nerfpp.data.nerfpp import write_camera
from mi_nerfpp.data.sfm import read_report
from mi_nerfpp.data.synth import (CLIP_CRF, CLIP_FPS, DEFAULT_FOV, DEFAULT_RADIUS, encode_clip,
                                  parse_res, scene_file)
from mi_nerfpp.jobs import bench, run
from mi_nerfpp.jobs.console import ConsoleObserver
from mi_nerfpp.training import choices
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.training.evaluate import evaluate_split
from mi_nerfpp.training.options import add_options, values

FPS, CRF = CLIP_FPS, CLIP_CRF
CLIP_VERSION = 1


# ---------------------------------------------------------------------------------- the clip

def orbit(args):
    """(azimuth, elevation) in radians of each frame of the clip."""
    n = args.video_frames
    step = args.span / n if args.span >= 360 else args.span / (n - 1)
    azimuth = np.radians(-args.span / 2 + step * np.arange(n))
    elevation = np.radians(args.elevation + args.bob * np.sin(2 * (azimuth - azimuth[0])))
    return azimuth, elevation


def blurred_frames(args) -> list[int]:
    """One frame of every other time window (window k: frames with floor(i N / count) == k), the
    first of the first such window, the second of the next, ..."""
    window = np.arange(args.video_frames) * args.frames // args.video_frames
    out = []
    for k in range(0, args.frames, 2):
        members = np.flatnonzero(window == k)
        out.append(int(members[(k // 2) % len(members)]))
    return out


def render_clip(args) -> dict:
    """``OUT/clip.mp4`` and ``OUT/clip.json`` (the parameters, the intrinsics, every frame's
    camera-to-world, the blurred frames); reused when the parameters are the same."""
    import mitsuba as mi
    from mi_nerfpp.core.color import to_srgb8
    from mi_nerfpp.data.cameras import Camera, mitsuba_sensor_dict
    from mi_nerfpp.data.synth.trajectories import intrinsics_from_fov, look_at
    width, height = parse_res(args.res)
    params = {'version': CLIP_VERSION, 'scene': args.scene, 'res': [width, height],
              'video_frames': args.video_frames, 'frames': args.frames, 'span': args.span,
              'elevation': args.elevation, 'bob': args.bob, 'radius': args.radius,
              'fov': args.fov, 'spp': args.spp, 'blur': args.blur, 'fps': FPS, 'crf': CRF,
              'mitsuba': mi.__version__}
    clip, record_path = os.path.join(args.out, 'clip.mp4'), os.path.join(args.out, 'clip.json')
    if os.path.isfile(clip) and os.path.isfile(record_path):
        with open(record_path) as f:
            record = json.load(f)
        if record.get('params') == params:
            print(f'{clip}: clip up to date (same parameters); not rendered again', flush=True)
            return record
    os.makedirs(args.out, exist_ok=True)
    scene = mi.load_file(scene_file(args.scene))
    K = intrinsics_from_fov(args.fov, width, height)
    blurred = set(blurred_frames(args))
    frames, poses = [], []
    for i, (azimuth, elevation) in enumerate(zip(*orbit(args))):
        eye = args.radius * np.array([np.cos(elevation) * np.sin(azimuth), np.sin(elevation),
                                      np.cos(elevation) * np.cos(azimuth)])
        camera = Camera(K, look_at(eye, np.zeros(3)), width, height, name=str(i))
        sensor = mi.load_dict(mitsuba_sensor_dict(camera, spp=args.spp, pixel_format='rgb'))
        rgb = np.array(mi.render(scene, sensor=sensor, spp=args.spp, seed=i), dtype=np.float32)
        image = to_srgb8(np.nan_to_num(rgb[..., :3]))
        if i in blurred:
            image = ndimage.uniform_filter1d(image.astype(np.float32), args.blur, axis=1)
            image = np.clip(image, 0, 255).astype(np.uint8)
        frames.append(image)
        poses.append(camera.c2w.tolist())
        if (i + 1) % 24 == 0 or i + 1 == args.video_frames:
            print(f'rendered {i + 1} of {args.video_frames} frames', flush=True)
    encode_clip(clip, frames, fps=FPS, crf=CRF)
    record = {'params': params, 'K': K.tolist(), 'c2w': poses, 'blurred': sorted(blurred)}
    with open(record_path, 'w') as f:
        json.dump(record, f)
    return record


# ---------------------------------------------------------------------------------- poses

def angles_between(pairs, align):
    """Degrees between each true rotation and ``align`` times the found one."""
    return np.degrees([np.arccos(np.clip((np.trace(true.T @ align @ found) - 1) / 2, -1, 1))
                       for true, found in pairs])


def pose_errors(cams, truth, radius):
    """Orientation errors (degrees) after the best rotation (the chordal mean of the per-frame
    differences, as the test) and after the rotation of the best similarity of the centres, and
    the centre errors after that similarity as a fraction of ``radius``; ``truth``: name ->
    true camera-to-world."""
    pairs = [(truth[c.name][:3, :3], c.c2w[:3, :3]) for c in cams]
    U, _, Vt = np.linalg.svd(sum(true @ found.T for true, found in pairs))
    best = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    found = np.array([c.c2w[:3, 3] for c in cams])
    expected = np.array([truth[c.name][:3, 3] for c in cams])
    fit = SimilarityTransform.from_estimate(found, expected)
    turn = fit.params[:3, :3] / np.cbrt(np.linalg.det(fit.params[:3, :3]))
    centres = np.linalg.norm(fit(found) - expected, axis=1) / radius
    return angles_between(pairs, best), angles_between(pairs, turn), centres


def fitted_camera(data):
    """COLMAP's camera of the video dataset (before undistortion): model name and parameters."""
    import pycolmap
    model = pycolmap.Reconstruction(os.path.join(data, 'colmap', 'sparse', '0'))
    (camera,) = model.cameras.values()
    return camera.model.name, [float(v) for v in camera.params]


# ---------------------------------------------------------------------------------- datasets

def split_names(data):
    """{'train': [...], 'test': [...]} image stems of a NeRF++ layout, in name order."""
    out = {}
    for split in ('train', 'test'):
        folder = os.path.join(data, split, 'rgb')
        out[split] = sorted(os.path.splitext(n)[0] for n in os.listdir(folder)) \
            if os.path.isdir(folder) else []
    return out


def write_posed(data, out, record, names):
    """The NeRF++ layout of the chosen frames ``names`` (split -> stems) of the video dataset
    ``data``: its original frame images with their true poses and intrinsics."""
    if os.path.isdir(out):
        shutil.rmtree(out)
    with open(os.path.join(data, video.FOLDER, video.FRAMES_FILE)) as f:
        chosen = {c['file'].rsplit('.', 1)[0]: c for c in json.load(f)['videos'][0]['chosen']}
    from mi_nerfpp.data.cameras import Camera
    w, h = record['params']['res']
    for split, stems in names.items():
        os.makedirs(os.path.join(out, split, 'rgb'))
        for stem in stems:
            frame = chosen[stem]
            shutil.copy2(os.path.join(data, video.FOLDER, frame['file']),
                         os.path.join(out, split, 'rgb', frame['file']))
            write_camera(os.path.join(out, split), stem,
                         Camera(np.array(record['K']), np.array(record['c2w'][frame['index']]),
                                w, h, stem))


# ---------------------------------------------------------------------------------- training

def train_and_score(label, data, cfg, out):
    dataset = load_dataset(data, downscale=cfg.data.downscale or 1,
                           background=cfg.data.background)
    folder = os.path.join(out, 'runs', label)
    run.check_run_folder(folder, resume=False, overwrite=True)
    observer = ConsoleObserver(f'train {label}')
    trainer = run.start(run.RunInputs(dataset.root, dataset, cfg, folder), observer=observer)
    run.train(trainer, observer)
    result = evaluate_split(trainer.model, trainer.test, os.path.join(folder, 'test'),
                            fit_appearance=cfg.model.per_photo_appearance)
    names = [os.path.splitext(os.path.basename(p))[0] for p in trainer.test.image_paths]
    print(f'{label}: {trainer.iteration} steps: held-out PSNR {result["psnr"]:.2f} dB, SSIM '
          f'{result["ssim"]:.3f}', flush=True)
    return trainer.iteration, result, names


def main():
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('out', help='work folder: the clip, the two datasets, the runs')
    p.add_argument('--scene', default='gt_plaza.xml', help='a scene of scenes/ (synth)')
    p.add_argument('--res', default='240x180')
    p.add_argument('--video-frames', type=int, default=144, help='frames of the clip (24 fps)')
    p.add_argument('--frames', type=int, default=48, help='frames kept (colmap --frames)')
    p.add_argument('--span', type=float, default=180.0, help='degrees of azimuth swept')
    p.add_argument('--elevation', type=float, default=20.0, help='mean elevation, degrees')
    p.add_argument('--bob', type=float, default=5.0,
                   help='elevation amplitude, degrees (twice up and down per 360 degrees)')
    p.add_argument('--radius', type=float, default=DEFAULT_RADIUS, help='orbit radius')
    p.add_argument('--fov', type=float, default=DEFAULT_FOV, help='horizontal field of view')
    p.add_argument('--spp', type=int, default=16, help='samples per pixel of the clip')
    p.add_argument('--blur', type=int, default=9, help='motion blur box width, pixels')
    p.add_argument('--name', default='video_in')
    add_options(p, TrainConfig)
    args = p.parse_args()
    if not 2 <= args.frames <= args.video_frames:
        raise SystemExit('error: video_in: --frames must be from 2 to --video-frames')
    options = dict(values(args, TrainConfig), checkpoint_every=0, preview_every=0)
    if not options.get('minutes'):
        options['iterations'] = options['iterations'] or 3000

    record = render_clip(args)
    truth_c2w = np.array(record['c2w'])
    blurred = set(record['blurred'])
    data, posed = os.path.join(args.out, 'video'), os.path.join(args.out, 'posed')
    clip = os.path.join(args.out, 'clip.mp4')
    if cli(['colmap', clip, '--frames', str(args.frames), '--out', data]) != 0:
        raise SystemExit('error: video_in: colmap failed (see above)')
    with open(os.path.join(data, video.FOLDER, video.FRAMES_FILE)) as f:
        entry = json.load(f)['videos'][0]
    chosen = [c['index'] for c in entry['chosen']]
    report = read_report(data)
    registered = report['registered']

    # The split: every hold-th registered frame in name order held out (sfm._write_dataset).
    hold = report['params']['hold']
    stems = sorted(os.path.splitext(n)[0] for n in registered)
    expected = {'train': [s for i, s in enumerate(stems) if not (hold and i % hold == 0)],
                'test': [s for i, s in enumerate(stems) if hold and i % hold == 0]}
    names = split_names(data)
    if names != expected:
        raise SystemExit(f'error: video_in: {data} splits its frames as {names}, not every '
                         f'{hold}-th held out as expected ({expected})')
    write_posed(data, posed, record, names)
    if split_names(posed) != names:
        raise SystemExit(f'error: video_in: {posed} does not split its frames as {data}')

    # Poses against the truth.
    ds = load_dataset(data)
    truth = {c['file'].rsplit('.', 1)[0]: truth_c2w[c['index']] for c in entry['chosen']}
    best, similar, centres = pose_errors(ds.train.cameras + ds.test.cameras, truth, args.radius)
    model_name, params = fitted_camera(data)
    K = np.array(record['K'])
    fitted_K = ds.train.cameras[0].K / ds.train.cameras[0].K[2, 2]
    # The dataset's K is in its own pixels (undistorted, maybe cropped); the focal length does
    # not change with a crop.
    undistorted = (ds.train.cameras[0].width, ds.train.cameras[0].height)
    focal_error = (fitted_K[0, 0] / K[0, 0] - 1)

    cfg = choices.from_capture(TrainConfig.from_options(**options), ds, notice=print)
    rows, views = [], {}
    for label, root in (('video', data), ('posed', posed)):
        steps, result, test_names = train_and_score(label, root, cfg, args.out)
        rows.append([label, steps, result['psnr'], result.get('psnr_neutral', result['psnr']),
                     result['ssim'], min(v['psnr'] for v in result['views'])])
        views[label] = dict(zip(test_names, (v['psnr'] for v in result['views'])))
    if list(views['video']) != list(views['posed']):
        raise SystemExit(f'error: video_in: the runs held out different views: {views}')
    gap = rows[1][2] - rows[0][2]

    w, h = parse_res(args.res)
    sfm_rows = [
        ['clip', f'{args.scene}, {w}x{h}, {args.video_frames} frames at {FPS} fps, '
                 f'{args.span:g} deg orbit, {len(blurred)} blurred'],
        ['frames chosen', len(chosen)],
        ['blurred frames chosen', len(set(chosen) & blurred)],
        ['registered', f'{len(registered)} of {len(chosen)}'],
        ['train / held-out views', f'{len(names["train"])} / {len(names["test"])}'],
        ['orientation error after the best rotation, max / mean (deg)',
         f'{best.max():.3f} / {best.mean():.3f}'],
        ['orientation error after the similarity, max / mean (deg)',
         f'{similar.max():.3f} / {similar.mean():.3f}'],
        ['camera-centre error after the best similarity, max / mean (% of the radius)',
         f'{100 * centres.max():.3f} / {100 * centres.mean():.3f}'],
        ['COLMAP camera', f'{model_name} {", ".join(f"{v:.4g}" for v in params)}'],
        ['focal length fitted (undistorted, px) / true', f'{fitted_K[0, 0]:.2f} / {K[0, 0]:.2f} '
         f'({100 * focal_error:+.2f} %)'],
        ['principal point fitted / true (px)', f'({fitted_K[0, 2]:.1f}, {fitted_K[1, 2]:.1f}) / '
         f'({K[0, 2]:.1f}, {K[1, 2]:.1f}); undistorted images {undistorted[0]}x'
         f'{undistorted[1]}'],
    ]
    print('\nStructure from motion on the clip')
    for label, value in sfm_rows:
        print(f'  {label:<78} {value}')
    print(f'\nHeld-out scores (each run on its own held-out views; options: '
          f'{bench.changed_options(cfg)})')
    print(f'  {"run":<8} {"steps":>6} {"PSNR":>7} {"neutral":>8} {"SSIM":>6} {"worst":>7}')
    for label, steps, psnr, neutral, ssim, worst in rows:
        print(f'  {label:<8} {steps:>6} {psnr:7.2f} {neutral:8.2f} {ssim:6.3f} {worst:7.2f}')
    print(f'  gap (posed - video): {gap:+.2f} dB')
    print('\nHeld-out PSNR of each view (dB)')
    print(f'  {"view":<16} {"video":>7} {"posed":>7}')
    for name in views['video']:
        print(f'  {name:<16} {views["video"][name]:7.2f} {views["posed"][name]:7.2f}')

    path = bench.write_results(args.name, 'Video in: poses and held-out PSNR against true poses', [
        bench.table('Structure from motion on the rendered clip', ['measure', 'value'], sfm_rows),
        bench.table('Held-out scores, each run on its own held-out views',
                    ['run', 'steps', 'PSNR (dB)', 'PSNR neutral (dB)', 'SSIM',
                     'worst view (dB)'], rows + [['gap (posed - video)', '', gap, '', '', '']],
                    note=f'video: trained on OUT/video (colmap CLIP --frames {args.frames}); '
                         f'posed: the same frame images with their true poses and intrinsics, '
                         f'the same split; one config ({bench.changed_options(cfg)}).'),
        bench.table('Held-out PSNR of each view (dB)', ['view', 'video', 'posed'],
                    [[n, views['video'][n], views['posed'][n]] for n in views['video']])],
        raw={'chosen': chosen, 'blurred': sorted(blurred), 'registered': registered,
             'orientation_best_deg': best, 'orientation_similarity_deg': similar,
             'centre_error_of_radius': centres, 'colmap_camera': [model_name, params],
             'true_K': K, 'fitted_K': fitted_K})
    print(f'results: {path}')


if __name__ == '__main__':
    main()
