"""Mitsuba shapes inside the reconstruction: the geometric half of the ``nerfpp`` integrator.

The reconstruction is an emitting, absorbing medium (no scattering) that fills the space
between the scene's surfaces. A light path is a chain of segments ``k = 0, 1, …``: segment 0
is the camera ray, segment ``k + 1`` leaves the surface vertex that ends segment ``k`` in the
direction its BSDF samples; a segment that hits nothing runs to infinity. Along segment ``k``
the two volumes give radiance ``L_k`` and transmittance ``T_k`` (:func:`render.render_rays
<mi_nerfpp.core.render.render_rays>` with ``far`` = the segment's length). With ``β_k`` the path
throughput (BSDF weights) before segment ``k`` and ``V_k`` the light that the surface vertex
at its end adds by itself (emission of an area light, MIS-weighted, and next-event
estimation towards the scene's emitters, already multiplied by ``β_k``), the radiance of the
path is

    ``L = Σ_k P_k (β_k L_k + T_k V_k)``,  ``P_0 = 1``,  ``P_{k+1} = P_k T_k``

(:func:`combine`). The geometry (intersections, BSDF and emitter sampling, Russian roulette)
does not depend on the volumes, so it is traced first for every path in one symbolic loop
(:func:`trace_paths`, the loop of Mitsuba's ``path`` integrator) that records the segments;
the volumes are then rendered for all segments at once, in chunks, outside the loop (they
need kernels of their own: block prefix sums, compaction).

Next-event estimation records its shadow ray too, so that the integrator can attenuate its
light by the volumes' transmittance along it. Environment maps are refused (the
background volume is the environment; directional emitters are fine). Shapes listed as
shadow catchers are proxies of reconstructed surfaces, not objects: paths ignore them
(:func:`split_scene`).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


@dataclass
class SceneParts:
    """The scene split for the integrator: ``objects`` (a :class:`mitsuba.Scene` of the
    inserted shapes and every emitter, or None when there are none) and ``catchers`` (a scene
    of the shadow-catcher shapes, or None)."""
    objects: object
    catchers: object


def split_scene(scene, catcher_ids=(), proxy_ids=()):
    """Split ``scene`` into its objects and its shadow catchers (shapes named by id).

    ``proxy_ids`` name shapes that stand for the reconstruction and are never rendered, like
    the catchers, but receive no shadows (a catcher listed in ``proxies`` only, e.g. with its
    shadows turned off). Refuses ids the scene does not have and, in a scene with shapes,
    environment emitters, saying what to do. The scene itself serves as ``objects`` when it
    has neither catchers nor proxies.
    """
    shapes = list(scene.shapes())
    ids = [s.id() for s in shapes]
    for what, wanted in (('shadow_catchers', catcher_ids), ('proxies', proxy_ids)):
        missing = [c for c in wanted if c not in ids]
        if missing:
            raise ValueError(
                f"nerfpp: {what} names {', '.join(missing)}, which the scene has no "
                f"shape for; its shapes are {', '.join(ids) or 'none'} (give the shape an "
                f"id=\"...\" attribute and list that id)")
    for emitter in scene.emitters() if shapes else ():     # (no shapes: emitters unused)
        flags = emitter.flags()
        if (mi.has_flag(flags, mi.EmitterFlags.Infinite)
                and not mi.has_flag(flags, mi.EmitterFlags.DeltaDirection)):
            name = str(emitter).split('[')[0].strip()
            raise ValueError(
                f"nerfpp: the scene has an environment emitter ({name}); the "
                f"reconstruction's background volume is the environment of a nerfpp render: "
                f"remove it (area, point, spot and directional emitters may light the objects)")
    hidden = set(catcher_ids) | set(proxy_ids)
    if not hidden:
        return SceneParts(scene if shapes else None, None)
    # Keyed by their own ids: load_dict gives every object its key as id.
    catchers = {_key(s, i): s for i, s in enumerate(shapes) if s.id() in catcher_ids}
    objects = {_key(s, i): s for i, s in enumerate(shapes) if s.id() not in hidden}
    # Area emitters travel with their shapes; the others (point, spot, directional) are
    # scene children of their own. (Only area emitters have a shape: Mitsuba's Python
    # Emitter of a point light has no ``shape()`` at all.)
    emitters = {_key(e, f'emitter{i}'): e for i, e in enumerate(scene.emitters())
                if not mi.has_flag(e.flags(), mi.EmitterFlags.Surface)}
    objects_scene = None
    if objects:
        objects_scene = mi.load_dict(dict({'type': 'scene'}, **objects, **emitters))
    catchers_scene = mi.load_dict(dict({'type': 'scene'}, **catchers)) if catchers else None
    return SceneParts(objects_scene, catchers_scene)


def _key(obj, fallback):
    return obj.id() or f'_{fallback}'


@dataclass
class Paths:
    """Segments of ``n`` paths, ``depth`` per path, stored segment-major (segment ``k`` of path
    ``i`` at ``k·n + i``): origin, direction, length ``far`` (``inf``: it leaves the geometry),
    throughput ``beta`` before it, light ``vertex`` of the surface vertex at its end (times
    ``beta``), and whether the path has the segment at all. ``nee`` is the part of ``vertex``
    that next-event estimation adds, and ``shadow_o``, ``shadow_d``, ``shadow_far`` its
    shadow ray (``shadow_far`` 0 where there is none), for the volumes' transmittance."""
    n: int
    depth: int
    o: mi.Point3f
    d: mi.Vector3f
    far: mi.Float
    beta: mi.Color3f
    vertex: mi.Color3f
    valid: mi.Bool
    nee: mi.Color3f
    shadow_o: mi.Point3f
    shadow_d: mi.Vector3f
    shadow_far: mi.Float

    def segment(self, k):
        """Index array of segment ``k`` of every path."""
        return dr.arange(mi.UInt32, self.n) + k * self.n


def path_rng(state, stream=0):
    """A PCG32 generator per lane from that lane's ``state`` (UInt32) and ``stream`` alone,
    hashed together (TEA), unlike ``mi.PCG32(size, initstate)``, which also adds the lane
    index: paths then do not depend on where their ray sits in a chunk."""
    hi, lo = mi.sample_tea_32(mi.UInt32(state), mi.UInt32(stream))
    rng = mi.PCG32(size=dr.width(hi))
    rng.seed((mi.UInt64(hi) << 32) | mi.UInt64(lo), mi.UInt64(0))
    return rng


def mis_weight(pdf_a, pdf_b):
    """Power heuristic (β = 2) of Mitsuba's integrators."""
    a2 = dr.square(pdf_a)
    return dr.detach(dr.select(pdf_a > 0, a2 / dr.fma(pdf_b, pdf_b, a2), 0))


@dr.syntax
def trace_paths(scene, ray, seed, max_depth, rr_depth=5):
    """Trace the geometry of one path per ray (see module docs): a symbolic loop of at most
    ``max_depth`` segments, random numbers from a PCG32 stream per path seeded by ``seed``
    (UInt32 per ray, so the paths do not depend on how the rays are chunked)."""
    n = dr.width(ray.o)
    size = n * max_depth
    seg_o, seg_d = dr.zeros(mi.Point3f, size), dr.zeros(mi.Vector3f, size)
    seg_far = dr.full(mi.Float, dr.inf, size)
    seg_beta, seg_vertex = dr.zeros(mi.Color3f, size), dr.zeros(mi.Color3f, size)
    seg_valid = dr.zeros(mi.Bool, size)
    seg_nee, seg_shadow_far = dr.zeros(mi.Color3f, size), dr.zeros(mi.Float, size)
    seg_shadow_o, seg_shadow_d = dr.zeros(mi.Point3f, size), dr.zeros(mi.Vector3f, size)

    ctx = mi.BSDFContext()
    rng = path_rng(seed)
    index = dr.arange(mi.UInt32, n)
    ray = mi.Ray3f(ray)
    depth = mi.UInt32(0)
    beta = mi.Color3f(1.0)
    eta = mi.Float(1.0)
    active = mi.Bool(True)
    si_prev = dr.zeros(mi.SurfaceInteraction3f, n)
    pdf_prev = mi.Float(1.0)
    delta_prev = mi.Bool(True)

    while dr.hint(active, max_iterations=max_depth, label='nerfpp paths'):
        si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=depth == 0)
        k = depth * n + index
        dr.scatter(seg_o, ray.o, k)
        dr.scatter(seg_d, ray.d, k)
        dr.scatter(seg_far, dr.select(si.is_valid(), si.t, dr.inf), k)
        dr.scatter(seg_beta, beta, k)
        dr.scatter(seg_valid, True, k)

        # An emitter found by the previous BSDF sample, MIS-weighted against emitter sampling.
        ds = mi.DirectionSample3f(scene, si=si, ref=si_prev)
        mis = mis_weight(pdf_prev, scene.pdf_emitter_direction(si_prev, ds, ~delta_prev))
        Le = beta * mis * ds.emitter.eval(si, si.is_valid())

        active_next = (depth + 1 < max_depth) & si.is_valid()
        bsdf = si.bsdf(ray)

        # Next-event estimation: shapes occlude here; the integrator attenuates it by the
        # volumes along the recorded shadow ray (volume_shadows).
        active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        u_em = mi.Point2f(rng.next_float32(), rng.next_float32())
        ds, em_weight = scene.sample_emitter_direction(si, u_em, True, active_em)
        active_em &= ds.pdf != 0.0
        value_em, pdf_em = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), active_em)
        mis_em = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, pdf_em))
        Lr = dr.select(active_em, beta * mis_em * value_em * em_weight, 0.0)
        dr.scatter(seg_vertex, mi.Color3f(Le + Lr), k)
        dr.scatter(seg_nee, mi.Color3f(Lr), k)
        shadow = si.spawn_ray(ds.d)
        dr.scatter(seg_shadow_o, shadow.o, k, active_em)
        dr.scatter(seg_shadow_d, shadow.d, k, active_em)
        # An emitter at infinity (directional): the shadow ray crosses the background
        # volume but not its opaque end at infinity.
        dr.scatter(seg_shadow_far, dr.minimum(ds.dist, 1e30), k, active_em)

        u1 = rng.next_float32()
        u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
        sample, weight = bsdf.sample(ctx, si, u1, u2, active_next)
        ray = si.spawn_ray(si.to_world(sample.wo))
        beta *= weight
        eta *= sample.eta
        si_prev = dr.detach(si, True)
        pdf_prev = sample.pdf
        delta_prev = mi.has_flag(sample.sampled_type, mi.BSDFFlags.Delta)

        beta_max = dr.max(beta)
        active_next &= beta_max != 0.0
        rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
        rr_active = depth >= rr_depth
        beta[rr_active] *= dr.rcp(rr_prob)
        active_next &= ~rr_active | (rng.next_float32() < rr_prob)
        depth += 1
        active = active_next

    return Paths(n, max_depth, seg_o, seg_d, seg_far, seg_beta, seg_vertex, seg_valid, seg_nee,
                 seg_shadow_o, seg_shadow_d, seg_shadow_far)


def combine(paths, L, T):
    """``L = Σ_k P_k (β_k L_k + T_k V_k)`` (module docs) from the volumes' radiance ``L`` and
    transmittance ``T`` of every segment (segment-major like ``paths``, any value where the
    segment is not valid). Returns ``(total, surfaces)``: the path radiance, and the part of it
    that comes from beyond the first surface, ``total - L_0``."""
    P = dr.ones(mi.Float, paths.n)
    surfaces = dr.zeros(mi.Color3f, paths.n)
    first = None
    for k in range(paths.depth):
        i = paths.segment(k)
        valid = dr.gather(mi.Bool, paths.valid, i)
        L_k = dr.select(valid, dr.gather(mi.Color3f, L, i), 0.0)
        T_k = dr.select(valid, dr.gather(mi.Float, T, i), 1.0)
        beta = dr.gather(mi.Color3f, paths.beta, i)
        vertex = dr.gather(mi.Color3f, paths.vertex, i)
        if k == 0:
            first = L_k
        else:
            surfaces += P * beta * L_k
        surfaces += P * T_k * vertex
        P = P * T_k
    return first + surfaces, surfaces
