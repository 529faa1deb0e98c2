"""Structure from motion with pycolmap: from a folder of photos to a NeRF++ dataset.

:func:`run_sfm` runs COLMAP's pipeline through its Python bindings, one progress bar per stage:

1. **images**: the photos (JPG/PNG/TIFF in the folder, not its subfolders) are copied into
   ``OUT/colmap/images/``; photos with an EXIF orientation, 16-bit or palette/alpha pixels are
   re-encoded upright as 8-bit PNG (COLMAP ignores EXIF orientation). Their masks, from a
   ``masks/`` subfolder (:mod:`mi_nerfpp.data.masks`), go to ``OUT/colmap/masks/`` as COLMAP
   names them.
2. **features**: SIFT features (``OUT/colmap/database.db``), none under a mask's black pixels
   (``mask_features``).
3. **matching**: exhaustive (every pair: best for unordered photos, up to a few hundred) or
   sequential (each frame with the next ``overlap`` frames: video frames in order), both
   without a vocabulary tree.
4. **mapping**: COLMAP's incremental mapper. The largest reconstruction is kept
   (``OUT/colmap/sparse/0``); when it registers fewer than :data:`RETRY_BELOW` of the photos,
   mapping runs once more with a relaxed initialization (smaller triangulation angle and
   fewer inliers for the first pair, which dense captures with small baselines need) and the
   larger result is kept.
5. **undistortion** to pinhole cameras (``OUT/colmap/undistorted/``).
6. **NeRF++ layout**: ``OUT/{train,test}/{rgb,pose,intrinsics}/`` (and ``mask/``, the masks
   undistorted and cropped like their photos) with NeRF++'s normalization
   applied (mean camera centre at the origin, farthest camera at radius 1/1.1), every
   ``hold``-th registered photo held out as test.

``OUT/sfm.json`` records the parameters, the input photos (name, size, modification time),
the registered and unregistered photos, the timings and the normalization, ``x_model =
(x_colmap - center) * scale``, so renders can be placed back in the COLMAP frame. A second run
with the same photos and parameters finds it and does nothing.

:func:`run_sfm_on_videos` takes videos instead: the sharpest frames of each
(:mod:`mi_nerfpp.data.video`, kept in ``OUT/video_frames/``) are solved with one shared camera
(COLMAP's single camera mode, for frames of one size) and sequential matching.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time

import numpy as np
from PIL import Image, ImageOps
from tqdm import tqdm

from mi_nerfpp.core.frame import Normalization
from mi_nerfpp.data.cameras import Camera
from mi_nerfpp.data import masks, video
from mi_nerfpp.data.colmap import colmap_frames, pinhole_model, with_masks
from mi_nerfpp.data.errors import DatasetError
from mi_nerfpp.data.nerfpp import write_camera
from mi_nerfpp.files.atomic import as_text, folder_path, remove_entries
from mi_nerfpp.files.readers import FileReadError, open_photo, read_json

PHOTO_EXTENSIONS = ('.jpg', '.jpeg', '.png', '.tif', '.tiff')
MATCHING = ('exhaustive', 'sequential')
CAMERA_MODES = ('auto', 'single', 'per-image')
SFM_FILE = 'sfm.json'
SFM_FORMAT = 'mi-nerfpp-sfm'
SFM_VERSION = 1
DEFAULT_HOLD = 8
DEFAULT_MAX_IMAGE_SIZE = 3200     # COLMAP's default for feature extraction
DEFAULT_OVERLAP = 10              # sequential matching: neighbours of each frame
# The largest count COLMAP's options take (a C int; pycolmap refused 10000000000 with its own
# "incompatible function arguments" text).
COLMAP_MAX_INT = 2 ** 31 - 1
# The lowest value of each count option (the photos' longer side: 16 pixels for SIFT).
COLMAP_MINIMUMS = {'hold': 0, 'max_image_size': 16, 'overlap': 1}
RETRY_BELOW = 0.8                 # registration rate under which mapping is retried relaxed
RELAXED_INIT = dict(init_min_tri_angle=4.0, init_min_num_inliers=50)
MIN_PAIR_INLIERS = 15             # COLMAP's default minimum of a verified pair
FEATURE_CHUNK = 8                 # images per feature-extraction call (progress granularity)
_EXIF_ORIENTATION = 0x0112
PHOTO_REMEDY = 'remove it, or convert it to JPG/PNG'     # a photo that cannot be read


class SfmError(RuntimeError):
    """Structure from motion failed; the message says why and what to try."""


def list_photos(folder) -> list[str]:
    """The photo file names directly in ``folder`` (sorted)."""
    folder = os.fspath(folder)
    return sorted(name for name in os.listdir(folder)
                  if name.lower().endswith(PHOTO_EXTENSIONS)
                  and os.path.isfile(os.path.join(folder, name)))


def is_photo_folder(path) -> bool:
    """Whether ``path`` is a folder holding photos directly (the input of :func:`run_sfm`)."""
    return os.path.isdir(path) and bool(list_photos(path))


def video_inputs(path) -> list[str] | None:
    """The videos that ``path`` stands for: itself (a video file), or the videos directly in
    it (a folder holding videos and no photos); None for anything else.

    Raises:
        DatasetError: a folder holding both photos and videos.
    """
    path = os.fspath(path)
    if video.is_video(path):
        return [path]
    if not os.path.isdir(path):
        return None
    videos = video.list_videos(path)
    if not videos:
        return None
    if list_photos(path):
        raise DatasetError(f'{path}: holds both photos and videos ({", ".join(videos[:3])}); '
                           f'put the videos in a folder of their own')
    return [os.path.join(path, name) for name in videos]


def _fingerprint(photos: str, names: list[str]) -> list:
    out = []
    for name in names:
        st = os.stat(os.path.join(photos, name))
        out.append([name, st.st_size, st.st_mtime_ns])
    return out


def read_report(out) -> dict | None:
    """``OUT/sfm.json``, or None if there is none (or it is unreadable)."""
    try:
        report = read_json(os.path.join(os.fspath(out), SFM_FILE), what='SfM report')
    except FileReadError:       # none, or damaged: the photos are solved again
        return None
    return report if report.get('format') == SFM_FORMAT else None


def _write_report(out: str, report: dict) -> None:
    tmp = os.path.join(out, SFM_FILE + '.tmp')
    with open(tmp, 'w') as f:
        json.dump(report, f, indent=1)
    os.replace(tmp, os.path.join(out, SFM_FILE))


SFM_SEED = 0   # seed of COLMAP's random generators (global, RANSAC, mapper) for every run


def run_sfm(photos, out, matching: str = 'exhaustive', camera: str = 'auto',
            hold: int = DEFAULT_HOLD, max_image_size: int = DEFAULT_MAX_IMAGE_SIZE,
            overlap: int = DEFAULT_OVERLAP, num_threads: int = -1,
            progress: bool = True, mask_features: bool = True) -> dict:
    """Poses for a folder of photos, written as a NeRF++ dataset (see the module docstring).

    Args:
        photos: folder of JPG/PNG/TIFF photos.
        out: dataset folder to write (created; an earlier run's output there is reused when
            the photos and parameters are the same, replaced otherwise).
        matching: 'exhaustive' or 'sequential'.
        camera: 'single' (one camera took all photos: they share intrinsics), 'per-image'
            (intrinsics of each photo its own) or 'auto' (single when all photos have one
            size and one EXIF make, model and focal length, else per-image).
        hold: every ``hold``-th registered photo is held out as test (0: none).
        max_image_size: photos are shrunk to this size for feature extraction.
        overlap: sequential matching: how many following frames each frame is matched with.
        num_threads: CPU threads for COLMAP (-1: all).
        progress: progress bars and the report printed.
        mask_features: photos with a mask in ``photos/masks/`` (:mod:`.masks`) give no
            features where their mask is black (what the masks cover is not the scene:
            ``--masks ignore``); False: features everywhere (object silhouettes). The masks
            go with their photos into the dataset either way.

    Returns:
        The contents of ``OUT/sfm.json``, plus ``'cached': True`` when nothing was run.

    Raises:
        SfmError: no photos, fewer than two registered, COLMAP failing.
        ValueError: unknown ``matching`` / ``camera``, bad numbers.
        FileExistsError: ``out`` holds files that are not an earlier run's.
    """
    import pycolmap  # deferred: COLMAP's native library, for SfM and undistortion only

    photos, out = os.fspath(photos), os.fspath(out)
    if matching not in MATCHING:
        raise ValueError(f'matching must be one of {", ".join(MATCHING)}, got {matching!r}')
    if camera not in CAMERA_MODES:
        raise ValueError(f'camera must be one of {", ".join(CAMERA_MODES)}, got {camera!r}')
    for name, value in (('hold', hold), ('max_image_size', max_image_size),
                        ('overlap', overlap)):
        if not COLMAP_MINIMUMS[name] <= value <= COLMAP_MAX_INT:
            raise ValueError(f'{name} must be from {COLMAP_MINIMUMS[name]} to {COLMAP_MAX_INT} '
                             f"(COLMAP's largest count), got {value}")
    if os.path.isfile(photos):
        raise SfmError(f'{photos}: a file, not a folder of photos or a video '
                       f'({", ".join(video.VIDEO_EXTENSIONS)})')
    if not os.path.isdir(photos):
        raise SfmError(f'{photos}: no such folder')
    names = list_photos(photos)
    if len(names) < 2:
        raise SfmError(f'{photos}: found {len(names)} photos ({", ".join(PHOTO_EXTENSIONS)}); '
                       f'structure from motion needs many overlapping photos (dozens)')
    mask_folder = os.path.join(photos, masks.FOLDER)
    photo_masks = {name: masks.find_mask(mask_folder, name) for name in names} \
        if os.path.isdir(mask_folder) else {}
    photo_masks = {name: path for name, path in photo_masks.items() if path is not None}
    params = {'photos': os.path.abspath(photos), 'matching': matching, 'camera': camera,
              'hold': hold, 'max_image_size': max_image_size, 'overlap': overlap,
              'pycolmap': pycolmap.__version__, 'version': SFM_VERSION,
              'mask_features': bool(mask_features and photo_masks)}
    inputs = _fingerprint(photos, names) + _fingerprint(
        mask_folder, sorted(os.path.relpath(p, mask_folder) for p in photo_masks.values()))
    previous = read_report(out)
    if (previous is not None and previous.get('complete') and previous.get('params') == params
            and previous.get('inputs') == inputs):
        if progress:
            print(f'{out}: structure from motion up to date (same photos and parameters); '
                  f'skipping it')
            _print_summary(previous, out)
        return dict(previous, cached=True)
    _prepare_output(out, previous is not None)
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # errors only: the progress bars say enough
    # COLMAP's RANSAC and mapper draw from one global generator: seed it, so that the result
    # does not depend on what ran before in the process (a test suite, a notebook).
    pycolmap.set_random_seed(SFM_SEED)
    try:
        return _run(pycolmap, photos, out, names, params, inputs, camera, hold,
                    max_image_size, overlap, matching, num_threads, progress, photo_masks)
    finally:
        pycolmap.logging.minloglevel = level


def _run(pycolmap, photos, out, names, params, inputs, camera, hold, max_image_size, overlap,
         matching, num_threads, progress, photo_masks) -> dict:

    def bar(desc, total, unit):
        return tqdm(total=total, desc=f'sfm {desc}', unit=unit, disable=not progress,
                    dynamic_ncols=True)

    workspace = os.path.join(out, 'colmap')
    image_dir = os.path.join(workspace, 'images')
    database = os.path.join(workspace, 'database.db')
    os.makedirs(image_dir)
    report = {'format': SFM_FORMAT, 'version': SFM_VERSION, 'complete': False, 'params': params,
              'inputs': inputs, 'seconds': {}}
    _write_report(out, report)
    seconds = report['seconds']

    t = time.perf_counter()
    with bar('images', len(names), 'photo') as b:
        colmap_names = {}
        for name in names:
            colmap_names[name] = _prepare_photo(os.path.join(photos, name), image_dir,
                                                _colmap_name(name, colmap_names.values()))
            if name in photo_masks:     # COLMAP's naming: the image's name plus .png
                _prepare_mask(photo_masks[name], os.path.join(photos, name),
                              os.path.join(workspace, masks.FOLDER, colmap_names[name] + '.png'))
            b.update(1)
    seconds['images'] = time.perf_counter() - t
    # COLMAP takes UTF-8 paths only (std::string): a workspace whose path is not UTF-8 is
    # given through its /proc/self/fd path (files.atomic.folder_path).
    with folder_path(workspace) as workspace:
        image_dir = os.path.join(workspace, 'images')
        database = os.path.join(workspace, 'database.db')
        reader = pycolmap.ImageReaderOptions()
        if params['mask_features']:
            reader.mask_path = os.path.join(workspace, masks.FOLDER)

        t = time.perf_counter()
        listed = sorted(colmap_names.values())
        if camera == 'auto':
            camera = 'single' if _one_camera(image_dir, listed) else 'per-image'
        report['camera_mode'] = camera
        mode = {'single': pycolmap.CameraMode.SINGLE,
                'per-image': pycolmap.CameraMode.PER_IMAGE}[camera]
        pycolmap.Database.open(database).close()
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = max_image_size
        extraction.num_threads = num_threads
        try:
            pycolmap.import_images(database, image_dir, camera_mode=mode, image_names=listed)
            with bar('features', len(listed), 'photo') as b:
                for i in range(0, len(listed), FEATURE_CHUNK):
                    chunk = listed[i:i + FEATURE_CHUNK]
                    pycolmap.extract_features(database, image_dir, image_names=chunk,
                                              camera_mode=mode, reader_options=reader,
                                              extraction_options=extraction)
                    b.update(len(chunk))
        except Exception as e:  # noqa: BLE001 - pycolmap raises ValueError/RuntimeError alike
            raise SfmError(f'{photos}: COLMAP feature extraction failed ({e})') from e
        seconds['features'] = time.perf_counter() - t

        t = time.perf_counter()
        n_pairs = len(listed) * (len(listed) - 1) // 2 if matching == 'exhaustive' else None
        matcher = pycolmap.FeatureMatchingOptions()
        matcher.num_threads = num_threads
        verification = pycolmap.TwoViewGeometryOptions()
        # Geometric verification's RANSAC has its own seed, unset by default (-1), which
        # set_random_seed does not reach: unseeded, the verified pairs varied from run to run.
        verification.ransac.random_seed = SFM_SEED
        with bar(f'matching ({matching})', 1, 'stage') as b:
            try:
                if matching == 'exhaustive':
                    pycolmap.match_exhaustive(database, matching_options=matcher,
                                              verification_options=verification)
                else:
                    pairing = pycolmap.SequentialPairingOptions()
                    pairing.overlap = overlap
                    pairing.loop_detection = False
                    pycolmap.match_sequential(database, matching_options=matcher,
                                              pairing_options=pairing,
                                              verification_options=verification)
            except Exception as e:  # noqa: BLE001
                raise SfmError(f'{photos}: COLMAP feature matching failed ({e})') from e
            b.update(1)
        with pycolmap.Database.open(database) as db:
            _, geometries = db.read_two_view_geometries()
            # Photo pairs whose matches passed geometric verification (COLMAP keeps a record,
            # possibly empty, for every pair it tried).
            report['verified_pairs'] = sum(len(g.inlier_matches) >= MIN_PAIR_INLIERS
                                           for g in geometries)
            report['cameras'] = int(db.num_cameras())
        if n_pairs is not None:
            report['pairs'] = n_pairs
        seconds['matching'] = time.perf_counter() - t

        t = time.perf_counter()
        model_dir, registered = _map(pycolmap, database, image_dir, workspace, len(listed),
                                     num_threads, bar)
        seconds['mapping'] = time.perf_counter() - t
        if model_dir is None or registered < 2:
            raise SfmError(
                f'{photos}: COLMAP could not reconstruct the scene: it found no pair of photos '
                f'to start from ({report["verified_pairs"]} pairs of the {len(listed)} photos have '
                f'{MIN_PAIR_INLIERS} or more geometrically verified matches; a start needs '
                f'{RELAXED_INIT["init_min_num_inliers"]}-100 and enough parallax). ' + ADVICE)

        t = time.perf_counter()
        with bar('undistortion', 1, 'stage') as b:
            try:
                model, undistorted_images = pinhole_model(workspace, model_dir, progress=False)
            except DatasetError as e:
                raise SfmError(str(e)) from e
            b.update(1)
        seconds['undistortion'] = time.perf_counter() - t

        t = time.perf_counter()
        report.update(_write_dataset(out, model, undistorted_images, hold, bar, workspace))
        seconds['dataset'] = time.perf_counter() - t

    by_colmap_name = {v: k for k, v in colmap_names.items()}
    reg = {by_colmap_name[im.name] for im in model.images.values()}
    report['registered'] = sorted(reg)
    report['unregistered'] = [name for name in names if name not in reg]
    report['registration_rate'] = len(reg) / len(names)
    report['seconds'] = {k: round(v, 2) for k, v in seconds.items()}
    report['complete'] = True
    _write_report(out, report)
    if progress:
        _print_summary(report, out)
    return dict(report, cached=False)


def run_sfm_on_videos(videos, out, frames: int | None = None, matching: str = 'sequential',
                      camera: str | None = None, progress: bool = True, **options) -> dict:
    """Poses for the sharpest frames of ``videos``, written as a NeRF++ dataset to ``out``.

    The frames (``frames`` per video, None: :func:`~mi_nerfpp.data.video.default_count`) are
    chosen and kept in ``OUT/video_frames/`` (:func:`~mi_nerfpp.data.video.extract_frames`,
    reused by a second run), then solved by :func:`run_sfm` with sequential matching and
    ``camera`` None: one shared camera ('single') when the frames have one size, else
    'per-image'. ``options``: the other arguments of :func:`run_sfm`.

    Raises:
        DatasetError: a video that cannot be read or is too short; and as :func:`run_sfm`.
    """
    out = os.fspath(out)
    _check_output(out, read_report(out) is not None)   # before any frame is written there
    record = video.extract_frames(videos, os.path.join(out, video.FOLDER), frames,
                                  progress=progress)
    if camera is None:
        camera = 'single' if len(video.frame_sizes(record)) == 1 else 'per-image'
    return run_sfm(os.path.join(out, video.FOLDER), out, matching=matching, camera=camera,
                   progress=progress, **options)


ADVICE = ('To register more photos: take them with more overlap (every part of the scene in '
          'three or more photos, neighbouring photos 10-20 degrees apart), keep the scene '
          'still, the exposure fixed and the photos sharp; avoid textureless, shiny or '
          'repetitive surfaces filling the frame; use exhaustive matching (the default) '
          'unless the photos are video frames in order (--matching sequential).')


def _one_camera(image_dir: str, names: list[str]) -> bool:
    """Whether the photos look like one camera's: one size, one EXIF make, model and focal
    length (or none)."""
    keys = set()
    for name in names:
        with open_photo(os.path.join(image_dir, name), error=SfmError, remedy=PHOTO_REMEDY,
                        pixels=False) as img:
            exif = img.getexif()
            focal = exif.get_ifd(0x8769).get(0x920A)  # Exif IFD: FocalLength
            keys.add((img.size, exif.get(0x010F), exif.get(0x0110), focal))
    return len(keys) == 1


def _check_output(out: str, has_report: bool) -> None:
    """Refuse an output folder holding files that are not an earlier run's (its video frames
    are)."""
    if os.path.isdir(out) and set(os.listdir(out)) - {video.FOLDER} and not has_report:
        raise FileExistsError(f'{out}: folder holds files that are not an earlier `colmap` '
                              f'run\'s; choose an empty or new folder')


def _prepare_output(out: str, has_report: bool) -> None:
    """Clear an earlier run's output, or refuse a folder holding other files."""
    _check_output(out, has_report)
    remove_entries(out, ('colmap', 'train', 'validation', 'test', SFM_FILE))
    os.makedirs(out, exist_ok=True)


def _colmap_name(name: str, taken) -> str:
    """The name of photo ``name`` in COLMAP's workspace: itself when it is UTF-8 (COLMAP's
    names are UTF-8 text), else :func:`~mi_nerfpp.files.atomic.as_text`, made unique against
    the names ``taken``."""
    text = as_text(name)
    stem, ext = os.path.splitext(text)
    k = 2
    while text in taken or text + '.png' in taken:
        text, k = f'{stem}~{k}{ext}', k + 1
    return text


def _prepare_photo(path: str, image_dir: str, name: str) -> str:
    """Copy one photo for COLMAP, upright and 8-bit; returns its name there."""
    with open_photo(path, error=SfmError, remedy=PHOTO_REMEDY) as img:
        orientation = img.getexif().get(_EXIF_ORIENTATION, 1)
        if orientation in (0, 1) and img.mode in ('RGB', 'L') and \
                not name.lower().endswith(('.tif', '.tiff')):
            shutil.copy2(path, os.path.join(image_dir, name))
            return name
        img = ImageOps.exif_transpose(img)
        if img.mode.startswith('I'):  # 16/32-bit integer grayscale
            pixels = np.asarray(img, dtype=np.float64)
            peak = 65535.0 if pixels.max() > 255 else 255.0
            img = Image.fromarray(np.round(pixels * 255.0 / peak).astype(np.uint8))
        elif img.mode not in ('RGB', 'L'):
            img = img.convert('RGB')
        converted = name + '.png'
        img.save(os.path.join(image_dir, converted))
        return converted


def _prepare_mask(path: str, photo: str, target: str) -> None:
    """A photo's mask for COLMAP: 8-bit grayscale PNG, black where the photo is masked out
    (:func:`~mi_nerfpp.data.masks.read_mask`, which checks it against the photo upright)."""
    with open_photo(photo, error=SfmError, remedy=PHOTO_REMEDY, pixels=False) as img:
        size = img.size
        if img.getexif().get(_EXIF_ORIENTATION, 1) in (5, 6, 7, 8):    # turned by 90°
            size = size[::-1]
    try:
        mask = masks.read_mask(path, size, photo)
    except DatasetError as e:
        raise SfmError(str(e)) from e
    os.makedirs(os.path.dirname(target), exist_ok=True)
    Image.fromarray(np.rint(mask * 255).astype(np.uint8)).save(target)


def _map(pycolmap, database, image_dir, workspace, n_images, num_threads, bar):
    """Incremental mapping, retried relaxed when few photos register; the largest model is
    moved to ``workspace/sparse/0``. Returns (its folder or None, registered count)."""
    best_dir, best = None, 0
    attempts = [{}, RELAXED_INIT]
    for k, relaxed in enumerate(attempts):
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = num_threads
        options.random_seed = SFM_SEED     # the mapper's own generators (see the matching)
        for key, value in relaxed.items():
            setattr(options.mapper, key, value)
        attempt_dir = os.path.join(workspace, f'mapping_{k}')
        os.makedirs(attempt_dir)
        desc = 'mapping' + (' (relaxed initialization)' if relaxed else '')
        with bar(desc, n_images, 'photo') as b:
            def registered():
                b.update(1)
            try:
                models = pycolmap.incremental_mapping(database, image_dir, attempt_dir,
                                                      options=options,
                                                      next_image_callback=registered)
            except Exception as e:  # noqa: BLE001
                raise SfmError(f'COLMAP incremental mapping failed ({e})') from e
            if models:
                index, largest = max(models.items(), key=lambda kv: kv[1].num_reg_images())
                b.n = largest.num_reg_images()
                b.refresh()
                if largest.num_reg_images() > best:
                    best, best_dir = largest.num_reg_images(), os.path.join(attempt_dir,
                                                                            str(index))
        if best >= RETRY_BELOW * n_images:
            break
    if best_dir is not None:
        final = os.path.join(workspace, 'sparse', '0')
        os.makedirs(os.path.dirname(final))
        shutil.move(best_dir, final)
        best_dir = final
    for k in range(len(attempts)):
        shutil.rmtree(os.path.join(workspace, f'mapping_{k}'), ignore_errors=True)
    return best_dir, best


def _write_dataset(out: str, model, image_folder: str, hold: int, bar, workspace: str) -> dict:
    """The NeRF++ layout of a pinhole model, normalized, with the photos' masks (undistorted
    like them); returns the report's entries."""

    frames = with_masks(workspace, model, colmap_frames(model, image_folder), progress=False)
    by_path = {os.path.join(image_folder, im.name): model.cameras[im.camera_id]
               for im in model.images.values()}
    cameras = []
    for frame in frames:
        cam = by_path[frame.image_path]
        cameras.append(Camera(frame.intrinsics(cam.width, cam.height), frame.c2w, cam.width,
                              cam.height, frame.name))
    cameras, offsets = _common_size(cameras, out)
    normalization = Normalization.for_cameras(cameras, always=True)
    held_out = set(range(0, len(frames), hold)) if hold > 0 else set()
    if len(held_out) == len(frames):
        held_out = set()
    with bar('NeRF++ layout', len(frames), 'photo') as b:
        for i, (frame, camera) in enumerate(zip(frames, cameras)):
            split = os.path.join(out, 'test' if i in held_out else 'train')
            stem = frame.name.replace(os.sep, '_').replace('/', '_')
            os.makedirs(os.path.join(split, 'rgb'), exist_ok=True)
            _copy_cropped(frame.image_path, os.path.join(split, 'rgb', stem), camera,
                          offsets[i])
            if frame.mask_path is not None:
                os.makedirs(os.path.join(split, masks.SPLIT_FOLDER), exist_ok=True)
                _copy_cropped(frame.mask_path, os.path.join(split, masks.SPLIT_FOLDER, stem),
                              camera, offsets[i])
            write_camera(split, stem, normalization.to_model_camera(camera))
            b.update(1)
    points = normalization.to_model_point(model.points) if len(model.points) else model.points
    inside = float(np.mean(np.linalg.norm(points, axis=1) < 1.0)) if len(points) else None
    return {
        'normalization': dict(normalization.to_config(),
                              meaning='x_model = (x_colmap - center) * scale'),
        'model': os.path.relpath(model.folder, out),
        'views': {'train': len(frames) - len(held_out), 'test': len(held_out)},
        'points3D': int(len(points)),
        'points_in_foreground': inside,
    }


def _common_size(cameras, out: str):
    """Cameras cropped about their centre to the smallest undistorted width and height (the
    NeRF++ layout needs one image size; undistortion gives each camera its own), principal
    points shifted to match, and the (x, y) crop offset of each (None: not cropped)."""
    width = min(cam.width for cam in cameras)
    height = min(cam.height for cam in cameras)
    if all((cam.width, cam.height) == (width, height) for cam in cameras):
        return cameras, [None] * len(cameras)
    largest = max(cameras, key=lambda cam: cam.width * cam.height)
    if width < 0.8 * largest.width or height < 0.8 * largest.height:
        print(f'warning: the undistorted photos differ in size (from {width}x{height} to '
              f'{largest.width}x{largest.height}, photos from several cameras?); all are '
              f'cropped about their centre to {width}x{height} for {out}')
    out_cameras, offsets = [], []
    for cam in cameras:
        x0, y0 = (cam.width - width) // 2, (cam.height - height) // 2
        K = cam.K.copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        out_cameras.append(dataclasses.replace(cam, K=K, width=width, height=height))
        offsets.append((x0, y0) if (cam.width, cam.height) != (width, height) else None)
    return out_cameras, offsets


def _copy_cropped(src: str, dst_stem: str, camera, offset) -> None:
    """Copy an image file, or crop it at ``offset`` to ``camera``'s size as PNG."""
    if offset is None:
        shutil.copy2(src, dst_stem + os.path.splitext(src)[1].lower())
        return
    x0, y0 = offset
    with open_photo(src, error=SfmError, remedy=PHOTO_REMEDY) as img:
        img.crop((x0, y0, x0 + camera.width, y0 + camera.height)).save(dst_stem + '.png')


def _print_summary(report: dict, out: str) -> None:
    registered, unregistered = report['registered'], report['unregistered']
    total = len(registered) + len(unregistered)
    print(f'registered {len(registered)} of {total} photos '
          f'({100 * report["registration_rate"]:.0f}%); {report["points3D"]} sparse points, '
          f'{_percent(report["points_in_foreground"])} of them inside the foreground sphere')
    if unregistered:
        shown = ', '.join(unregistered[:20]) + (', ...' if len(unregistered) > 20 else '')
        print(f'not registered (left out of the dataset): {shown}')
        if report['registration_rate'] < 0.5:
            print('warning: fewer than half of the photos registered. ' + ADVICE)
        else:
            print(ADVICE)
    print(f'dataset written to {out} ({report["views"]["train"]} train / '
          f'{report["views"]["test"]} test views, NeRF++ layout); COLMAP workspace in '
          f'{os.path.join(out, "colmap")}; normalization in {os.path.join(out, SFM_FILE)}')


def _percent(value):
    return 'n/a' if value is None else f'{100 * value:.0f}%'


def sfm_normalization(dataset_root):
    """The normalization structure from motion applied to a photo run's dataset (which the
    export undoes, and a tracked camera in applies again), or None."""
    report = read_report(dataset_root) if dataset_root else None
    if not report or 'normalization' not in report:
        return None
    config = {k: v for k, v in report['normalization'].items() if k in ('center', 'scale')}
    return Normalization.from_config(config)
