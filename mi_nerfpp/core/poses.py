"""Camera pose refinement (``--refine-poses``): a learned SE(3) correction per training image.

Each training image ``i`` gets a 6-vector ``(ω_i, τ_i)`` in the model frame: an axis-angle
rotation ``ω`` and a translation ``τ``. Its camera becomes::

    R' = exp(ω)·R        (rotation about the camera centre)
    c' = c + τ

so each of its rays ``o + t·d`` (``o`` the camera centre) is rendered as ``(o + τ) + t·exp(ω)d``.
The corrections start at zero and are learned jointly with the fields, with their own small
learning rate, from the photometric loss: gradients reach the ray through the sample
positions ``p = o + t·d`` (the distances ``t`` along the ray are treated as constants, as
nerfstudio does; :func:`~mi_nerfpp.core.render.render_rays` with ``ray_gradients=True``).

Gauge: moving every camera and the scene together by a similarity changes no pixel. Training
image 0 is the reference: its pose is kept as given (its correction is never updated). One
image does not hold the scale, and holds the rotation and position only through its own
pixels, so the other cameras
drift together with the scene (their scale by 2-7 % in 3,000 steps, the more the larger the
learning rate): renders from cameras given in the capture's frame would then miss the scene.
So after every step the corrections of images 1.. are kept free of a common similarity
(:func:`gauge_basis`, :func:`pin_gauge`): the refined cameras are, in the least-squares sense, where
the given ones are, and each is only corrected against the others.

Only training rays are corrected. Held-out views keep their given poses: the training loss
never sees them (as nerfstudio evaluates).

The parameters are one ``(n_images, 6)`` tensor ``[ω_x, ω_y, ω_z, τ_x, τ_y, τ_z]``, stored in
the checkpoint as ``param/poses``.
"""
from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np

PARAMS = 6                  # axis-angle rotation and translation
LR_POSES = 1e-3             # Adam learning rate of the corrections (radians, model units)
# The largest learning rate of the corrections: an Adam step moves each by about the learning
# rate, and one radian or the unit sphere's radius per step already throws a camera out of its
# scene in a few steps (--lr-poses 1e10 moved the cameras so far that the process crashed).
MAX_LR_POSES = 1.0
# The largest correction a ray is rendered with: a shift of the camera centre (model units; the
# cameras lie in the unit sphere) and a turn (radians). A correction beyond them is applied at
# that length: farther, the samples' float32 placement breaks down (shifts of 1e10 crashed the
# process in the sample-placement loop, and turns of 1e20 gave NaN directions).
MAX_SHIFT = 10.0
MAX_TURN = math.pi
START = 0.02                # fraction of the run before the corrections are learned
# Coarse to fine while poses are refined (BARF's schedule, on the grid levels): each training
# ray's pixel footprint is widened to at least BLUR degrees at the start of the run, so that the
# fields' levels finer than that footprint are weighted out (:func:`~mi_nerfpp.core.fields.
# level_weight`) and a pose error of that size moves the rendered image smoothly; the floor falls
# geometrically, by FALL over the first SHARP of the run (below the pixels' own footprints long
# before), then goes. (Needs --antialias, on by default.)
BLUR = 2.0
SHARP = 0.4
FALL = 100.0


def blur(progress: float, degrees: float = BLUR, sharp: float = SHARP) -> float:
    """The least pixel footprint (radians per unit distance) of the training rays at
    ``progress`` (fraction of the run): ``degrees`` falling geometrically to 1/FALL of it at
    ``sharp``, then 0."""
    if degrees <= 0 or progress >= sharp:
        return 0.0
    return float(math.radians(degrees) * FALL ** (-progress / sharp))


def zeros(n_images: int) -> mi.TensorXf:
    """The parameters of ``n_images`` identity corrections."""
    if n_images < 1:
        raise ValueError(f'pose refinement needs at least one image, got {n_images}')
    return dr.zeros(mi.TensorXf, (n_images, PARAMS))


def rotate(omega: mi.Vector3f, v: mi.Vector3f) -> mi.Vector3f:
    """``exp(ω)·v`` by Rodrigues' formula, differentiable at ``ω = 0`` (Taylor series there)."""
    theta2 = dr.squared_norm(omega)
    theta = dr.sqrt(dr.maximum(theta2, 1e-12))
    small = theta2 < 1e-6
    a = dr.select(small, 1.0 - theta2 / 6.0, dr.sin(theta) / theta)
    b = dr.select(small, 0.5 - theta2 / 24.0, (1.0 - dr.cos(theta)) / dr.maximum(theta2, 1e-12))
    w_v = dr.cross(omega, v)
    return v + a * w_v + b * dr.cross(omega, w_v)


def gauge_basis(centres) -> np.ndarray:
    """An orthonormal basis (``6n x 7``, float64) of the corrections that move the cameras
    1.. (centres ``centres``, model frame, ``n x 3``) together by a small similarity: the
    three translations ``τ_i = t``, the three rotations about the origin ``(ω_i, τ_i) = (φ,
    φ x c_i)`` and the scaling ``τ_i = σ·c_i`` (first order; image 0 is not moved)."""
    c = np.asarray(centres, np.float64).reshape(-1, 3)
    if len(c) < 2:
        return np.zeros((PARAMS * len(c), 0))
    columns = []
    for e in np.eye(3):
        shift, turn = np.zeros((len(c), PARAMS)), np.zeros((len(c), PARAMS))
        shift[1:, 3:] = e
        turn[1:, :3], turn[1:, 3:] = e, np.cross(e, c[1:])
        columns += [shift.ravel(), turn.ravel()]
    scale = np.zeros((len(c), PARAMS))
    scale[1:, 3:] = c[1:]
    columns.append(scale.ravel())
    basis = np.stack(columns, axis=1)
    q, r = np.linalg.qr(basis)
    q[:PARAMS] = 0.0                    # image 0 is not moved (QR leaves round-off there)
    return q[:, np.abs(np.diag(r)) > 1e-9 * np.abs(r).max()]    # cameras on a line: fewer


def pin_gauge(params: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """The corrections ``params`` (``n x 6``) without their part along ``basis``
    (:func:`gauge_basis`): the common similarity of the cameras taken out."""
    x = np.asarray(params, np.float64).reshape(-1)
    return (x - basis @ (basis.T @ x)).reshape(-1, PARAMS)


def correct_rays(params: mi.TensorXf, image, o: mi.Point3f, d: mi.Vector3f):
    """Rays ``(o', d')`` of the corrected cameras: ray ``k`` of image ``image[k]`` (UInt32).
    Image 0 is the gauge: never corrected, so its parameters get no gradient."""
    image = mi.UInt32(image)
    active = image != 0
    omega = dr.gather(mi.Vector3f, params.array, 2 * image, active)        # row [ω, τ]
    tau = dr.gather(mi.Vector3f, params.array, 2 * image + 1, active)
    return o + _at_most(tau, MAX_SHIFT), rotate(_at_most(omega, MAX_TURN), d)


def _at_most(v: mi.Vector3f, length: float) -> mi.Vector3f:
    """``v`` shortened to ``length`` where it is longer (the factor is not differentiated:
    the gradient of a shortened correction is scaled with it); NaN stays NaN (the training
    step's guard stops the run)."""
    u = dr.detach(v)
    a = dr.abs(u)
    largest = dr.maximum(dr.maximum(a.x, a.y), a.z)
    norm = largest * dr.norm(u / dr.maximum(largest, 1e-30))   # no float32 overflow of |v|²
    return v * dr.select(norm > length, length / norm, 1.0)


def gradient_scope():
    """The context in which to render corrected rays and back-propagate: Dr.Jit 1.5 with
    constant propagation on loses part of the gradient of the ray origins when both volumes
    are rendered (τ_x came back exactly 0 in the finite-difference test); off, it is exact."""
    return dr.scoped_set_flag(dr.JitFlag.ConstantPropagation, False)


# ----------------------------------------------------------------------------- NumPy side

def rotation_matrix(omega) -> np.ndarray:
    """``exp(ω)`` as a 3x3 matrix (float64)."""
    omega = np.asarray(omega, np.float64)
    theta = np.linalg.norm(omega)
    if theta < 1e-12:
        return np.eye(3)
    k = omega / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def _np_at_most(v, length) -> np.ndarray:
    """``v`` shortened to ``length`` where it is longer (as :func:`correct_rays` renders it)."""
    v = np.asarray(v, np.float64)
    norm = np.linalg.norm(v)
    return v * (length / norm) if norm > length else v


def corrected_c2w(c2w, correction) -> np.ndarray:
    """A 4x4 camera-to-world matrix with the correction ``(ω, τ)`` applied (each at most
    :data:`MAX_TURN` and :data:`MAX_SHIFT` long, as training renders it)."""
    out = np.array(c2w, np.float64)
    out[:3, :3] = rotation_matrix(_np_at_most(correction[:3], MAX_TURN)) @ out[:3, :3]
    out[:3, 3] += _np_at_most(correction[3:6], MAX_SHIFT)
    return out


def refined_cameras(cameras, params) -> list:
    """The cameras (model frame) with their learned corrections applied."""
    p = np.asarray(params, np.float64).reshape(-1, PARAMS)
    if len(p) != len(cameras):
        raise ValueError(f'{len(p)} pose corrections for {len(cameras)} cameras')
    return [dataclasses.replace(cam, c2w=corrected_c2w(cam.c2w, q)) for cam, q in zip(cameras, p)]


def pose_errors(c2w, true_c2w) -> tuple[np.ndarray, np.ndarray]:
    """Per camera: rotation error in degrees and camera-centre distance (same units as the
    matrices) between two lists of 4x4 camera-to-world matrices."""
    rot, trans = [], []
    for a, b in zip(c2w, true_c2w):
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
        rot.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        trans.append(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    return np.array(rot), np.array(trans)


def world_poses(model, cameras) -> list:
    """The 4x4 camera-to-world matrices (world frame) of the training ``cameras`` (model
    frame, in training order) as ``model`` sees them: corrected when it refines poses."""
    if model.poses is not None:
        cameras = refined_cameras(cameras, model.poses.numpy())
    return [model.normalization.to_world_camera(cam).c2w for cam in cameras]
