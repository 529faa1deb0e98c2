"""Export a training run to DCC tools: cameras and proxy geometry for USD, Nuke and Blender.

``python -m mi_nerfpp export RUN --out DIR`` (:func:`export_run`) writes::

    DIR/scene.usda        USD (usd-core): one UsdGeom.Camera per dataset image under
                          /cameras/<split>/, named <split>_<image stem> (a valid identifier,
                          unique over the splits: importers that flatten the hierarchy, such as
                          Blender's, keep the names); the video's orbit path
                          (python -m mi_nerfpp video's default, 60 frames at 24 fps) as the
                          animated /cameras/video_orbit; the proxy referenced as /proxy
    DIR/proxy.usda        the proxy mesh as a UsdGeom.Mesh (vertex colours: displayColor; UVs:
                          primvars:st; a UsdPreviewSurface material mapping proxy_texture.png)
    DIR/proxy.ply         the same mesh as PLY (vertex colours, 8-bit sRGB)
    DIR/proxy.obj, .mtl   the same mesh as OBJ with UVs, its material mapping the texture (map_Kd)
    DIR/proxy_texture.png the texture of the proxy (8-bit sRGB, texture_size texels a side)
    DIR/sfm_points.ply    the structure-from-motion points, for a run trained from photos
    DIR/<split>.chan      Nuke .chan of the split's cameras, one frame per image (frame i + 1:
                          image i of DIR/cameras.json), and video_orbit.chan
    DIR/cameras.json      per camera: name, split, frame, world c2w (OpenCV), K, size

**Frame.** Everything is in the capture's world frame: the model's normalization is undone,
and for a run trained from photos also the one structure from motion applied (``sfm.json``),
so cameras and points are in COLMAP's frame.

**Cameras.** USD cameras look down -z with +y up (``c2w_usd = c2w_opencv·diag(1, -1, -1,
1)``), transforms stored as USD's row-vector matrices. Film back: ``horizontalAperture`` =
36 (mm; USD's lens attributes are in tenths of a scene unit, i.e. millimetres by convention),
``focalLength = fx·36/width``, ``verticalAperture = height·focalLength/fy``, and the principal
point as aperture offsets, ``(width/2 - cx)/width·horizontalAperture`` and ``(cy -
height/2)/height·verticalAperture``. Nuke's ``.chan`` holds per frame ``tx ty tz rx ry rz
vfov`` (degrees; Nuke's default rotation order ZXY, the camera looking down -z): set the
Camera's film back to the aspect of the images and its rotation order to ZXY before importing.

**Proxy.** Marching cubes (scikit-image) on the foreground's density on a ``resolution``³ grid
over the unit sphere, at the density whose opacity over one grid step is 1/2 (``level``:
``ln 2 / step``) unless given; vertex colours are the field's radiance there seen along the
inward normal, sRGB-encoded. Its UVs and the texture baked from the model's colour (neutral
appearance, seen from the best-facing training camera) come from
:mod:`mi_nerfpp.output.proxy_texture`. A model whose density never reaches the level gets no
proxy (a warning names the largest density reached and a ``--density`` that meshes); the
cameras are written all the same.

**All or nothing.** An export is written into ``DIR/.export.partial/`` and then moved into
``DIR`` in place of the files of the export before it (listed in ``DIR/.export.json``); an
export cut short (a signal, a full disk) leaves the earlier export as it was, and its partial
folder is removed by the next export. The move itself is a few renames during which Ctrl-C,
SIGTERM and SIGHUP wait (they take effect once it is done), so the folder always holds one
export or the other; only a kill that cannot be caught (SIGKILL, a power cut) can stop the move
begun, and the next export finishes it. Files in ``DIR`` that no export wrote are left alone.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import signal
import sys
import threading

import drjit as dr
import mitsuba as mi
import numpy as np
from skimage.measure import marching_cubes

from mi_nerfpp.core import budget
from mi_nerfpp.core.color import to_srgb8
from mi_nerfpp.core.frame import Normalization
from mi_nerfpp.data.colmap import read_model
from mi_nerfpp.data.sfm import read_report, sfm_normalization
from mi_nerfpp.core.geometry import nuke_rotation
from mi_nerfpp.files.atomic import as_text, atomic_write_path, check_writable_folder, name_bytes
from mi_nerfpp.files.readers import FileReadError, read_json
from mi_nerfpp.jobs.run import open_run
from mi_nerfpp.output.proxy_texture import (bake_texture, surface_color, unwrap, write_obj,
                                            write_texture)
from mi_nerfpp.output.video import orbit_cameras

# USD film back width (mm): a full-frame sensor.
FILM_BACK_MM = 36.0
# The texture of the proxy: its file, and its default size (texels a side, --texture-size).
TEXTURE, DEFAULT_TEXTURE_SIZE = 'proxy_texture.png', 1024
# The orbit path that ``video`` renders by default.
VIDEO_FRAMES, VIDEO_FPS = 60, 24


def world_cameras(model, cameras, sfm=None):
    """Model-frame ``cameras`` in the capture's world frame (module docs)."""
    cams = [model.normalization.to_world_camera(c) for c in cameras]
    return [sfm.to_world_camera(c) for c in cams] if sfm is not None else cams


def usd_camera_values(camera):
    """USD camera attributes of an OpenCV pinhole ``camera`` (module docs): ``(transform 4x4
    column-vector camera-to-world, looking down -z; dict of lens attributes)``."""
    K = camera.K
    c2w = camera.c2w @ np.diag([1.0, -1.0, -1.0, 1.0])
    focal = K[0, 0] * FILM_BACK_MM / camera.width
    vertical = camera.height * focal / K[1, 1]
    return c2w, {
        'focalLength': focal, 'horizontalAperture': FILM_BACK_MM, 'verticalAperture': vertical,
        'horizontalApertureOffset': (camera.width / 2 - K[0, 2]) / camera.width * FILM_BACK_MM,
        'verticalApertureOffset': (K[1, 2] - camera.height / 2) / camera.height * vertical}


def camera_prim_names(cameras) -> dict:
    """``{(split, index): prim name}`` of the dataset cameras (``{split: [Camera]}``): the split
    and the image stem as one valid identifier (``train_000000``), unique over the splits."""
    from pxr import Tf  # deferred: usd-core is the optional extra [export]
    names, taken = {}, set()
    for split, cams in cameras.items():
        for i, camera in enumerate(cams):
            base = Tf.MakeValidIdentifier(f'{split}_{as_text(camera.name or str(i))}')
            name, k = base, 2
            while name in taken:
                name, k = f'{base}_{k}', k + 1
            taken.add(name)
            names[split, i] = name
    return names


def _define_camera(stage, path, cameras, times=None):
    """A UsdGeom.Camera at ``path``: one camera, or an animation over ``times``."""
    from pxr import Gf, UsdGeom  # deferred: usd-core is the optional extra [export]
    cam = UsdGeom.Camera.Define(stage, path)
    op = cam.AddTransformOp()
    for i, camera in enumerate(cameras):
        time = None if times is None else times[i]
        c2w, lens = usd_camera_values(camera)
        op.Set(Gf.Matrix4d(c2w.T.tolist()), *(() if time is None else (time,)))
        for name, value in lens.items():
            attr = getattr(cam, f'Get{name[0].upper()}{name[1:]}Attr')()
            attr.Set(float(value), *(() if time is None else (time,)))
    cam.GetProjectionAttr().Set(UsdGeom.Tokens.perspective)
    cam.GetClippingRangeAttr().Set(Gf.Vec2f(0.01, 1e6))
    return cam


def write_usd(folder, cameras, video=None, proxy='proxy.usda'):
    """``folder/scene.usda`` (module docs); ``cameras``: ``{split: [Camera]}`` (world)."""
    from pxr import Usd  # deferred: usd-core is the optional extra [export]
    path = os.path.join(folder, 'scene.usda')
    with atomic_write_path(path) as tmp:      # a UTF-8 name: USD takes no other bytes
        _write_scene_usd(Usd.Stage.CreateNew(tmp), cameras, video, proxy)
    return path


def _write_scene_usd(stage, cameras, video, proxy):
    from pxr import UsdGeom  # deferred: usd-core is the optional extra [export]
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    root = UsdGeom.Xform.Define(stage, '/World')
    stage.SetDefaultPrim(root.GetPrim())
    UsdGeom.Scope.Define(stage, '/World/cameras')
    names = camera_prim_names(cameras)
    for split, cams in cameras.items():
        if not cams:
            continue
        UsdGeom.Scope.Define(stage, f'/World/cameras/{split}')
        for i, camera in enumerate(cams):
            prim = _define_camera(stage, f'/World/cameras/{split}/{names[split, i]}',
                                  [camera]).GetPrim()
            prim.SetDisplayName(as_text(camera.name))
            prim.SetCustomDataByKey('imageStem', as_text(camera.name))
            if name_bytes(camera.name):     # not UTF-8: the exact bytes too
                prim.SetCustomDataByKey('imageStemBytes', name_bytes(camera.name))
    if video:
        _define_camera(stage, '/World/cameras/video_orbit', video,
                       times=list(range(1, len(video) + 1)))
        stage.SetStartTimeCode(1)
        stage.SetEndTimeCode(len(video))
        stage.SetTimeCodesPerSecond(VIDEO_FPS)
    if proxy:
        stage.DefinePrim('/World/proxy').GetReferences().AddReference(proxy)
    stage.GetRootLayer().Save()


# The coarsest marching-cubes grid: at 2 or 3 points a side no grid point lies inside the unit
# sphere but its centre, and the mesh says nothing of the surface.
MIN_RESOLUTION = 8
# Bytes per point of the marching-cubes grid: its coordinates (3 float64), the density and
# the volume (float32), marching cubes' own arrays.
BYTES_PER_POINT = 48


def largest_resolution(memory: int | None = None) -> int:
    """The largest marching-cubes resolution whose grid fits in ``memory`` bytes (this
    machine's by default)."""
    memory = budget.memory_bytes() if memory is None else memory
    return int(round((memory / BYTES_PER_POINT) ** (1 / 3) - 0.5))


class NoSurfaceError(ValueError):
    """The foreground's density never reaches the proxy's level: nothing to mesh."""


def model_surface(model, resolution=128, level=None, chunk=1 << 18):
    """``(vertices, faces, outward unit normals)`` of the foreground's surface in the model's
    frame (module docs). Raises :class:`NoSurfaceError` when the density never reaches
    ``level``."""
    step = 2.0 / (resolution - 1)
    level = math.log(2.0) / step if level is None else float(level)
    axis = np.linspace(-1.0, 1.0, resolution)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing='ij'), axis=-1).reshape(-1, 3)
    fg, _ = model.radiance_fields()
    density = np.zeros(len(grid), dtype=np.float32)
    with dr.suspend_grad():
        for start in range(0, len(grid), chunk):
            p = grid[start:start + chunk].astype(np.float32)
            x = [mi.Float(p[:, i]) for i in range(3)]
            density[start:start + chunk] = np.array(fg.density(x), dtype=np.float32)
    density[np.linalg.norm(grid, axis=1) > 1.0] = 0.0
    volume = density.reshape(resolution, resolution, resolution)
    if not volume.max() > level:
        raise NoSurfaceError(
            f'the foreground density never reaches {level:.4g} on the {resolution}^3 grid (its '
            f'largest value there is {volume.max():.4g}); --density {0.5 * volume.max():.4g} '
            f'would mesh where it is densest')
    # scikit-image's gradient normals point towards lower values: out of the surface.
    verts, faces, normals, _ = marching_cubes(volume, level, spacing=(step, step, step))
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return verts - 1.0, faces.astype(np.int64), normals    # the grid starts at -1 on every axis


def model_to_world(model, vertices):
    """Model-frame ``vertices`` in the world frame of the model's normalization."""
    norm = model.normalization
    return vertices / norm.scale + norm.center_array


def proxy_mesh(model, resolution=128, level=None, chunk=1 << 18):
    """``(vertices (world), faces, colours (linear RGB))`` of the foreground's surface (module
    docs): the colours are the field's radiance seen along the inward normals. Raises
    :class:`NoSurfaceError` when the density never reaches ``level``."""
    verts, faces, normals = model_surface(model, resolution, level, chunk)
    colors = surface_color(model.radiance_fields()[0], verts, -normals)
    return model_to_world(model, verts), faces, colors


def write_ply(path, vertices, faces=None, colors=None):
    """An ASCII PLY of ``vertices`` (N x 3), optional ``faces`` (M x 3) and linear ``colours``
    (N x 3, written sRGB-encoded as 8-bit), atomically."""
    lines = ['ply', 'format ascii 1.0', f'element vertex {len(vertices)}',
             'property float x', 'property float y', 'property float z']
    if colors is not None:
        lines += ['property uchar red', 'property uchar green', 'property uchar blue']
        rgb8 = to_srgb8(np.asarray(colors, dtype=np.float32).reshape(-1, 1, 3)).reshape(-1, 3)
    if faces is not None:
        lines += [f'element face {len(faces)}', 'property list uchar int vertex_indices']
    lines.append('end_header')
    body = []
    for i, v in enumerate(vertices):
        row = f'{v[0]:.7g} {v[1]:.7g} {v[2]:.7g}'
        if colors is not None:
            row += ' {} {} {}'.format(*rgb8[i])
        body.append(row)
    if faces is not None:
        body += [f'3 {a} {b} {c}' for a, b, c in faces]
    with atomic_write_path(path) as tmp, open(tmp, 'w') as f:
        f.write('\n'.join(lines + body) + '\n')


def write_proxy_usd(path, vertices, faces, colors, uvs=None, uv_faces=None, texture=None):
    """The proxy mesh as ``path`` (a USD layer with a default prim /proxy); with ``uvs`` and
    ``uv_faces`` (:func:`~mi_nerfpp.output.proxy_texture.unwrap`) also its ``primvars:st``,
    and with ``texture`` (a file name beside ``path``) a material that maps it."""
    from pxr import Usd  # deferred: usd-core is the optional extra [export]
    with atomic_write_path(path) as tmp:      # a UTF-8 name: USD takes no other bytes
        _write_proxy_usd(Usd.Stage.CreateNew(tmp), vertices, faces, colors, uvs, uv_faces,
                         texture)


def _write_proxy_usd(stage, vertices, faces, colors, uvs, uv_faces, texture):
    from pxr import Sdf, UsdGeom, Vt  # deferred: usd-core is the optional extra [export]
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    mesh = UsdGeom.Mesh.Define(stage, '/proxy')
    stage.SetDefaultPrim(mesh.GetPrim())
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.asarray(vertices, np.float32)))
    mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(
        np.full(len(faces), 3, dtype=np.int32)))
    # scikit-image's winding faces the lower values; USD's default orientation is
    # right-handed: reverse the triangles so their normals point out of the surface.
    mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray.FromNumpy(
        np.ascontiguousarray(np.asarray(faces)[:, ::-1], dtype=np.int32).ravel()))
    color = mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex)
    # displayColor is linear by USD's convention.
    color.Set(Vt.Vec3fArray.FromNumpy(np.asarray(colors, np.float32)))
    if uvs is not None:
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
            'st', Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
        st.Set(Vt.Vec2fArray.FromNumpy(np.asarray(uvs, np.float32)))
        # One UV per face corner, in the reversed winding of the faces.
        st.SetIndices(Vt.IntArray.FromNumpy(
            np.ascontiguousarray(np.asarray(uv_faces)[:, ::-1], dtype=np.int32).ravel()))
    if texture is not None:
        _bind_texture(stage, mesh, texture)
    stage.GetRootLayer().Save()


def _bind_texture(stage, mesh, texture):
    """A UsdPreviewSurface material under the mesh whose diffuse colour is ``texture`` (an
    8-bit sRGB image) read through ``primvars:st``, bound to the mesh."""
    from pxr import Sdf, UsdShade  # deferred: usd-core is the optional extra [export]
    path = mesh.GetPath().AppendChild('material')
    material = UsdShade.Material.Define(stage, path)
    surface = UsdShade.Shader.Define(stage, path.AppendChild('surface'))
    surface.CreateIdAttr('UsdPreviewSurface')
    surface.CreateInput('roughness', Sdf.ValueTypeNames.Float).Set(1.0)
    reader = UsdShade.Shader.Define(stage, path.AppendChild('st'))
    reader.CreateIdAttr('UsdPrimvarReader_float2')
    reader.CreateInput('varname', Sdf.ValueTypeNames.Token).Set('st')
    image = UsdShade.Shader.Define(stage, path.AppendChild('texture'))
    image.CreateIdAttr('UsdUVTexture')
    image.CreateInput('file', Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(f'./{texture}'))
    image.CreateInput('sourceColorSpace', Sdf.ValueTypeNames.Token).Set('sRGB')
    for wrap in ('wrapS', 'wrapT'):
        image.CreateInput(wrap, Sdf.ValueTypeNames.Token).Set('clamp')
    image.CreateInput('st', Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.ConnectableAPI(), 'result')
    image.CreateOutput('rgb', Sdf.ValueTypeNames.Float3)
    surface.CreateInput('diffuseColor', Sdf.ValueTypeNames.Color3f).ConnectToSource(
        image.ConnectableAPI(), 'rgb')
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), 'surface')
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)


def write_chan(path, cameras):
    """A Nuke ``.chan`` of ``cameras``, one frame each from 1 (module docs)."""
    rows = []
    for i, camera in enumerate(cameras):
        c2w = camera.c2w @ np.diag([1.0, -1.0, -1.0, 1.0])
        rx, ry, rz = nuke_rotation(c2w)
        vfov = math.degrees(2 * math.atan(camera.height / (2 * camera.K[1, 1])))
        t = c2w[:3, 3]
        rows.append(f'{i + 1} {t[0]:.9g} {t[1]:.9g} {t[2]:.9g} {rx:.9g} {ry:.9g} {rz:.9g} '
                    f'{vfov:.9g}')
    with atomic_write_path(path) as tmp, open(tmp, 'w') as f:
        f.write('\n'.join(rows) + '\n')


def _sfm_points(dataset_root, sfm):
    """The structure-from-motion points of a photo run, in COLMAP's frame, or None."""
    model_dir = os.path.join(dataset_root, 'colmap', 'sparse', '0')
    if sfm is None or not os.path.isdir(model_dir):
        return None
    return read_model(model_dir).points


PARTIAL = '.export.partial'
OLD = '.export.old'
MANIFEST = '.export.json'


def export_run(run, out, resolution=128, density=None, opened=None, warn=None,
               texture_size=DEFAULT_TEXTURE_SIZE):
    """Write the files of the module docs for run folder ``run`` into ``out``, all or nothing
    (module docs); returns the paths written. ``opened``: :func:`mi_nerfpp.jobs.run.open_run`
    of the run, if already read; ``warn``: how a skipped proxy is reported."""
    model, meta, _, dataset = opened or open_run(run)
    warn = warn or (lambda text: print(text, file=sys.stderr, flush=True))
    check_writable_folder(out, 'export folder (--out)')
    finish_swap(out)
    staging = os.path.join(out, PARTIAL)
    shutil.rmtree(staging, ignore_errors=True)
    os.makedirs(staging)
    try:
        names = _write_export(model, meta, dataset, staging, resolution, density, warn,
                              texture_size)
        with atomic_write_path(os.path.join(staging, MANIFEST)) as tmp, open(tmp, 'w') as f:
            json.dump({'files': names}, f)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    finish_swap(out)
    return [os.path.join(out, name) for name in names]


def finish_swap(out):
    """Move a complete export staged in ``out/.export.partial/`` (its manifest written) into
    ``out``, in place of the files of the export before it; remove an incomplete one. Also
    finishes a move that was cut short."""
    staging, old = os.path.join(out, PARTIAL), os.path.join(out, OLD)
    manifest = os.path.join(staging, MANIFEST)
    if not os.path.isfile(manifest):
        shutil.rmtree(staging, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)
        return
    new = _manifest_files(manifest, remedy=f'delete the folder {staging} and export again')
    # A few renames: Ctrl-C, SIGTERM or SIGHUP arriving meanwhile take effect once they are
    # done, so that the folder is never left between the two exports; an interrupt raised in
    # them all the same (a signal already pending) finishes them first. Only a kill that
    # cannot be caught (SIGKILL, power) leaves the move begun, finished by the next export.
    with _signals_held():
        try:
            _move_in(out, staging, old, new)
        except (KeyboardInterrupt, SystemExit):
            _move_in(out, staging, old, new)
            _remove_staging(staging, old)
            raise
        _remove_staging(staging, old)


def _remove_staging(staging, old):
    shutil.rmtree(staging, ignore_errors=True)
    shutil.rmtree(old, ignore_errors=True)


def _move_in(out, staging, old, new):
    """The moves of :func:`finish_swap`; a move done already is skipped, so that they may be
    made again after an interruption."""
    manifest = os.path.join(staging, MANIFEST)
    os.makedirs(old, exist_ok=True)
    for name in _previous_export(out):
        if name not in new:                    # the new export overwrites the others
            with contextlib.suppress(FileNotFoundError):
                os.replace(os.path.join(out, name), os.path.join(old, name))
    for name in new:
        source = os.path.join(staging, name)
        if os.path.lexists(source):
            os.replace(source, os.path.join(out, name))
    if os.path.lexists(manifest):
        os.replace(manifest, os.path.join(out, MANIFEST))


@contextlib.contextmanager
def _signals_held():
    """Hold back SIGINT, SIGTERM and SIGHUP for the time of the ``with`` (in the main thread,
    where Python handles them); they are delivered at its end."""
    held = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}
    if threading.current_thread() is not threading.main_thread() or \
            not hasattr(signal, 'pthread_sigmask'):
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def _previous_export(out) -> list[str]:
    """The files the last export into ``out`` wrote (its manifest)."""
    try:
        return _manifest_files(os.path.join(out, MANIFEST))
    except FileReadError:       # none (no export before), or damaged: nothing to move aside
        return []


def _manifest_files(path, remedy=None) -> list[str]:
    """The names an export's manifest lists; :class:`FileReadError` for one that cannot be
    read or does not list names."""
    manifest = read_json(path, what='export manifest', remedy=remedy)
    names = manifest.get('files')
    if not isinstance(names, list) or not all(isinstance(name, str) and name and
                                              os.path.basename(name) == name for name in names):
        raise FileReadError(f'{path}: cannot read export manifest (its "files" is not a list of '
                            f'file names)' + (f': {remedy}' if remedy else ''))
    return names


def _write_proxy(model, train_cameras, sfm, out, resolution, density, texture_size):
    """The proxy's files (module docs), written into ``out``; their names. ``train_cameras``:
    in the model's frame. Raises :class:`NoSurfaceError` when there is nothing to mesh."""
    vertices, faces, normals = model_surface(model, resolution, density)
    fg, _ = model.radiance_fields()
    colors = surface_color(fg, vertices, -normals)
    uvs, uv_faces = unwrap(vertices, faces, texture_size)
    texture = bake_texture(model, vertices, normals, faces, uvs, uv_faces, train_cameras,
                           texture_size)
    vertices = model_to_world(model, vertices)
    if sfm is not None and len(vertices):
        vertices = np.stack([sfm.to_world_point(v) for v in vertices])
    write_ply(os.path.join(out, 'proxy.ply'), vertices, faces, colors)
    write_texture(os.path.join(out, TEXTURE), texture)
    write_obj(os.path.join(out, 'proxy.obj'), vertices, faces, uvs, uv_faces, TEXTURE)
    write_proxy_usd(os.path.join(out, 'proxy.usda'), vertices, faces, colors, uvs, uv_faces,
                    TEXTURE)
    return ['proxy.ply', TEXTURE, 'proxy.obj', 'proxy.mtl', 'proxy.usda']


def _write_export(model, meta, dataset, out, resolution, density, warn,
                  texture_size) -> list[str]:
    """The export's files, written into ``out``; their names."""
    sfm = sfm_normalization(meta.get('dataset'))
    cameras = {name: world_cameras(model, split.cameras, sfm) for name, split in
               (('train', dataset.train), ('validation', dataset.validation),
                ('test', dataset.test))}
    video = world_cameras(model, orbit_cameras(dataset.train.cameras, VIDEO_FRAMES,
                                               dataset.train.cameras[0]), sfm)
    written = []
    try:
        proxy = _write_proxy(model, dataset.train.cameras, sfm, out, resolution, density,
                             texture_size)
    except NoSurfaceError as e:
        warn(f'warning: export: no proxy mesh: {e}; the cameras are exported')
        proxy = []
    written += [os.path.join(out, name) for name in proxy]
    written.append(write_usd(out, cameras, video, 'proxy.usda' if proxy else None))
    odd = [c.name for cams in cameras.values() for c in cams if name_bytes(c.name)]
    if odd:
        warn(f'note: export: {len(odd)} image names are not UTF-8 (e.g. "{as_text(odd[0])}"): '
             f'USD and cameras.json have them as text with \\xNN for each such byte, and their '
             f'exact bytes in hexadecimal (customData imageStemBytes, name_bytes)')
    points = _sfm_points(meta.get('dataset'), sfm)
    if points is not None and len(points):
        write_ply(os.path.join(out, 'sfm_points.ply'), points)
        written.append(os.path.join(out, 'sfm_points.ply'))
    table = []
    for split, cams in list(cameras.items()) + [('video_orbit', video)]:
        if not cams:
            continue
        write_chan(os.path.join(out, f'{split}.chan'), cams)
        written.append(os.path.join(out, f'{split}.chan'))
        table += [dict({'name': as_text(c.name), 'split': split, 'frame': i + 1,
                        'c2w': c.c2w.tolist(), 'K': c.K.tolist(), 'width': c.width,
                        'height': c.height},
                       **({'name_bytes': name_bytes(c.name)} if name_bytes(c.name) else {}))
                  for i, c in enumerate(cams)]
    with atomic_write_path(os.path.join(out, 'cameras.json')) as tmp, open(tmp, 'w') as f:
        json.dump({'frame': 'capture world (normalization undone)', 'cameras': table}, f,
                  indent=1)
    written.append(os.path.join(out, 'cameras.json'))
    return [os.path.relpath(path, out) for path in written]
