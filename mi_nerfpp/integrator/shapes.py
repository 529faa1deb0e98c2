"""The scene's shapes in the ``nerfpp`` integrator: the volumes up to the first surface, the
surfaces path traced with the volumes as their light (:mod:`mi_nerfpp.core.objects`), the shadow
catchers' differential shading, and their layers."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_nerfpp.core.layers import layer_channels
from mi_nerfpp.core.objects import combine, path_rng, trace_paths
from mi_nerfpp.core.rays import Rays
from mi_nerfpp.integrator.loading import appearance_transform
from mi_nerfpp.integrator.volumes import VolumeRenderer


class ShapeRenderer:
    """Renders camera rays through a scene with shapes, with the settings of one
    :class:`~mi_nerfpp.integrator.NeRFPPIntegrator` (``max_depth``, ``rr_depth``,
    ``volume_shadows``, ``catcher_samples``, ...) and its :class:`~.volumes.VolumeRenderer`
    for the volumes along every path segment."""

    def __init__(self, integrator, volumes: VolumeRenderer):
        self.integrator, self.volumes = integrator, volumes

    def layers(self, parts, rays: Rays, primal, environment=None, record=None):
        """Beauty and AOVs of camera ``rays`` (:class:`~mi_nerfpp.core.rays.Rays`, with their
        ``path_seed``) through a scene with shapes (see
        :mod:`mi_nerfpp.core.objects`): the volumes up to the first surface, the surfaces path
        traced with the volumes as their light, the shadow catchers' differential shading
        (with the ``environment`` of :meth:`catcher_environment`, where the scene has
        catchers). ``record`` (a dict, or None) receives the volumes' per-sample render (see
        :meth:`~.volumes.VolumeRenderer.layers`) and the surfaces' ``far``, ``hit``, ``L0``,
        ``surfaces`` and ``shadow``."""
        ig = self.integrator
        o, d, n = rays.o, rays.d, rays.width
        hit = dr.zeros(mi.Bool, n)
        far0 = None
        if parts.objects is not None:
            paths = trace_paths(parts.objects, mi.Ray3f(o, d), rays.path_seed, ig.max_depth,
                                ig.rr_depth)
            far0 = dr.gather(mi.Float, paths.far, paths.segment(0))
            hit = ~dr.isinf(far0)
        rays = rays.replace(far=far0)       # the camera segment ends at the first surface
        L0, volumes, opacity0 = self.volumes.layers(rays, primal, record=record)
        surfaces = dr.zeros(mi.Color3f, n)
        if parts.objects is not None:
            # Every segment's volumes: the camera segment's from above, the others here.
            L_seg = dr.zeros(mi.Color3f, paths.n * paths.depth)
            T_seg = dr.ones(mi.Float, paths.n * paths.depth)
            if paths.depth > 1:
                later = dr.compress(paths.valid & (dr.arange(mi.UInt32, dr.width(paths.valid))
                                                   >= n))
                if dr.width(later):
                    L_k, T_k = self.volumes.segments(
                        Rays(paths.o, paths.d, far=paths.far).gather(later), primal)
                    dr.scatter(L_seg, L_k, later)
                    dr.scatter(T_seg, T_k, later)
            dr.scatter(T_seg, 1.0 - opacity0, paths.segment(0))
            if ig.volume_shadows:
                paths.vertex = self.shadowed_by_volumes(paths, primal)
            _, surfaces = combine(paths, L_seg, T_seg)
            if ig.appearance_image >= 0:
                surfaces = appearance_transform(ig.model, ig.appearance_image)[0] * surfaces
        shadow = dr.zeros(mi.Color3f, n)
        if environment is not None and parts.objects is not None:
            shadow = self.shadow(parts, rays, L0, environment)
        t_hit = dr.select(hit, far0, 0.0) if far0 is not None else dr.zeros(mi.Float, n)
        z_hit = ig.camera_depth(o, d, t_hit)
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
            A=(dr.full(mi.Float, 1.0, n) if ig.background
               else fg_alpha + (1.0 - fg_alpha) * mask,)))
        if record is not None:
            record.update(far=far0, hit=hit, L0=L0, surfaces=surfaces, shadow=shadow)
        return L0 + surfaces + shadow, aovs

    def shadowed_by_volumes(self, paths, primal):
        """The paths' vertex light with next-event estimation attenuated by the volumes'
        transmittance along each shadow ray: ``V - (1 - T)·V_nee``."""
        rays = dr.compress(paths.shadow_far > 0.0)
        if dr.width(rays) == 0:
            return paths.vertex
        _, T = self.volumes.segments(
            Rays(paths.shadow_o, paths.shadow_d, far=paths.shadow_far).gather(rays), primal)
        vertex = mi.Color3f(paths.vertex)
        dr.scatter(vertex, dr.gather(mi.Color3f, vertex, rays)
                   - (1.0 - T) * dr.gather(mi.Color3f, paths.nee, rays), rays)
        return vertex

    def catcher_environment(self, parts):
        """The reconstruction as the shadow catchers see it: the volumes' radiance along
        :data:`ENVIRONMENT_SIZE` directions (a latitude-longitude map) from the centre of the
        catchers' bounding box, rendered once per frame, as a bilinear texture
        (:func:`environment_direction`)."""
        height, width = ENVIRONMENT_SIZE
        v, u = dr.meshgrid(dr.arange(mi.Float, height), dr.arange(mi.Float, width),
                           indexing='ij')
        d = environment_direction((u + 0.5) / width, (v + 0.5) / height)
        n = height * width
        centre = parts.catchers.bbox().center()
        o = mi.Point3f(*[dr.full(mi.Float, float(c), n) for c in centre])
        with dr.suspend_grad():
            L, _ = self.volumes.segments(Rays(o, d, far=dr.full(mi.Float, dr.inf, n)),
                                         primal=True)
            texels = dr.ravel(dr.detach(L))
            dr.eval(texels)
        return mi.Texture2f(mi.TensorXf(texels, (height, width, 3)),
                            filter_mode=dr.FilterMode.Linear, wrap_mode=dr.WrapMode.Clamp)

    def shadow(self, parts, rays, L0, environment):
        """Differential rendering on the shadow catchers (Debevec 1998), the occlusion part:
        where a camera ray of ``rays`` (their ``far``: the first object, their ``path_seed``)
        meets a catcher before any object, the radiance ``L0`` of the
        volumes along it is scaled by ``E_with / E_without``, the catcher's irradiance with
        and without the objects, estimated from the same ``catcher_samples``
        cosine-distributed directions over its hemisphere that faces the camera, each carrying
        the reconstruction's radiance from the catcher ``environment``; a direction that meets
        an object carries none. Returns the change, ``(ratio - 1)·L0``: never positive, and
        exactly 0 where no catcher is seen or no direction meets an object. The light that
        objects reflect onto the catcher is left out (no colour bleeding), and the
        environment is seen from one point (the catchers' centre), whose parallax mostly
        cancels in the ratio."""
        o, d, far0, path_seed = rays.o, rays.d, rays.far, rays.path_seed
        n, K = rays.width, self.integrator.catcher_samples
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
        blocked = parts.objects.ray_test(ray_k)
        texel = environment.eval(environment_uv(ray_k.d))
        L_k = mi.Color3f(texel[0], texel[1], texel[2])
        e_without = dr.block_sum(L_k, K)
        e_with = dr.block_sum(dr.select(blocked, 0.0, L_k), K)
        any_blocked = dr.block_sum(dr.select(blocked, 1, 0), K) > 0
        ratio = dr.select(any_blocked & (e_without > 0.0),
                          e_with / dr.maximum(e_without, 1e-30), 1.0)
        change = (ratio - 1.0) * dr.gather(mi.Color3f, L0, caught)
        dr.scatter(shadow, dr.select(any_blocked, change, 0.0), caught)
        return shadow


# Texels (height, width) of the latitude-longitude map of the reconstruction that the shadow
# catchers see (:meth:`ShapeRenderer.catcher_environment`): 8192 volume rays per frame.
ENVIRONMENT_SIZE = (64, 128)


def environment_direction(u, v):
    """The unit direction at ``(u, v)`` of the latitude-longitude map (v = 0: +y, u from the
    -z axis round through +x)."""
    phi, theta = dr.two_pi * (u - 0.5), dr.pi * v
    sin_theta = dr.sin(theta)
    return mi.Vector3f(sin_theta * dr.sin(phi), dr.cos(theta), -sin_theta * dr.cos(phi))


def environment_uv(d):
    """The inverse of :func:`environment_direction`."""
    return mi.Point2f(dr.atan2(d.x, -d.z) * dr.inv_two_pi + 0.5,
                      dr.safe_acos(dr.clip(d.y, -1.0, 1.0)) * dr.inv_pi)
