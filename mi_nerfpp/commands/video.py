"""``python -m mi_nerfpp video RUN``: a novel-view video (orbit, test path or a camera path file)
of a training run.

Frames are written to a frames folder first (PNG, and the multi-layer EXR with ``--exr``), each
atomically; frames already there are skipped, so a re-run resumes an interrupted job. With
``--ray`` the frames are rendered by workers on a Ray cluster (:mod:`mi_nerfpp.jobs.cluster`), with
the same function as in one process. The video is assembled from the PNGs. ``--path FILE`` renders
a camera path file (:mod:`mi_nerfpp.output.camera_path`, drawn in the viewer's path editor), or a
tracked camera (:mod:`mi_nerfpp.output.tracked_camera`: USD, Nuke ``.chan``, nerfstudio's
``camera_path.json``; ``--camera NAME`` picks a USD camera, ``--frame-range`` limits the frames),
whose frame files carry the file's name and frame numbers (``shot.1001.exr``); ``--write-path
FILE`` writes the orbit or test path in that format instead of rendering it.
"""
from __future__ import annotations

import argparse
import os
from dataclasses import dataclass

from tqdm import tqdm

from mi_nerfpp.commands.arguments import (frame_range, positive_int,
                                          resolution, whole_between)
from mi_nerfpp.core import budget
from mi_nerfpp.files.atomic import remove_stale_temporaries
from mi_nerfpp.jobs.cluster import (FramePool, FrameWorker, check_address,
                                    cluster_cpus, session, timeout_line)
from mi_nerfpp.integrator.loading import check_appearance
from mi_nerfpp.jobs.run import open_run
from mi_nerfpp.output.camera_path import (DEFAULT_FPS, path_cameras,
                                          read_path, write_path)
from mi_nerfpp.output.tracked_camera import (capture_normalizations, digest,
                                             read_shot, shot_format)
from mi_nerfpp.output.video import (BUILT_IN_PATHS, FRAME_NAME,
                                    built_in_cameras, built_in_path,
                                    check_video_path, pending_frames,
                                    prepare_frames_dir, read_frames,
                                    write_video)


def add_parser(sub):
    p = sub.add_parser('video', help='render a novel-view video of a training run')
    p.add_argument('run', help='run folder written by optimize (holds model.npz)')
    p.add_argument('-o', '--output', help='.mp4 or .gif (default: RUN/video.mp4)')
    p.add_argument('--path', default='orbit', metavar='orbit|test|FILE',
                   help="an orbit around the scene, the dataset's test cameras, a camera path "
                        "file (JSON, as the viewer's path editor or --write-path saves it; its "
                        'resolution, fps and cameras in the world frame), or a tracked camera: '
                        "USD (.usd/.usda/.usdc/.usdz), Nuke .chan or nerfstudio's "
                        "camera_path.json, in the frame of export's files, its frames named "
                        "after the file and its frame numbers (NAME.1001.png) (default: orbit)")
    p.add_argument('--camera', metavar='NAME',
                   help='with --path FILE.usd: the camera to render, of several (its prim name, '
                        "its parent's, as Blender names the object, or its path)")
    p.add_argument('--frame-range', type=frame_range, metavar='FIRST-LAST',
                   help="with a tracked camera: render only its frames FIRST to LAST (the file's "
                        'frame numbers; default: all)')
    p.add_argument('--frames', type=positive_int, default=60, help='orbit frames (default 60)')
    p.add_argument('--fps', type=positive_int,
                   help="frames per second (default: the path or camera file's, else 24)")
    p.add_argument('--res', type=resolution, metavar='WxH',
                   help="WxH (default: a path file's resolution, nerfstudio's render size, else "
                        "the training images' (a USD camera's: their width, its film's aspect); "
                        "a path file's cameras keep their vertical field of view)")
    p.add_argument('--write-path', metavar='FILE',
                   help='write the cameras of the video (orbit or test) as a camera path file '
                        'that the viewer loads into its path editor, and render nothing')
    p.add_argument('--exr', action='store_true',
                   help='also write every frame as a multi-layer EXR (all layers) next to its PNG')
    p.add_argument('--skip-empty', action=argparse.BooleanOptionalAction, default=True,
                   help='skip the space the occupancy grids mark empty, as training did '
                        '(default); --no-skip-empty samples whole rays: slower, and paths that '
                        'leave the captured ring show no rectangular cells where few training '
                        'rays looked')
    p.add_argument('--appearance-image', type=whole_between(-1, 2 ** 31 - 1), default=-1,
                   metavar='N', help="render with training image N's appearance (its colour "
                   'transform of --appearance, its code of --appearance-embedding); -1: the '
                   'neutral appearance (default)')
    p.add_argument('--frames-dir', metavar='DIR',
                   help='where the frames go (default: the output path without its extension, '
                        'plus _frames); frames already there are not rendered again')
    add_ray_options(p, 'render the frames on a Ray cluster')
    p.add_argument('--workers', type=positive_int,
                   help='with --ray: frame workers (default: the cluster CPUs / --worker-cpus)')
    p.add_argument('--worker-cpus', type=positive_int, default=1,
                   help='with --ray: CPUs (Dr.Jit threads) of each frame worker (default 1)')
    p.set_defaults(func=run)
    return p


def add_ray_options(p, what):
    """``--ray [auto|ADDRESS]`` (shared by the commands that can use a cluster)."""
    p.add_argument('--ray', nargs='?', const='auto', metavar='auto|ADDRESS',
                   help=f'{what}: auto joins the running cluster (ray start) or starts a local '
                        f'one; ADDRESS joins that cluster. Needs pip install -e \'.[cluster]\'')


@dataclass
class Frames:
    """What a video renders: the run's checkpoint path, the cameras by frame index (model
    frame), the description of the job, the name pattern of the frame files and the frames
    per second of the path (None: not the path's to say)."""
    checkpoint: str
    cameras: dict
    job: dict
    name: str = FRAME_NAME
    fps: float | None = None


def cameras_of(args):
    """The run's checkpoint path, the video's cameras (in order) and the description of the
    job (:func:`frames_of`)."""
    frames = frames_of(args)
    return frames.checkpoint, list(frames.cameras.values()), frames.job


def frames_of(args) -> Frames:
    """The video's :class:`Frames`: a built-in path, a camera path file, or a tracked camera
    (numbered as in its file)."""

    model, meta, _, dataset = open_run(args.run)
    checkpoint = os.path.join(args.run, 'model.npz')
    job = {'checkpoint': os.path.abspath(checkpoint), 'iteration': meta.get('iteration')}
    name, fps = FRAME_NAME, None
    size_what = f'--res {args.res[0]}x{args.res[1]}' if args.res else args.path
    if args.path in BUILT_IN_PATHS:
        check_orbit_frames(args, dataset)
        cameras = dict(enumerate(built_in_cameras(args.path, dataset, args.frames, args.res)))
        job['path'] = args.path
    elif shot_format(args.path):
        shot = read_shot(args.path, args.camera).within(args.frame_range)
        template = dataset.train.cameras[0]
        width, height = args.res or shot.image_size(template.width, template.height)
        check_frames(len(shot.frames), width, height, args.path, size_what)
        cameras = shot.cameras(width, height, capture_normalizations(meta.get('dataset'))
                               + [model.normalization])
        name, fps = shot.frame_name, shot.fps
        job.update(path=os.path.abspath(args.path), path_digest=digest(cameras),
                   frame_name=name)
    else:
        path = read_path(args.path)
        cameras = dict(enumerate(path_cameras(path, model.normalization, args.res)))
        if not cameras:
            raise ValueError(f'{args.path}: the camera path has no frames')
        check_frames(len(cameras), cameras[0].width, cameras[0].height, args.path, size_what)
        job.update(path=os.path.abspath(args.path), path_digest=path.digest())
        fps = path.fps
    first = next(iter(cameras.values()))
    job.update(frames=len(cameras), size=[first.width, first.height])
    if not args.skip_empty:              # frames of whole rays are another video's
        job['skip_empty'] = False
    if args.appearance_image >= 0:       # ... and so are frames of another appearance
        check_appearance(model, args.appearance_image, flag='--appearance-image')
        job['appearance_image'] = args.appearance_image
    return Frames(checkpoint, cameras, job, name, fps)


def look(args) -> dict:
    """How the frames are rendered (:class:`~mi_nerfpp.output.views.ViewRenderer`'s options)."""
    return {'skip_empty': args.skip_empty, 'appearance_image': args.appearance_image}


def check_frames(count, width, height, what, size_what=None):
    """Refuse a video of more frames than memory holds (:func:`~mi_nerfpp.core.budget.
    video_frames_limit`), naming ``what`` asked for them and the most frames that fit; when not
    even one frame fits, ``size_what`` (what set the frame size, e.g. ``--res 100000x100000``)
    and the most pixels a frame may have."""
    most = budget.video_frames_limit(width, height)
    if most == 0 and count > 0:
        pixels = max((budget.images_budget() - budget.VIDEO_CAMERA_BYTES) // 3, 0)
        raise ValueError(
            f'{size_what or what}: one frame of {width}x{height} takes '
            f'{budget.memory_text(width * height * 3)}, more than the '
            f'{budget.memory_text(budget.images_budget())} available; a frame fits with at '
            f'most {pixels:,} pixels')
    if count > most:
        raise ValueError(
            f'{what}: {count:,} frames of {width}x{height} are too many: a video holds each '
            f"frame's camera and, while it is assembled, its pixels in memory, more than the "
            f'{budget.memory_text(budget.images_budget())} available; at most {most:,} frames '
            f'of {width}x{height} fit')


def check_orbit_frames(args, dataset):
    """``--frames`` of the orbit path against memory, before its cameras are made."""
    if args.path == 'orbit':
        template = dataset.train.cameras[0]
        width, height = args.res or (template.width, template.height)
        size = f'--res {width}x{height}' if args.res else f'the training images ({width}x{height})'
        check_frames(args.frames, width, height, f'--frames {args.frames}', size)


def subject(args):
    return f'run folder {args.run}'


def check_path_argument(args):
    """``--path``: a built-in path or an existing file; ``--write-path`` only of a built-in
    path; ``--camera`` only of a USD file, ``--frame-range`` only of a tracked camera."""
    if args.path not in BUILT_IN_PATHS and not os.path.isfile(args.path):
        raise ValueError(f"--path {args.path}: neither 'orbit', 'test' nor a camera path file")
    if args.write_path and args.path not in BUILT_IN_PATHS:
        raise ValueError('--write-path writes the orbit or test path: --path FILE is a path '
                         'file already')
    kind = None if args.path in BUILT_IN_PATHS else shot_format(args.path)
    if args.camera is not None and kind != 'usd':
        raise ValueError(f'--camera {args.camera} picks a camera of a USD file (--path '
                         f'FILE.usd), not of --path {args.path}')
    if args.frame_range is not None and kind is None:
        raise ValueError(f'--frame-range numbers the frames of a tracked camera (--path of a '
                         f'USD, .chan or nerfstudio file), not of --path {args.path}')


def run(args):

    check_path_argument(args)
    if args.write_path:
        model, _, _, dataset = open_run(args.run)
        check_orbit_frames(args, dataset)
        path = built_in_path(args.path, dataset, model.normalization, args.frames, args.res,
                             args.fps or DEFAULT_FPS)
        write_path(args.write_path, path)
        print(f'wrote {args.write_path} ({args.path}: {len(path.frames)} frames, '
              f'{len(path.keyframes)} keyframes); render it with: python -m mi_nerfpp video '
              f'{args.run} --path {args.write_path}')
        return 0
    out = args.output or os.path.join(args.run, 'video.mp4')
    check_video_path(out)           # a format it cannot write: before any frame is rendered
    if args.ray:
        check_address(args.ray)     # ray not installed, or no cluster there: before any work
    frames = frames_of(args)
    cameras = frames.cameras
    frames_dir = args.frames_dir or os.path.splitext(out)[0] + '_frames'
    prepare_frames_dir(frames_dir, frames.job)
    pending = pending_frames(frames_dir, cameras, args.exr, frames.name)
    with tqdm(total=len(cameras), initial=len(cameras) - len(pending), desc='video',
              unit='frame', dynamic_ncols=True) as bar:
        if pending and args.ray:
            render_on_cluster(args, frames, pending, frames_dir, bar)
        elif pending:
            render_here(frames, pending, frames_dir, args.exr, bar, look(args))
    remove_stale_temporaries(frames_dir)
    write_video(out, read_frames(frames_dir, cameras, frames.name),
                fps=args.fps or frames.fps or DEFAULT_FPS)
    print(f'wrote {out} ({len(cameras)} frames; frames in {frames_dir})')


def render_here(frames: Frames, pending, frames_dir, exr, bar, look=None):
    FrameWorker(frames.checkpoint, look=look).render_frames(
        {i: frames.cameras[i] for i in pending}, frames_dir, exr,
        on_frame=lambda i: bar.update(1), name=frames.name)


def render_on_cluster(args, frames: Frames, pending, frames_dir, bar):
    with session(args.ray, timeout_line('video', args.ray)) as ray:
        workers = args.workers or max(1, cluster_cpus(ray) // args.worker_cpus)
        workers = min(workers, len(pending))
        bar.write(f'rendering {len(pending)} frames on {workers} Ray workers of '
                  f'{args.worker_cpus} CPU(s)')
        pool = FramePool(frames.checkpoint, workers, args.worker_cpus, look(args))
        try:
            pool.render_frames(frames.cameras, pending, os.path.abspath(frames_dir), args.exr,
                               on_frames=bar.update, name=frames.name)
        finally:
            pool.close()
