"""Video in: the sharpest frames of a video, kept for structure from motion.

A walk-around filmed on a phone holds thousands of frames, many of them blurred by the motion
of the hand. :func:`extract_frames` decodes a video (or each video of a folder) with PyAV
(FFmpeg's libraries in a wheel: no system ffmpeg), applies its rotation metadata (a phone
stores a portrait video as landscape frames and a display matrix; the frames are turned
upright as a player shows them) and keeps one frame per equal time window: the video's length
is cut into as many windows as frames are wanted, and in each window the sharpest frame is
kept, sharpness being the variance of the Laplacian of the frame's luminance (a blurred frame
has weak edges: a low variance). Equal windows keep the frames spread along the camera's path
(sequential matching needs neighbours that overlap), and choosing within a window skips the
blurred ones (a fixed rate keeps whatever frame falls on it).

How many: ``frames`` per video, or by default :data:`FRAMES_PER_SECOND` per second of video (the
rate instant-ngp's colmap2nerf.py takes by default) within :data:`MIN_FRAMES` (enough views for
structure from motion and an eighth held out) and :data:`MAX_FRAMES` (what a CPU trains on in
the project's minutes), never more than the video has. The count, the length and the window are
announced on one line.

The frames go to ``DATA/video_frames/`` (:data:`FOLDER`) as ``<video stem>_<frame
index>.jpg`` (JPEG of quality :data:`JPEG_QUALITY`: the video is lossy already), with
``frames.json`` (:data:`FRAMES_FILE`): per video its path, size, SHA-256, frame count, rate,
rotation, the count asked for, the window, every decoded frame's index, time and sharpness,
and the chosen ones. A second run with the same video (same digest) and the same count reuses
them without decoding; a changed video or count extracts again. Structure from motion then
runs on that folder with one shared camera and sequential matching
(:mod:`mi_nerfpp.data.sfm`).

A video that cannot be read (damaged, truncated, not a video) or that has fewer frames than
asked for ends with a :class:`~mi_nerfpp.data.errors.DatasetError` naming the file.
"""
from __future__ import annotations

import hashlib
import os

import numpy as np
from PIL import Image
from tqdm import tqdm

from mi_nerfpp.data.errors import DatasetError
from mi_nerfpp.files.atomic import write_json
from mi_nerfpp.files.readers import FileReadError, read_json

VIDEO_EXTENSIONS = ('.mp4', '.mov', '.m4v', '.mkv', '.avi', '.webm', '.mts')
FOLDER = 'video_frames'           # in the dataset folder
FRAMES_FILE = 'frames.json'       # in FOLDER
FRAMES_FORMAT = 'mi-nerfpp-video-frames'
FRAMES_VERSION = 1
FRAMES_PER_SECOND = 2.0           # default count: frames per second of video
MIN_FRAMES = 30                   # ... at least (when the video has them)
MAX_FRAMES = 150                  # ... at most
JPEG_QUALITY = 95
# Frames a container's index may list beyond those its decoder gives (edit lists, a last
# frame dropped) before the video counts as truncated.
MISSING_FRAMES_ALLOWED = 2


def is_video(path) -> bool:
    """Whether ``path`` is a file with a video's extension."""
    return os.path.isfile(path) and os.fspath(path).lower().endswith(VIDEO_EXTENSIONS)


def list_videos(folder) -> list[str]:
    """The video file names directly in ``folder`` (sorted)."""
    folder = os.fspath(folder)
    return sorted(name for name in os.listdir(folder) if is_video(os.path.join(folder, name)))


def default_count(seconds: float, available: int) -> int:
    """Frames kept of a video of ``seconds`` with ``available`` frames when no count is
    asked for (see the module docstring)."""
    wanted = min(MAX_FRAMES, max(MIN_FRAMES, round(FRAMES_PER_SECOND * seconds)))
    return max(1, min(wanted, available))


def sharpness(grey: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of a luminance image (values 0-255)."""
    g = np.asarray(grey, dtype=np.float32)
    lap = g[:-2, 1:-1] + g[2:, 1:-1] + g[1:-1, :-2] + g[1:-1, 2:] - 4.0 * g[1:-1, 1:-1]
    return float(lap.var())


def sha256(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, 'rb') as f:
        for block in iter(lambda: f.read(1 << 22), b''):
            digest.update(block)
    return digest.hexdigest()


def read_record(folder) -> dict:
    """``FOLDER/frames.json`` (empty when there is none, or it is damaged)."""
    try:
        record = read_json(os.path.join(os.fspath(folder), FRAMES_FILE),
                           what='video frames record')
    except FileReadError:
        return {}
    ok = record.get('format') == FRAMES_FORMAT and record.get('version') == FRAMES_VERSION
    return record if ok else {}


def extract_frames(videos, folder, frames: int | None = None,
                   progress: bool = True) -> dict:
    """The chosen frames of ``videos`` in ``folder`` (see the module docstring); reused when
    ``folder`` holds them already for the same videos and count.

    Args:
        videos: video file paths.
        folder: where the frames and ``frames.json`` go (created).
        frames: frames kept per video (None: the default count).
        progress: a progress bar while decoding, and the announcements printed.

    Returns:
        The contents of ``frames.json``, plus ``'decoded'``: the videos decoded this time.

    Raises:
        DatasetError: a video that cannot be read, is truncated or has fewer frames than
            ``frames``.
        ValueError: ``frames`` below 1.
    """
    if frames is not None and frames < 1:
        raise ValueError(f'--frames must be 1 or more, got {frames}')
    folder = os.fspath(folder)
    os.makedirs(folder, exist_ok=True)
    previous = {entry['path']: entry for entry in read_record(folder).get('videos', [])}
    prefixes = _prefixes(videos)
    entries, decoded = [], []
    for video, prefix in zip(videos, prefixes):
        path = os.path.abspath(video)
        try:
            digest = sha256(path)
        except OSError as e:
            raise DatasetError(f'{video}: cannot read this video ({e.strerror or e})') from e
        old = previous.get(path)
        if (old is not None and old['sha256'] == digest and old['asked'] == frames
                and old['prefix'] == prefix
                and all(os.path.isfile(os.path.join(folder, f['file'])) for f in old['chosen'])):
            if progress:
                print(f'{video}: {len(old["chosen"])} frames kept in {folder} from an earlier '
                      f'run (same video and --frames); not decoded again')
            entries.append(old)
            continue
        entries.append(_extract(video, path, digest, prefix, folder, frames, progress))
        decoded.append(path)
    keep = {f['file'] for entry in entries for f in entry['chosen']} | {FRAMES_FILE}
    for name in os.listdir(folder):     # frames of earlier videos or counts
        if name not in keep and os.path.isfile(os.path.join(folder, name)):
            os.remove(os.path.join(folder, name))
    record = {'format': FRAMES_FORMAT, 'version': FRAMES_VERSION, 'videos': entries}
    write_json(os.path.join(folder, FRAMES_FILE), record)
    return dict(record, decoded=decoded)


def _prefixes(videos) -> list[str]:
    """File name prefix of each video's frames: its stem, or its name when stems repeat."""
    stems = [os.path.splitext(os.path.basename(v))[0] for v in videos]
    return [stem if stems.count(stem) == 1 else os.path.basename(v).replace('.', '_')
            for stem, v in zip(stems, videos)]


def _unreadable(video, error) -> DatasetError:
    reason = getattr(error, 'strerror', None) or str(error)
    return DatasetError(f'{video}: cannot read this video ({reason}): it is damaged, truncated '
                        f'or not a video; film or copy it again')


def _extract(video, path, digest, prefix, folder, asked, progress) -> dict:
    """Decode one video, keep the sharpest frame of each window; its frames.json entry."""
    import av     # deferred: FFmpeg's libraries, for video input only

    try:
        container = av.open(path)
    except (av.FFmpegError, OSError) as e:
        raise _unreadable(video, e) from e
    with container:
        if not container.streams.video:
            raise DatasetError(f'{video}: holds no video stream')
        stream = container.streams.video[0]
        stream.thread_type = 'AUTO'
        rate = float(stream.average_rate or stream.guessed_rate or 0) or None
        listed = int(stream.frames or 0)
        if stream.duration is not None and stream.time_base is not None:
            seconds = float(stream.duration * stream.time_base)
        elif container.duration is not None:
            seconds = container.duration / av.time_base
        else:
            seconds = listed / rate if listed and rate else 0.0
        if listed and asked is not None and listed < asked:
            raise _too_short(video, listed, seconds, asked)
        count = asked if asked is not None else default_count(seconds, listed or MAX_FRAMES)
        window = seconds / count if seconds > 0 else None
        if progress:
            how = '--frames' if asked is not None else \
                f'{FRAMES_PER_SECOND:g} per second, {MIN_FRAMES}-{MAX_FRAMES}'
            print(f'{video}: {seconds:.1f} s, {listed or "?"} frames at {rate or 0:.3g} fps; '
                  f'keeping {count} frames ({how}): the sharpest of each '
                  + (f'{window:.2f} s window' if window else 'window'))
        candidates = {'index': [], 'time': [], 'sharpness': []}
        chosen, best, rotation, t0 = [], None, 0, None
        bar = tqdm(total=listed or None, desc=f'video {os.path.basename(video)}', unit='frame',
                   disable=not progress, dynamic_ncols=True)
        try:
            for index, frame in enumerate(container.decode(stream)):
                t = frame.time if frame.time is not None else index / (rate or 1.0)
                t0 = t if t0 is None else t0
                if window is None:      # length unknown: windows of the listed frames
                    slot = min(count - 1, index * count // max(listed, 1))
                else:
                    slot = min(count - 1, int((t - t0) / window))
                score = sharpness(frame.to_ndarray(format='gray'))
                for key, value in (('index', index), ('time', round(t - t0, 6)),
                                   ('sharpness', round(score, 4))):
                    candidates[key].append(value)
                if best is not None and slot != best[0]:
                    chosen.append(_keep(best, prefix, folder))
                    best = None
                if index == 0:
                    rotation = frame.rotation or 0
                if best is None or score > best[2]:
                    best = (slot, index, score, t - t0, frame)
                bar.update(1)
        except av.FFmpegError as e:
            raise _unreadable(video, e) from e
        finally:
            bar.close()
        if best is not None:
            chosen.append(_keep(best, prefix, folder))
    if progress and len(chosen) < count:     # windows without a frame: a gap in the video
        print(f'{video}: {count - len(chosen)} of the {count} windows hold no frame (a gap in '
              f'the video); kept {len(chosen)} frames')
    decoded = len(candidates['index'])
    if listed and decoded + MISSING_FRAMES_ALLOWED < listed:
        raise DatasetError(f'{video}: truncated or damaged: decoded {decoded} of the {listed} '
                           f'frames it lists; film or copy it again')
    if asked is not None and decoded < asked:
        raise _too_short(video, decoded, seconds, asked)
    return {'path': path, 'sha256': digest, 'size': os.path.getsize(path), 'prefix': prefix,
            'seconds': seconds, 'fps': rate, 'frames': decoded, 'rotation': rotation,
            'asked': asked, 'count': count, 'window_seconds': window,
            'chosen': chosen, 'candidates': candidates}


def _too_short(video, available, seconds, asked) -> DatasetError:
    return DatasetError(f'{video}: has {available} frames ({seconds:.1f} s), fewer than the '
                        f'{asked} asked for (--frames): ask for {available} or fewer')


def _keep(best, prefix, folder) -> dict:
    """Write a window's sharpest frame, upright; its entry in frames.json."""
    slot, index, score, t, frame = best
    rgb = frame.to_ndarray(format='rgb24')
    turns = round((frame.rotation or 0) / 90) % 4   # counter-clockwise, as the display matrix
    if turns:
        rgb = np.ascontiguousarray(np.rot90(rgb, turns))
    name = f'{prefix}_{index:06d}.jpg'
    Image.fromarray(rgb).save(os.path.join(folder, name), quality=JPEG_QUALITY)
    return {'file': name, 'index': index, 'time': round(t, 6), 'sharpness': round(score, 4),
            'window': slot, 'width': int(rgb.shape[1]), 'height': int(rgb.shape[0])}


def frame_sizes(record: dict) -> set:
    """The (width, height) of the kept frames."""
    return {(f['width'], f['height']) for entry in record['videos'] for f in entry['chosen']}
