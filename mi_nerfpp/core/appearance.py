"""Per-image appearance: an affine colour transform per training image (exposure, white balance).

Photos of one capture differ in exposure and white balance. With ``--appearance`` each training
image ``i`` gets a transform of the rendered *linear* colour ``c``::

    c' = exp(g_i) ⊙ c + b_i        (per channel: gain exp(g_i), bias b_i)

learned jointly with the fields (its own learning rate) under an L2 prior pulling
``(g_i, b_i)`` to 0, the identity (as the original NeRF++'s auto-exposure option). The loss
compares ``c'`` (sRGB-encoded for photos) with the pixels.

Gauge: scaling the model's radiance and dividing every gain by the same factor (or adding a
colour to it and subtracting it from every bias) changes no pixel, so the transforms' common
part must be fixed. It is their mean: after every step the mean over the training images of
each parameter is taken out (:func:`center`), so the log-gains and biases average to zero and
the model's own (neutral) colour is that of the capture's *average* exposure and white balance,
and a learned gain ``exp(g_i)`` estimates image ``i``'s exposure relative to that average. (It
was training image 0's until 2026-11-29: renders then took the one photo's exposure, a colour
shift wherever that photo was darker or warmer than the rest. A checkpoint of that time keeps
its neutral colour; training it further moves it to the average.)

The parameters are one ``(n_images, 6)`` tensor ``[g_r, g_g, g_b, b_r, b_g, b_b]``, stored in
the checkpoint as ``param/appearance``. Rendering is neutral unless the integrator is asked for
a training image's transform (``appearance_image``).

``--appearance-embedding DIMS`` learns, beside or instead of the transform, a code of ``DIMS``
numbers per training image (NeRF-W's appearance embedding) that both colour networks take with
the view direction (:attr:`mi_nerfpp.core.fields.GridField.appearance_code`): what an affine
transform cannot express - a different sky, haze over the distance - is explained per photo
instead of averaged into the volumes. The codes start at zero and an L2 prior keeps them near
it, so the zero code is a photo of typical appearance: renders use it unless asked for a
training image's (``appearance_image``). They are stored as ``param/embedding``, (n, DIMS).

Held-out photos have their own exposure, unknown to the model: :func:`fit_affine` fits it as
NeRF-W evaluates (the transform of a test image is fitted on its left half - closed-form linear
least squares in linear light - and the right half is scored).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

PARAMS = 6                  # log-gain and bias per channel
LR_APPEARANCE = 0.02        # Adam learning rate of the transforms (and of the embeddings)
PRIOR = 1e-3                # weight of the L2 prior towards the identity (and towards zero)


def identity(n_images: int) -> mi.TensorXf:
    """The parameters of ``n_images`` identity transforms."""
    if n_images < 1:
        raise ValueError(f'appearance needs at least one image, got {n_images}')
    return dr.zeros(mi.TensorXf, (n_images, PARAMS))


def transform_rays(params: mi.TensorXf, image, rgb: mi.Color3f) -> mi.Color3f:
    """Apply the transform of image ``image[k]`` (UInt32 per ray) to ray ``k``'s linear colour."""
    image = mi.UInt32(image)
    p = [dr.gather(mi.Float, params.array, image * PARAMS + j) for j in range(PARAMS)]
    gain = dr.exp(mi.Color3f(p[0], p[1], p[2]))
    return gain * rgb + mi.Color3f(p[3], p[4], p[5])


def center(params) -> np.ndarray:
    """The parameters (n, :data:`PARAMS`) with their mean over the images taken out: the
    gauge (module docs)."""
    p = np.asarray(params, dtype=np.float64).reshape(-1, PARAMS)
    return p - p.mean(axis=0, keepdims=True)


def prior(params: mi.TensorXf) -> mi.Float:
    """L2 of the parameters (0 at the identity), averaged over images and entries."""
    return dr.mean(dr.square(params.array))


def gains_biases(params) -> tuple[np.ndarray, np.ndarray]:
    """``(gains (n, 3), biases (n, 3))`` as NumPy arrays."""
    p = np.asarray(params, dtype=np.float64).reshape(-1, PARAMS)
    return np.exp(p[:, :3]), p[:, 3:]


def single(params, index: int) -> tuple[np.ndarray, np.ndarray]:
    """``(gain, bias)`` of one image (3-vectors)."""
    gains, biases = gains_biases(params)
    return gains[index], biases[index]


# ----------------------------------------------------------------------------- embeddings

def zero_embeddings(n_images: int, dims: int) -> mi.TensorXf:
    """The appearance embeddings of ``n_images`` images, ``dims`` each, at the neutral code."""
    if n_images < 1 or dims < 1:
        raise ValueError(f'appearance embeddings need images and dimensions, got {n_images} '
                         f'images of {dims}')
    return dr.zeros(mi.TensorXf, (n_images, dims))


def codes(embeddings: mi.TensorXf, image) -> list:
    """The embedding of image ``image[k]`` (UInt32 per ray) for each ray: ``dims`` Floats."""
    dims = embeddings.shape[1]
    image = mi.UInt32(image)
    return [dr.gather(mi.Float, embeddings.array, image * dims + j) for j in range(dims)]


def image_code(embeddings, index: int) -> list:
    """One training image's embedding as ``dims`` Python floats (a render's code)."""
    return [float(v) for v in np.asarray(embeddings, dtype=np.float64)[index]]


# ----------------------------------------------------------------------------- evaluation

def fit_affine(pred: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel ``(gain, bias)`` minimizing ``|gain·pred + bias - target|²`` over the pixels
    ((..., 3) arrays, linear light): closed-form linear least squares."""
    x = pred.reshape(-1, 3).astype(np.float64)
    y = target.reshape(-1, 3).astype(np.float64)
    gain, bias = np.ones(3), np.zeros(3)
    for c in range(3):
        a = np.stack([x[:, c], np.ones(len(x))], axis=1)
        (g, b), *_ = np.linalg.lstsq(a, y[:, c], rcond=None)
        if np.isfinite(g) and np.isfinite(b):
            gain[c], bias[c] = g, b
    return gain, bias


def left_right(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The left and right halves of an (H, W, ...) image (the right one gets the odd column)."""
    half = image.shape[1] // 2
    return image[:, :half], image[:, half:]
