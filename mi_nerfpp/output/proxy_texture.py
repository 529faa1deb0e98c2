"""A textured proxy: the export's mesh unwrapped into one UV atlas, and the model's colour baked
into a texture over it.

**UVs.** xatlas (the optional extra ``[export]``) cuts the mesh into charts and packs them into
one square atlas of ``size`` texels a side; the cuts split vertices, so the UVs have their own
indices (``uv_faces`` into ``uvs``: one UV triangle per mesh triangle). ``v`` grows upwards:
texel row 0 (the image's top) is ``v = 1``, as OBJ and USD read it.

**Texels.** Each texel whose centre lies in a UV triangle (found by casting a ray at the atlas
laid flat, with Mitsuba's ray tracer) gets the triangle's 3D point with the same barycentric
coordinates, and the interpolated vertex normal there.

**Colour.** The weighted mean of the model's colour rendered as its views are (both volumes,
neutral appearance) along the rays from the training cameras that see the point: the
:data:`CAMERAS_AVERAGED` that face it best (largest cosine between the outward normal and the
direction to the camera), of the :data:`CAMERAS_TRIED` best-facing, among those that have it
in front of them, inside their image, and unoccluded by the proxy itself (a ray from the point
towards the camera misses the mesh). Each camera weighs its cosine to the power
:data:`FACING_POWER`, normalized: what those cameras' views of the model show there, mostly the
best-facing ones', so that no one camera's view-dependent highlights and errors are baked in,
and few rays that graze the surface (where a proxy off the model's surface shows the colour of
a point beside it). A texel that no camera sees takes the foreground's radiance at the point
seen along its inward normal (:func:`surface_color`), as the vertex colours do.

**Padding.** Texels outside every chart take the mean of their filled neighbours, ring by ring,
:data:`DILATE_TEXELS` times; the rest take the texture's mean colour, so that mip-mapping blends
no black into the charts' edges.
"""
from __future__ import annotations

import os

import drjit as dr
import imageio.v3 as iio
import mitsuba as mi
import numpy as np

from mi_nerfpp.core.color import to_srgb8
from mi_nerfpp.core.rays import Rays
from mi_nerfpp.files.atomic import atomic_write_path
from mi_nerfpp.output.views import ViewRenderer

# The smallest texture (texels a side) that holds a chart of every triangle of a small proxy.
MIN_TEXTURE_SIZE = 16
# Bytes per texel of the bake: the texel's point, normal, colour, cameras and their cosines and
# coverage (numpy), the rays cast for it (Dr.Jit: CHUNK at a time, whatever the cameras per
# texel), and the 8-bit image; an estimate, rounded up (the default export, 1024² texels and
# 58,000 triangles, peaked at 0.7 GiB with the process and the model, one camera per texel;
# averaging CAMERAS_AVERAGED = 4 cameras, a 1024² export of a 10,500-triangle proxy peaked at
# 671 MiB, against 666 MiB with one).
BYTES_PER_TEXEL = 256
# Rings of empty texels around the charts filled with their neighbours' colour.
DILATE_TEXELS = 8
# Training cameras tried per texel, best-facing first, before the texel is seen along its
# inward normal (all of them occluded).
CAMERAS_TRIED = 8
# Cameras whose colours a texel averages: the best-facing that see it, of those tried. On the
# test's capture (tests/jobs/test_textured_proxy.py, 5 trained runs, seeds 0 and 2-5), with
# FACING_POWER 8, held-out PSNR inside the proxy gained 0.05-0.45 dB (mean 0.27) over one camera;
# 3 cameras were within 0.05 dB of 4, 8 within 0.014 dB (for up to twice the rays).
CAMERAS_AVERAGED = 4
# The power of the facing cosine that weighs each camera's colour (normalized; 0: a plain mean).
# On the same runs power 1 gained more held-out PSNR on four (0.39-0.87 dB) but lost 0.11 dB on
# one, and it blurred a known colour baked on a sphere, which held-out views of 32 x 24 pixels
# may not resolve (test_the_bake_puts_a_known_colour_where_it_belongs: RMS 0.083 against 0.028
# with one camera; power 4: 0.040; power 8: 0.028).
FACING_POWER = 8.0
# Texels (x cameras) handled at once.
CHUNK = 1 << 18


def largest_texture_size(memory: int) -> int:
    """The largest texture size (texels a side) whose bake fits in ``memory`` bytes."""
    return int((memory / BYTES_PER_TEXEL) ** 0.5)


def surface_color(field, points, directions):
    """Linear radiance of ``field`` at ``points`` (N x 3, model frame) seen along
    ``directions`` (N x 3, normalized here), neutral appearance."""
    n = len(points)
    if n == 0:
        return np.zeros((0, 3))
    x = [mi.Float(points[:, i].astype(np.float32)) for i in range(3)]
    d = directions / np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-12)
    d = mi.Vector3f(*[mi.Float(d[:, i].astype(np.float32)) for i in range(3)])
    with dr.suspend_grad():
        if getattr(field, 'deferred', False):
            _, features = field.features(x)
            rgb = field.color(features, d)
        else:
            _, rgb = field(x, d, dr.arange(mi.UInt32, n))
    return np.clip(np.array(rgb, dtype=np.float64).reshape(3, -1).T, 0.0, None)


def unwrap(vertices, faces, size):
    """``(uvs (K x 2, in [0, 1]), uv_faces (M x 3 indices into uvs))``: xatlas's atlas of the
    mesh, packed for a texture of ``size`` texels a side."""
    import xatlas  # deferred: xatlas is the optional extra [export]
    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(vertices, np.float32),
                   np.ascontiguousarray(faces, np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution, pack.padding, pack.bilinear = int(size), 2, True
    atlas.generate(pack_options=pack)
    if atlas.atlas_count != 1:      # with a resolution and no texels per unit, xatlas makes one
        raise RuntimeError(f'xatlas packed the proxy into {atlas.atlas_count} atlases, not one')
    _, uv_faces, uvs = atlas[0]
    return np.clip(uvs.astype(np.float64), 0.0, 1.0), uv_faces.astype(np.int64)


def _mesh_scene(points, faces):
    """A Mitsuba scene of one triangle mesh (``points`` N x 3), for ray casts."""
    mesh = mi.Mesh('proxy', len(points), len(faces))
    params = mi.traverse(mesh)
    params['vertex_positions'] = mi.Float(np.ascontiguousarray(points, np.float32).ravel())
    params['faces'] = mi.UInt32(np.ascontiguousarray(faces, np.uint32).ravel())
    params.update()
    return mi.load_dict({'type': 'scene', 'proxy': mesh})


def _vector(a):
    return mi.Vector3f(*[mi.Float(np.ascontiguousarray(a[:, i], np.float32)) for i in range(3)])


def texel_surface(vertices, normals, faces, uvs, uv_faces, size):
    """``(rows, cols, points, normals)`` of the texels whose centres lie in a UV triangle
    (module docs): their indices in the image and their 3D points and unit outward normals."""
    uv_points = np.concatenate([uvs, np.zeros((len(uvs), 1))], axis=1)
    scene = _mesh_scene(uv_points, uv_faces)
    rows, cols = np.divmod(np.arange(size * size), size)
    found = []
    for start in range(0, len(rows), CHUNK):
        r, c = rows[start:start + CHUNK], cols[start:start + CHUNK]
        origin = np.stack([(c + 0.5) / size, 1.0 - (r + 0.5) / size, np.ones(len(r))], axis=1)
        with dr.suspend_grad():
            hit = scene.ray_intersect_preliminary(mi.Ray3f(_vector(origin), mi.Vector3f(0, 0, -1)))
        valid = np.array(hit.is_valid(), dtype=bool)
        prim = np.array(hit.prim_index, dtype=np.int64)[valid]
        b = np.array(hit.prim_uv, dtype=np.float64).reshape(2, -1).T[valid]
        found.append((r[valid], c[valid], prim, b))
    r, c, prim, b = (np.concatenate(parts) for parts in zip(*found))
    weights = np.stack([1.0 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], axis=1)[:, :, None]
    corners = faces[prim]
    points = (vertices[corners] * weights).sum(axis=1)
    n = (normals[corners] * weights).sum(axis=1)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return r, c, points, n


def seeing_cameras(points, normals, cameras, vertices, faces, count=None):
    """``(chosen, facing)``, both points x ``count`` (default :data:`CAMERAS_AVERAGED`): per
    point, the indices of the best-facing cameras of ``cameras`` that see it unoccluded by the
    mesh, best first, then -1; and their facing cosines, then 0 (module docs)."""
    count = CAMERAS_AVERAGED if count is None else count
    chosen = np.full((len(points), count), -1, dtype=np.int32)
    facing_of = np.zeros((len(points), count), dtype=np.float32)
    if not cameras or not len(points):
        return chosen, facing_of
    centers = np.stack([c.c2w[:3, 3] for c in cameras])
    w2c = np.stack([np.linalg.inv(c.c2w) for c in cameras])
    K = np.stack([c.K for c in cameras])
    size = np.array([[c.width, c.height] for c in cameras], dtype=np.float64)
    scene = _mesh_scene(vertices, faces)
    edge = np.linalg.norm(vertices[faces[:, 0]] - vertices[faces[:, 1]], axis=1).mean()
    per_chunk = max(1, CHUNK // len(cameras))
    for start in range(0, len(points), per_chunk):
        p, n = points[start:start + per_chunk], normals[start:start + per_chunk]
        to_cam = centers[None] - p[:, None]                       # points x cameras x 3
        distance = np.linalg.norm(to_cam, axis=2)
        facing = np.einsum('pcj,pj->pc', to_cam, n) / np.maximum(distance, 1e-12)
        local = np.einsum('cij,pj->pci', w2c[:, :3, :3], p) + w2c[None, :, :3, 3]
        depth = local[..., 2]
        pixel = np.einsum('cij,pcj->pci', K, local)[..., :2] / np.where(
            depth > 1e-9, depth, 1.0)[..., None]
        seen = (facing > 0) & (depth > 1e-9) & np.all((pixel >= 0) & (pixel < size[None]), axis=2)
        score = np.where(seen, facing, -np.inf)
        order = np.argsort(-score, axis=1)[:, :CAMERAS_TRIED]
        best = chosen[start:start + per_chunk]                    # views: filled in place
        best_facing = facing_of[start:start + per_chunk]
        found = np.zeros(len(p), dtype=np.int64)                  # cameras found per point
        for k in range(order.shape[1]):
            camera = order[:, k]
            open_ = (found < count) & np.isfinite(score[np.arange(len(p)), camera])
            if not open_.any():
                break
            idx = np.flatnonzero(open_)
            origin = p[idx] + n[idx] * 0.5 * edge
            target = centers[camera[idx]] - origin
            length = np.linalg.norm(target, axis=1)
            with dr.suspend_grad():
                ray = mi.Ray3f(_vector(origin), _vector(target / length[:, None]))
                ray.maxt = mi.Float(length.astype(np.float32))    # up to the camera's centre
                blocked = np.array(scene.ray_test(ray), dtype=bool)
            idx = idx[~blocked]
            best[idx, found[idx]] = camera[idx]
            best_facing[idx, found[idx]] = score[idx, camera[idx]]
            found[idx] += 1
    return chosen, facing_of


def camera_weights(facing):
    """The weights (rows summing to 1, or all 0 where no camera sees the point) of the cameras
    whose facing cosines are ``facing`` (points x cameras; 0: no camera): each cosine to the
    power :data:`FACING_POWER`, normalized over the point's cameras."""
    facing = np.asarray(facing, dtype=np.float64)
    w = np.where(facing > 0, np.maximum(facing, 0.0) ** FACING_POWER, 0.0)
    total = w.sum(axis=1, keepdims=True)
    return np.where(total > 0, w / np.where(total > 0, total, 1.0), 0.0)


def model_colors(model, origins, points):
    """Linear colour of ``model`` rendered along the rays from ``origins`` through ``points``
    (model frame), as its views are rendered (neutral appearance)."""
    renderer = ViewRenderer(model)
    integrator = renderer.scene.integrator()
    frame = integrator.frame(renderer.scene)
    d = points - origins
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    o = model.normalization.to_world_point(origins)
    with dr.suspend_grad():
        L, _ = integrator.render_rays(frame, Rays(mi.Point3f(_vector(o)), _vector(d)))
    return np.clip(np.array(L, dtype=np.float64).reshape(3, -1).T, 0.0, None)


def dilate(image, covered, rings=DILATE_TEXELS):
    """``image`` (H x W x 3) with the texels outside ``covered`` filled (module docs)."""
    image, covered = image.copy(), covered.copy()
    for _ in range(rings):
        if covered.all():
            break
        total = np.zeros_like(image)
        count = np.zeros(covered.shape)
        padded = np.pad(image * covered[..., None], ((1, 1), (1, 1), (0, 0)))
        weight = np.pad(covered.astype(np.float64), 1)
        h, w = covered.shape
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                total += padded[dy:dy + h, dx:dx + w]
                count += weight[dy:dy + h, dx:dx + w]
        grow = ~covered & (count > 0)
        image[grow] = total[grow] / count[grow, None]
        covered |= grow
    if covered.any():
        image[~covered] = image[covered].mean(axis=0)
    return image


def texel_colors(model, points, normals, cameras, vertices, faces):
    """Linear colour (N x 3) of the proxy's surface ``points`` (outward unit ``normals``,
    model frame) as the texture bakes it (module docs: the weighted mean over the cameras that
    see each point, or the colour along its inward normal)."""
    chosen, facing = seeing_cameras(points, normals, cameras, vertices, faces)
    centers = np.stack([c.c2w[:3, 3] for c in cameras]) if cameras else np.zeros((0, 3))
    field, _ = model.radiance_fields()
    colors = np.zeros((len(points), 3))
    per_chunk = max(1, CHUNK // chosen.shape[1])                  # texels x cameras: CHUNK rays
    for start in range(0, len(points), per_chunk):
        part = slice(start, start + per_chunk)
        seen, w, p = chosen[part], camera_weights(facing[part]), points[part]
        color = np.zeros((len(p), 3))
        pair = seen >= 0                                          # texels x cameras
        if pair.any():
            rows = np.nonzero(pair)[0]
            views = np.zeros(seen.shape + (3,))
            views[pair] = model_colors(model, centers[seen[pair]], p[rows])
            color = (views * w[..., None]).sum(axis=1)
        none = ~pair.any(axis=1)
        if none.any():
            color[none] = surface_color(field, p[none], -normals[part][none])
        colors[part] = color
    return colors


def bake_texture(model, vertices, normals, faces, uvs, uv_faces, cameras, size):
    """The linear texture (``size`` x ``size`` x 3, padded) of the proxy of ``model`` (model
    frame: ``vertices``, outward vertex ``normals``, ``faces``; ``cameras``: the training
    cameras in the model's frame), module docs."""
    rows, cols, points, n = texel_surface(vertices, normals, faces, uvs, uv_faces, size)
    image = np.zeros((size, size, 3))
    image[rows, cols] = texel_colors(model, points, n, cameras, vertices, faces)
    covered = np.zeros((size, size), dtype=bool)
    covered[rows, cols] = True
    return dilate(image, covered)


def write_texture(path, image):
    """The linear ``image`` as an 8-bit sRGB PNG, atomically."""
    with atomic_write_path(path) as tmp:
        iio.imwrite(tmp, to_srgb8(np.asarray(image, np.float32)), extension='.png')


def write_obj(path, vertices, faces, uvs, uv_faces, texture):
    """``path`` (.obj) and the material library beside it (same stem, .mtl) whose one material
    maps ``texture`` (a file name beside them) as the diffuse colour, atomically. ``faces`` in
    scikit-image's winding, reversed here so that the normals point out of the surface."""
    stem = os.path.splitext(os.path.basename(path))[0]
    mtl = os.path.splitext(path)[0] + '.mtl'
    with atomic_write_path(mtl) as tmp, open(tmp, 'w') as f:
        f.write(f'newmtl {stem}\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd {texture}\n')
    lines = [f'mtllib {os.path.basename(mtl)}', f'o {stem}']
    lines += [f'v {x:.7g} {y:.7g} {z:.7g}' for x, y, z in vertices]
    lines += [f'vt {u:.7g} {v:.7g}' for u, v in uvs]
    lines += [f'usemtl {stem}', 's off']
    lines += ['f ' + ' '.join(f'{a + 1}/{t + 1}' for a, t in zip(face[::-1], uv[::-1]))
              for face, uv in zip(faces, uv_faces)]
    with atomic_write_path(path) as tmp, open(tmp, 'w') as f:
        f.write('\n'.join(lines) + '\n')
