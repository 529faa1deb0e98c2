"""``python -m mi_nerfpp colmap PHOTOS --out DATA``: structure from motion
(:mod:`mi_nerfpp.data.sfm`) on a folder of photos, a video or a folder of videos
(:mod:`mi_nerfpp.data.video`)."""
from __future__ import annotations

import argparse

from mi_nerfpp.commands.arguments import thread_count, whole_between
from mi_nerfpp.data import video
from mi_nerfpp.data.sfm import (CAMERA_MODES, COLMAP_MAX_INT, COLMAP_MINIMUMS,
                                DEFAULT_HOLD, DEFAULT_MAX_IMAGE_SIZE,
                                DEFAULT_OVERLAP, MATCHING, run_sfm, run_sfm_on_videos,
                                video_inputs)
from mi_nerfpp.files.atomic import check_not_a_file


def run(args) -> int:
    check_not_a_file(args.out)
    # Errors (SfmError, DatasetError, OSError, ...) end the command at its boundary
    # (mi_nerfpp.commands.cli).
    options = dict(hold=args.hold, max_image_size=args.max_image_size, overlap=args.overlap,
                   num_threads=args.threads)
    videos = video_inputs(args.photos)
    if videos:
        run_sfm_on_videos(videos, args.out, frames=args.frames,
                          matching=args.matching or 'sequential', camera=args.camera, **options)
        return 0
    if args.frames is not None:
        raise ValueError(f'--frames: {args.photos} is not a video or a folder of videos')
    run_sfm(args.photos, args.out, matching=args.matching or 'exhaustive',
            camera=args.camera or 'auto', **options)
    return 0


def _count(name):
    """argparse type of COLMAP's count option ``name``: within its minimum and COLMAP's
    largest count."""
    return whole_between(COLMAP_MINIMUMS[name], COLMAP_MAX_INT, "COLMAP's largest count")


def add_frames_option(p) -> None:
    """``--frames N`` of a command that takes videos (``colmap``, ``optimize``)."""
    p.add_argument('--frames', type=whole_between(1, COLMAP_MAX_INT, "COLMAP's largest count"),
                   default=None,
                   help='videos: frames kept of each, the sharpest of as many equal time '
                        f'windows (default: {video.FRAMES_PER_SECOND:g} per second of video, '
                        f'{video.MIN_FRAMES} to {video.MAX_FRAMES})')


def subject(args):
    return f'the photos or videos in {args.photos}'


def add_parser(sub) -> argparse.ArgumentParser:
    """Register ``colmap`` on the sub-command parsers of ``python -m mi_nerfpp``."""
    p = sub.add_parser(
        'colmap', help='poses for a folder of photos or a video (structure from motion with '
                       'pycolmap), written as a NeRF++ dataset',
        description='Feature extraction, matching, incremental mapping and undistortion with '
                    'COLMAP (pycolmap), then the registered photos in the NeRF++ layout with '
                    'NeRF++\'s normalization (DATA/sfm.json holds it, and the registered and '
                    'unregistered photos). A video (or a folder of videos) gives the sharpest '
                    'frame of each equal time window, kept in DATA/video_frames/, solved with '
                    'one shared camera and sequential matching. A second run with the same '
                    'photos or videos and options reuses DATA.')
    p.add_argument('photos', help='folder of JPG/PNG/TIFF photos (its subfolders are ignored), '
                                  f'a video ({", ".join(video.VIDEO_EXTENSIONS)}) or a folder '
                                  f'of videos')
    p.add_argument('--out', required=True, metavar='DATA', help='dataset folder to write')
    add_frames_option(p)
    p.add_argument('--matching', choices=MATCHING, default=None,
                   help='exhaustive: every pair of photos (unordered photo sets); sequential: '
                        'each frame with the next --overlap frames (video frames in order) '
                        '(default: exhaustive for photos, sequential for videos)')
    p.add_argument('--overlap', type=_count('overlap'), default=DEFAULT_OVERLAP,
                   help='sequential matching: frames each frame is matched with '
                        '(default %(default)s)')
    p.add_argument('--camera', choices=CAMERA_MODES, default=None,
                   help='which photos share intrinsics: single (one camera took all), '
                        'per-image, or auto: single when all photos have one size and one EXIF '
                        'camera and focal length, else per-image (default: auto for photos; '
                        'for videos single, per-image when their frames differ in size)')
    p.add_argument('--hold', type=_count('hold'), default=DEFAULT_HOLD,
                   help='every N-th registered photo is a test view (0: none) '
                        '(default %(default)s)')
    p.add_argument('--max-image-size', type=_count('max_image_size'),
                   default=DEFAULT_MAX_IMAGE_SIZE,
                   help='photos are shrunk to this many pixels (longer side) for feature '
                        'extraction (default %(default)s)')
    p.add_argument('--threads', type=thread_count, default=-1,
                   help='CPU threads for COLMAP (default: all)')
    p.set_defaults(func=run)
    return p
