"""The scene's shapes in the ``nerfpp`` integrator: the volumes up to the first surface, the
surfaces path traced with the volumes as their light (:mod:`mi_nerfpp.objects`), the shadow
catchers' differential shading, and their layers."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..layers import layer_channels
from ..objects import combine, path_rng, trace_paths
from .loading import appearance_transform


class ShapeLayers:
    """The shapes' methods of :class:`~mi_nerfpp.integrator.NeRFPPIntegrator` (which takes
    them as its own; they use those of :class:`~.volumes.VolumeLayers`)."""

    def _render_scene(self, parts, o, d, seed, path_seed, primal, catchers=True,
                      transform=True, camera=True):
        """Beauty and AOVs of camera rays through a scene with shapes (see
        :mod:`mi_nerfpp.objects`): the volumes up to the first surface, the surfaces path
        traced with the volumes as their light, the shadow catchers' differential shading
        (``catchers``); ``transform=False`` leaves out the appearance transform;
        ``camera=False``: the rays start on a surface (see :meth:`_volume`)."""
        n = dr.width(o)
        hit = dr.zeros(mi.Bool, n)
        far0 = None
        if parts.objects is not None:
            paths = trace_paths(parts.objects, mi.Ray3f(o, d), path_seed, self.max_depth,
                                self.rr_depth)
            far0 = dr.gather(mi.Float, paths.far, paths.segment(0))
            hit = ~dr.isinf(far0)
        L0, volumes, opacity0 = self._volume(o, d, seed, primal, far0, transform, camera)
        surfaces = dr.zeros(mi.Color3f, n)
        if parts.objects is not None:
            # Every segment's volumes: the camera segment's from above, the others here.
            L_seg = dr.zeros(mi.Color3f, paths.n * paths.depth)
            T_seg = dr.ones(mi.Float, paths.n * paths.depth)
            if paths.depth > 1:
                later = dr.compress(paths.valid & (dr.arange(mi.UInt32, dr.width(paths.valid))
                                                   >= n))
                if dr.width(later):
                    L_k, T_k = self._volume_batch(dr.gather(mi.Point3f, paths.o, later),
                                                  dr.gather(mi.Vector3f, paths.d, later),
                                                  dr.gather(mi.Float, paths.far, later), primal)
                    dr.scatter(L_seg, L_k, later)
                    dr.scatter(T_seg, T_k, later)
            dr.scatter(T_seg, 1.0 - opacity0, paths.segment(0))
            if self.volume_shadows:
                paths.vertex = self._shadowed_by_volumes(paths, primal)
            _, surfaces = combine(paths, L_seg, T_seg)
            if self.appearance_image >= 0 and transform:
                surfaces = appearance_transform(self.model, self.appearance_image)[0] * surfaces
        shadow = dr.zeros(mi.Color3f, n)
        if catchers and parts.catchers is not None and parts.objects is not None:
            shadow = self._shadow(parts, o, d, far0, L0, path_seed, primal)
        t_hit = dr.select(hit, far0, 0.0) if far0 is not None else dr.zeros(mi.Float, n)
        z_hit = t_hit
        if self._view is not None:
            center, axis = self._view
            z_hit = dr.dot(o - center, axis) + t_hit * dr.dot(dr.normalize(d), axis)
        # The surface is the depth where the volumes in front of it stay below half opacity.
        depth = dr.select(hit & (opacity0 < 0.5), z_hit, volumes['depth.Z'])
        distance = volumes['distance.Y'] + dr.select(hit, (1.0 - opacity0) * t_hit, 0.0)
        mask = dr.select(hit, 1.0, 0.0)
        fg_alpha = volumes['fg.A']
        aovs = dict(volumes, **layer_channels(
            depth=(depth,), distance=(distance,),
            obj=(surfaces.x, surfaces.y, surfaces.z, mask),
            obj_depth=(dr.select(hit, z_hit, 0.0),),
            shadow=(shadow.x, shadow.y, shadow.z),
            # Without the background: the foreground over the shapes, sample by sample.
            A=(dr.full(mi.Float, 1.0, n) if self.background
               else fg_alpha + (1.0 - fg_alpha) * mask,)))
        return L0 + surfaces + shadow, aovs

    def _shadowed_by_volumes(self, paths, primal):
        """The paths' vertex light with next-event estimation attenuated by the volumes'
        transmittance along each shadow ray: ``V - (1 - T)·V_nee``."""
        rays = dr.compress(paths.shadow_far > 0.0)
        if dr.width(rays) == 0:
            return paths.vertex
        _, T = self._volume_batch(dr.gather(mi.Point3f, paths.shadow_o, rays),
                                  dr.gather(mi.Vector3f, paths.shadow_d, rays),
                                  dr.gather(mi.Float, paths.shadow_far, rays), primal)
        vertex = mi.Color3f(paths.vertex)
        dr.scatter(vertex, dr.gather(mi.Color3f, vertex, rays)
                   - (1.0 - T) * dr.gather(mi.Color3f, paths.nee, rays), rays)
        return vertex

    def _shadow(self, parts, o, d, far0, L0, path_seed, primal):
        """Differential rendering on the shadow catchers (Debevec 1998): where a camera ray
        meets a catcher before any object, the radiance ``L0`` of the volumes along it is
        scaled by ``E_with / E_without``, the catcher's irradiance with and without the
        objects, both estimated from the same ``catcher_samples`` cosine-distributed
        directions (a direction that meets no object contributes the same volume radiance
        to both). Returns the change, ``(ratio - 1)·L0`` (0 where no catcher is seen, and
        where no direction meets an object)."""
        n, K = dr.width(o), self.catcher_samples
        ray = mi.Ray3f(o, d)
        if far0 is not None:
            ray.maxt = dr.select(dr.isinf(far0), dr.largest(mi.Float), far0)
        si = parts.catchers.ray_intersect(ray)
        caught = dr.compress(si.is_valid())
        shadow = dr.zeros(mi.Color3f, n)
        m = dr.width(caught)
        if m == 0:
            return shadow
        j = dr.arange(mi.UInt32, m * K)
        ray_of = dr.gather(mi.UInt32, caught, j // K)
        si_k = dr.gather(mi.SurfaceInteraction3f, si, ray_of)
        rng = path_rng(dr.gather(mi.UInt32, path_seed, ray_of), j % K + 1)
        # The hemisphere of the catcher that faces the camera.
        normal = si_k.sh_frame.n
        normal = dr.mulsign(normal, -dr.dot(normal, dr.gather(mi.Vector3f, d, ray_of)))
        u = mi.Point2f(rng.next_float32(), rng.next_float32())
        local = mi.warp.square_to_cosine_hemisphere(u)
        ray_k = si_k.spawn_ray(mi.Frame3f(normal).to_world(local))
        seed_k = rng.next_uint32()
        # Where no direction meets an object the ratio is 1: only catcher points next to
        # objects are shaded, each from all of its directions.
        blocked = parts.objects.ray_test(ray_k)
        near = dr.compress(dr.block_sum(dr.select(blocked, 1, 0), K) > 0)
        if dr.width(near) == 0:
            return shadow
        j = dr.arange(mi.UInt32, dr.width(near) * K)
        r = dr.gather(mi.UInt32, near, j // K) * K + j % K
        o_r, d_r = dr.gather(mi.Point3f, ray_k.o, r), dr.gather(mi.Vector3f, ray_k.d, r)
        without, _ = self._volume_batch(o_r, d_r, dr.full(mi.Float, dr.inf, dr.width(r)), primal)
        with_objects = mi.Color3f(without)
        hits = dr.compress(dr.gather(mi.Bool, blocked, r))
        def render_hits(o, d, seed):
            return self._render_scene(parts, o, d, None, seed, primal, catchers=False,
                                      transform=False, camera=False)
        hit_args = [dr.gather(mi.Point3f, o_r, hits), dr.gather(mi.Vector3f, d_r, hits),
                    dr.gather(mi.UInt32, seed_k, dr.gather(mi.UInt32, r, hits))]
        if primal:      # up to chunk_rays x catcher_samples rays: in chunks too
            L_hit, _ = self._chunked(render_hits, hit_args, dr.width(hits), progress=False)
        else:
            L_hit, _ = render_hits(*hit_args)
        dr.scatter(with_objects, L_hit, hits)
        e_with, e_without = dr.block_sum(with_objects, K), dr.block_sum(without, K)
        ratio = dr.select(e_without > 0.0, e_with / dr.maximum(e_without, 1e-30), 1.0)
        rays = dr.gather(mi.UInt32, caught, near)
        dr.scatter(shadow, (ratio - 1.0) * dr.gather(mi.Color3f, L0, rays), rays)
        return shadow
