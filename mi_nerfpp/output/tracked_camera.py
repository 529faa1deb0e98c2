"""Tracked cameras in: a shot's camera from a matchmove, with the shot's own frame numbers.

``python -m mi_nerfpp video RUN --path FILE`` and ``render SCENE --camera FILE`` read, besides
the project's own camera path files (:mod:`mi_nerfpp.output.camera_path`), the camera files of
a tracker or a DCC, told apart by extension and content (:func:`shot_format`):

* **USD** (``.usd``, ``.usda``, ``.usdc``, ``.usdz``; usd-core): a ``UsdGeom.Camera`` prim (one
  of several picked by name) and its animation. Its world transform
  (``ComputeLocalToWorldTransform``, the camera looking down -z with +y up), focal length,
  apertures and aperture offsets are evaluated at every whole frame of the stage's time range
  (``startTimeCode`` to ``endTimeCode``; without one, of the camera's time samples; a camera
  with neither is one frame, 1). A Z-up stage is turned into the Y-up frame that ``export``
  writes (and that Blender's USD importer turns into its Z-up one: ``x, y, z -> x, z, -y``).
  Positions are taken in the stage's units as they are: ``export`` authors no
  ``metersPerUnit`` and Blender 4.2 neither scales on import nor on export; the lens attributes
  are in tenths of a stage unit, but only their ratios place the film.
* **Nuke .chan**: per line ``frame tx ty tz rx ry rz vfov`` as Nuke's *Export chan file* and
  ``export`` write it (degrees, rotation order ZXY, the camera looking down -z; the film back
  of the images' aspect, so ``vfov`` spans the image height).
* **nerfstudio's camera_path.json** (the rendered form ``ns-render camera-path`` reads):
  ``camera_path`` of ``{"camera_to_world": 16 numbers (row-major 4 x 4, OpenGL), "fov":
  vertical degrees, "aspect"}``, ``render_width``/``render_height``, ``fps``; frames numbered
  from 0 as ``ns-render`` numbers them.

**The film.** Each frame's lens is a :class:`Window`, the film seen at unit distance in front
of the camera (OpenCV: x right, y down), and which of its extents spans the image: USD's
horizontal aperture spans the image width (``fx = width·focalLength/horizontalAperture``; the
principal point from the offsets, ``cx = width/2 - horizontalApertureOffset·fx/focalLength``,
``cy = height/2 + verticalApertureOffset·fx/focalLength``), the inverse of ``export``'s USD
cameras for square pixels; a ``.chan``'s and nerfstudio's vertical field of view spans the
height, the principal point at the centre. Pixels are square. A file's own image size is
nerfstudio's ``render_width`` x ``render_height`` (its per-frame ``aspect`` then ignored, as
``ns-render`` ignores it); otherwise the caller's width (the training images', the scene's film)
with the film's aspect (USD's apertures, nerfstudio's ``aspect``), or the caller's size for a
``.chan``. A film whose aspect changes between frames (an animated aperture, nerfstudio
keyframes of several aspects) gives each frame of ``render`` its own size; a video's frames
share one, so its size is then asked for (``--res``), each frame keeping its field of view
across the extent that spans the image.

**The frame.** The cameras are in the frame of ``export``'s files: the capture's world, COLMAP's
for a run trained from photos (the normalization structure from motion applied, undone by
``export``, is applied again), then moved into the model's frame by its normalization, as the
project's camera path files are (:func:`Shot.cameras`). So a camera matchmoved against the
exported cameras or proxy lines the plates up with the shot.

usd-core is imported where a USD file is read.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import re
from dataclasses import dataclass

import numpy as np

from mi_nerfpp.core.geometry import rotation_zxy
from mi_nerfpp.data import Camera
from mi_nerfpp.data.cameras import opengl_to_opencv
from mi_nerfpp.data.sfm import sfm_normalization
from mi_nerfpp.files.readers import FileReadError, read_json
from mi_nerfpp.output.camera_path import DEFAULT_FPS, MAX_FRAMES, CameraPathError

USD_EXTENSIONS = ('.usd', '.usda', '.usdc', '.usdz')
CHAN_EXTENSION = '.chan'
# The columns of a .chan line, as Nuke's Export chan file and ``export`` write them.
CHAN_COLUMNS = ('frame', 'tx', 'ty', 'tz', 'rx', 'ry', 'rz', 'vfov')
# nerfstudio's camera path: the one key that tells it from the project's own path file.
NERFSTUDIO_KEY = 'camera_path'
# What to do about a camera file that cannot be read.
REMEDY = 'export the camera from the tracker or DCC again'
# The file name of a frame: the camera file's stem and its frame number (``shot.1001``).
FRAME_DIGITS = 4
# A Z-up stage's world turned into the Y-up frame of ``export`` (x, y, z -> x, z, -y).
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
# How far from a rotation (after its scale is divided out) a camera's transform may be.
ROTATION_TOLERANCE = 1e-4
# How far (relative) the film aspects of a shot's frames may differ and still share one size.
ASPECT_TOLERANCE = 1e-4


class TrackedCameraError(CameraPathError):
    """A camera file that cannot be read (one line: the file, the problem, what to do)."""


def _fail(path, detail, remedy=REMEDY):
    raise TrackedCameraError(f'{path}: {detail}' + (f': {remedy}' if remedy else ''))


@dataclass(frozen=True)
class Window:
    """The film seen at unit distance in front of the camera (OpenCV: x right, y down):
    ``left``/``right`` (None where the file leaves the width to the image's aspect) and
    ``top``/``bottom``; ``fit``: the extent that spans the image, ``'width'`` or
    ``'height'`` (module docs)."""
    left: float | None
    right: float | None
    top: float
    bottom: float
    fit: str

    @property
    def aspect(self) -> float | None:
        """Width over height of the film, None where the file does not say."""
        if self.left is None:
            return None
        return (self.right - self.left) / (self.bottom - self.top)

    def intrinsics(self, width: int, height: int) -> np.ndarray:
        """K of an image of ``width`` x ``height`` square pixels through this film."""
        if self.fit == 'width':
            fx = width / (self.right - self.left)
            cx = -self.left * fx
            cy = height / 2 - fx * (self.top + self.bottom) / 2
        else:
            fx = height / (self.bottom - self.top)
            cy = -self.top * fx
            middle = 0.0 if self.left is None else (self.left + self.right) / 2
            cx = width / 2 - fx * middle
        return np.array([[fx, 0, cx], [0, fx, cy], [0, 0, 1]], dtype=np.float64)


@dataclass
class ShotFrame:
    """One frame of a shot: its number in the file, camera-to-world (OpenCV, the frame of
    ``export``'s files) and film; ``focal_mm``: the focal length in millimetres where the
    file says (USD)."""
    number: int
    c2w: np.ndarray
    window: Window
    focal_mm: float | None = None


@dataclass
class Shot:
    """The frames of a camera file (module docs), in order of their numbers."""
    path: str
    format: str
    frames: list
    fps: float = DEFAULT_FPS
    size: tuple | None = None        # the file's own image size (nerfstudio's)
    camera: str = ''                 # the USD camera's prim path

    @property
    def numbers(self) -> list:
        return [f.number for f in self.frames]

    @property
    def span(self) -> str:
        """The file's frames as ``first-last`` (one frame: its number)."""
        return _span(self.numbers[0], self.numbers[-1])

    @property
    def frame_name(self) -> str:
        """The name pattern of its frame files (``str.format`` of the frame number):
        the file's stem, a dot and the number of :data:`FRAME_DIGITS` digits."""
        stem = os.path.splitext(os.path.basename(self.path))[0] or 'shot'
        return stem.replace('{', '{{').replace('}', '}}') + '.{:0%dd}' % FRAME_DIGITS

    def within(self, frame_range) -> Shot:
        """The frames ``first <= number <= last`` of ``frame_range`` (None: all); a range
        reaching outside the file's frames is refused, naming them."""
        if frame_range is None:
            return self
        first, last = frame_range
        if first < self.numbers[0] or last > self.numbers[-1]:
            raise TrackedCameraError(
                f'{self.path}: frames {_span(first, last)} asked for, but the file has frames '
                f'{self.span}: ask for frames within them')
        frames = [f for f in self.frames if first <= f.number <= last]
        return Shot(self.path, self.format, frames, self.fps, self.size, self.camera)

    def frame(self, number: int) -> ShotFrame:
        """The frame ``number``; refused, naming the file's frames, where it has none."""
        for f in self.frames:
            if f.number == number:
                return f
        raise TrackedCameraError(f'{self.path}: no frame {number}; the file has frames '
                                 f'{self.span}: ask for one of them')

    def image_size(self, width: int, height: int) -> tuple:
        """The frames' image size: the file's own, else ``width`` with the film's aspect,
        else ``width`` x ``height`` (module docs). Frames whose film aspects differ have no
        one size: refused, naming the first two, unless the file gives the size."""
        if self.size:
            return self.size
        aspects = [(f.number, f.window.aspect) for f in self.frames
                   if f.window.aspect is not None]
        if not aspects:
            return int(width), int(height)
        aspect = aspects[0][1]
        for (before, previous), (number, other) in zip(aspects, aspects[1:]):
            if abs(other / aspect - 1.0) > ASPECT_TOLERANCE:
                raise TrackedCameraError(
                    f'{self.path}: the film aspect changes from {previous:.4g} at frame {before} '
                    f'to {other:.4g} at frame {number}, and the frames of a video share one '
                    f'image size: give it with --res WxH (each frame keeps its field of view '
                    f'across the {"width" if self.frames[0].window.fit == "width" else "height"}'
                    f'), or ask for frames of one aspect with --frame-range')
        return int(width), max(1, int(round(width / aspect)))

    def cameras(self, width: int, height: int, normalizations=()) -> dict:
        """``{frame number: Camera}`` of ``width`` x ``height`` pixels, each moved by the
        normalizations in turn (``to_model_camera``: the structure-from-motion one of a photo
        run, then the model's), named by :attr:`frame_name`."""
        out = {}
        for f in self.frames:
            camera = Camera(f.window.intrinsics(width, height), f.c2w, width, height,
                            self.frame_name.format(f.number))
            for normalization in normalizations:
                camera = normalization.to_model_camera(camera)
            out[f.number] = camera
        return out


def digest(cameras: dict) -> str:
    """A short hash of ``{number: Camera}`` (frames rendered for other cameras are not
    reused)."""
    text = json.dumps([[n, np.round(c.c2w, 12).tolist(), np.round(c.K, 9).tolist(), c.width,
                        c.height] for n, c in cameras.items()])
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _span(first, last) -> str:
    return f'{first}' if first == last else f'{first}-{last}'


def parse_frame_range(text: str) -> tuple:
    """``FIRST-LAST`` or ``N`` (whole frame numbers, FIRST <= LAST) as ``(first, last)``;
    ValueError otherwise."""
    match = re.fullmatch(r'\s*(-?\d+)\s*(?:-\s*(-?\d+)\s*)?', text)
    if not match:
        raise ValueError(f"expects FIRST-LAST or one frame number, e.g. 1001-1010, got '{text}'")
    first = int(match.group(1))
    last = int(match.group(2)) if match.group(2) is not None else first
    if last < first:
        raise ValueError(f"the last frame comes before the first in '{text}'")
    return first, last


# ----------------------------------------------------------------------------- formats

def shot_format(path) -> str | None:
    """``'usd'``, ``'chan'`` or ``'nerfstudio'`` for a camera file this module reads, None for
    anything else (the project's own camera path file): by extension, and a JSON file by its
    ``camera_path`` list."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext in USD_EXTENSIONS:
        return 'usd'
    if ext == CHAN_EXTENSION:
        return 'chan'
    try:
        data = read_json(path, expect=None)
    except FileReadError:
        return None           # read again, and its problem named, as a camera path file
    if isinstance(data, dict) and isinstance(data.get(NERFSTUDIO_KEY), list):
        return 'nerfstudio'
    return None


def read_shot(path, camera: str | None = None) -> Shot:
    """The shot of a camera file (module docs); ``camera``: the USD camera's name (its prim
    name, its parent's, as Blender names the object, or its path). Raises
    :class:`TrackedCameraError` naming the file and what is wrong."""
    path = os.fsdecode(os.fspath(path))
    kind = shot_format(path)
    if kind is None:
        # A damaged JSON file: its problem, named by the reader.
        read_json(path, what='camera file', remedy=REMEDY, expect=None, error=TrackedCameraError)
        _fail(path, 'not a camera file this reads (USD .usd/.usda/.usdc/.usdz, Nuke .chan, '
                    "nerfstudio's camera_path.json with its camera_path list)", None)
    if camera is not None and kind != 'usd':
        _fail(path, f'camera {camera} asked for, but only a USD file holds several cameras '
                    f'to pick from', None)
    if not os.path.isfile(path):
        _fail(path, 'not found' if not os.path.exists(path) else 'a folder, not a file',
              'give the camera file')
    shot = {'usd': _read_usd, 'chan': _read_chan, 'nerfstudio': _read_nerfstudio}[kind](
        path, camera)
    if not shot.frames:
        _fail(path, 'the file has no frames')
    return shot


def _rigid(path, matrix, where) -> np.ndarray:
    """A camera-to-world matrix with its scale divided out; refused unless a rotation and a
    translation remain."""
    c2w = np.array(matrix, dtype=np.float64)
    if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
        _fail(path, f'{where}: the camera transform is not a finite 4 x 4 matrix')
    norms = np.linalg.norm(c2w[:3, :3], axis=0)
    if not np.all(norms > 0):
        _fail(path, f'{where}: the camera transform has a zero scale')
    c2w[:3, :3] /= norms
    rotation = c2w[:3, :3]
    if not (np.allclose(rotation.T @ rotation, np.eye(3), atol=ROTATION_TOLERANCE)
            and np.linalg.det(rotation) > 0 and np.allclose(c2w[3], [0, 0, 0, 1])):
        _fail(path, f'{where}: the camera transform is sheared, mirrored or projective, not a '
                    f'rotation, translation and scale')
    return c2w


# ----------------------------------------------------------------------------- USD

def _usd_detail(error) -> str:
    """The reason in usd-core's error text (the parser's first message, without the file)."""
    messages = re.findall(r": '(.*?)'\s*(?:\n|$)", str(error))
    for message in messages:
        if not message.startswith('Failed to open layer'):
            return re.sub(r'^.*?:\d+:\d+: ', '', message).strip()
    return 'usd-core cannot open it: damaged, cut short or not USD'


def _stage(path):
    from pxr import Tf, Usd  # deferred: usd-core is the optional extra [export]
    try:
        stage = Usd.Stage.Open(path)
    except Tf.ErrorException as e:
        _fail(path, f'cannot read USD file ({_usd_detail(e)})')
    if stage is None:
        _fail(path, 'cannot read USD file (usd-core cannot open it)')
    return stage


def _pick_camera(path, stage, name):
    from pxr import UsdGeom  # deferred: usd-core is the optional extra [export]
    prims = [p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)]
    if not prims:
        _fail(path, 'no camera in the USD file (no UsdGeom.Camera prim)',
              'export the file with its cameras (Blender: Export > USD with Cameras ticked)')
    names = ', '.join(p.GetName() for p in prims)
    if name is None:
        if len(prims) > 1:
            _fail(path, f'{len(prims)} cameras in the USD file ({names})',
                  'pick one with --camera NAME')
        return prims[0]
    found = [p for p in prims if name in (p.GetName(), str(p.GetPath()),
                                          p.GetParent().GetName())]
    if not found:
        _fail(path, f'no camera named {name} in the USD file; its cameras: {names}', None)
    if len(found) > 1:
        _fail(path, f'{len(found)} cameras named {name} in the USD file '
                    f'({", ".join(str(p.GetPath()) for p in found)})',
              'give the camera\'s path with --camera')
    return found[0]


def _usd_numbers(path, stage, prim) -> list:
    """The whole frames of the stage's time range; else of the camera's time samples (its
    lens and its transform, its ancestors' included); else frame 1 alone."""
    from pxr import UsdGeom  # deferred: usd-core is the optional extra [export]
    if stage.HasAuthoredTimeCodeRange():
        start, end = stage.GetStartTimeCode(), stage.GetEndTimeCode()
    else:
        times = set()
        for attribute in prim.GetAttributes():
            times.update(attribute.GetTimeSamples())
        node = prim
        while node and not node.IsPseudoRoot():
            if node.IsA(UsdGeom.Xformable):
                times.update(UsdGeom.Xformable(node).GetTimeSamples())
            node = node.GetParent()
        if not times:
            return [1]
        start, end = min(times), max(times)
    first, last = math.ceil(start), math.floor(end)
    if last < first:
        return [first]
    if last - first + 1 > MAX_FRAMES:
        _fail(path, f'{prim.GetPath()}: frames {first}-{last} are more than {MAX_FRAMES:,}',
              None)
    return list(range(first, last + 1))


def _read_usd(path, name) -> Shot:
    from pxr import Usd, UsdGeom  # deferred: usd-core is the optional extra [export]
    stage = _stage(path)
    prim = _pick_camera(path, stage, name)
    camera = UsdGeom.Camera(prim)
    up = Z_UP_TO_Y_UP if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z else np.eye(4)
    mm_per_tenth = 100.0 * UsdGeom.GetStageMetersPerUnit(stage)     # lens units -> mm
    frames = []
    for number in _usd_numbers(path, stage, prim):
        time = Usd.TimeCode(number)
        where = f'{prim.GetPath()} at frame {number}'
        if camera.GetProjectionAttr().Get(time) != UsdGeom.Tokens.perspective:
            _fail(path, f'{where}: the camera is not perspective', 'give a perspective camera')
        lens = [camera.GetFocalLengthAttr().Get(time), camera.GetHorizontalApertureAttr().Get(
            time), camera.GetVerticalApertureAttr().Get(time),
            camera.GetHorizontalApertureOffsetAttr().Get(time),
            camera.GetVerticalApertureOffsetAttr().Get(time)]
        focal, horizontal, vertical, h_offset, v_offset = (float(v) for v in lens)
        if not (all(math.isfinite(v) for v in lens) and focal > 0 and horizontal > 0
                and vertical > 0):
            _fail(path, f'{where}: focal length {focal:g}, apertures {horizontal:g} x '
                        f'{vertical:g}: all must be positive')
        transform = np.array(camera.ComputeLocalToWorldTransform(time), dtype=np.float64).T
        c2w = opengl_to_opencv(_rigid(path, up @ transform, where))
        # The film at unit distance (OpenCV: y down, USD's film y up).
        window = Window((h_offset - horizontal / 2) / focal, (h_offset + horizontal / 2) / focal,
                        -(v_offset + vertical / 2) / focal, -(v_offset - vertical / 2) / focal,
                        'width')
        frames.append(ShotFrame(number, c2w, window, focal * mm_per_tenth))
    return Shot(path, 'usd', frames, _usd_fps(stage), camera=str(prim.GetPath()))


def _usd_fps(stage) -> float:
    """The frames per second: the stage's time codes per second (a frame per whole time
    code), else its frames per second, else :data:`DEFAULT_FPS`."""
    layer = stage.GetRootLayer()
    if layer.HasTimeCodesPerSecond():
        return float(layer.timeCodesPerSecond)
    if layer.HasFramesPerSecond():
        return float(layer.framesPerSecond)
    return float(DEFAULT_FPS)


# ----------------------------------------------------------------------------- Nuke .chan

def _read_text(path) -> str:
    """The text of ``path`` (UTF-8), or the error of a file that cannot be read."""
    try:
        with open(path, 'rb') as f:
            data = f.read()
    except OSError as e:
        _fail(path, f'cannot read Nuke .chan file ({e.strerror or type(e).__name__})')
    if not data.strip():
        _fail(path, 'cannot read Nuke .chan file (the file is empty)')
    try:
        return data.decode('utf-8-sig')
    except UnicodeDecodeError as e:
        _fail(path, f'cannot read Nuke .chan file (not text: byte 0x{e.object[e.start]:02x} '
                    f'at offset {e.start})')


def _read_chan(path, _name=None) -> Shot:
    frames = []
    for line_number, line in enumerate(_read_text(path).splitlines(), 1):
        fields = line.split()
        if not fields or fields[0].startswith('#'):
            continue
        where = f'line {line_number}'
        if len(fields) != len(CHAN_COLUMNS):
            _fail(path, f'{where} has {len(fields)} columns where {len(CHAN_COLUMNS)} are '
                        f'expected ({" ".join(CHAN_COLUMNS)})',
                  'export the camera with Nuke\'s Export chan file (field of view included)')
        try:
            values = [float(v) for v in fields]
        except ValueError:
            bad = next(v for v in fields if not _is_number(v))
            _fail(path, f"{where}: '{bad}' is not a number")
        if not all(math.isfinite(v) for v in values):
            _fail(path, f'{where}: a value is not finite')
        frame, tx, ty, tz, rx, ry, rz, vfov = values
        if frame != int(frame):
            _fail(path, f'{where}: frame {frame:g} is not a whole number')
        if frames and int(frame) <= frames[-1].number:
            _fail(path, f'{where}: frame {int(frame)} does not follow frame '
                        f'{frames[-1].number}')
        if not 0 < vfov < 180:
            _fail(path, f'{where}: vertical field of view {vfov:g} is not between 0 and 180 '
                        f'degrees')
        c2w = np.eye(4)
        c2w[:3, :3] = rotation_zxy(rx, ry, rz)
        c2w[:3, 3] = tx, ty, tz
        half = math.tan(math.radians(vfov) / 2)
        frames.append(ShotFrame(int(frame), opengl_to_opencv(c2w),
                                Window(None, None, -half, half, 'height')))
    return Shot(path, 'chan', frames)


def _is_number(text) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


# ----------------------------------------------------------------------------- nerfstudio

def _positive_number(value) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value) and value > 0)


def _read_nerfstudio(path, _name=None) -> Shot:
    data = read_json(path, what="nerfstudio camera path", remedy=REMEDY,
                     error=TrackedCameraError)
    kind = data.get('camera_type', 'perspective')
    if kind != 'perspective':
        _fail(path, f"camera_type '{kind}': only perspective cameras are rendered",
              'render a perspective camera path')
    size = None
    if 'render_width' in data or 'render_height' in data:
        size = data.get('render_width'), data.get('render_height')
        if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size):
            _fail(path, f'render_width x render_height must be whole numbers of pixels, got '
                        f'{size[0]!r} x {size[1]!r}')
    fps = data.get('fps', DEFAULT_FPS)
    if not _positive_number(fps):
        _fail(path, f'fps must be a positive number, got {fps!r}')
    frames = []
    for i, entry in enumerate(data[NERFSTUDIO_KEY]):
        where = f'camera_path[{i}]'
        if not isinstance(entry, dict) or 'camera_to_world' not in entry or 'fov' not in entry:
            _fail(path, f'{where}: expected {{"camera_to_world": 16 numbers, "fov": degrees}}')
        try:
            matrix = np.array(entry['camera_to_world'], dtype=np.float64).reshape(4, 4)
        except (TypeError, ValueError):
            _fail(path, f'{where}: camera_to_world must be 16 numbers (a row-major 4 x 4)')
        fov, aspect = entry['fov'], entry.get('aspect', size[0] / size[1] if size else None)
        if not (_positive_number(fov) and fov < 180):
            _fail(path, f'{where}: fov must be a vertical field of view in degrees between 0 '
                        f'and 180, got {fov!r}')
        if aspect is not None and not _positive_number(aspect):
            _fail(path, f'{where}: aspect must be a positive number, got {aspect!r}')
        half = math.tan(math.radians(fov) / 2)
        side = None if aspect is None else half * aspect
        window = Window(None if side is None else -side, side, -half, half, 'height')
        frames.append(ShotFrame(i, opengl_to_opencv(_rigid(path, matrix, where)), window))
    return Shot(path, 'nerfstudio', frames, float(fps), size)


def capture_normalizations(dataset_root) -> list:
    """The normalizations that move a camera of ``export``'s frame into the dataset's world
    frame, in turn: structure from motion's for a run trained from photos, none otherwise."""
    sfm = sfm_normalization(dataset_root)
    return [] if sfm is None else [sfm]
