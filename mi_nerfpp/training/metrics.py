"""Image quality metrics for ``H x W x C`` float images: MSE, PSNR and SSIM.

This module must not import drjit or mitsuba.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter, median_filter
from skimage.metrics import structural_similarity

SSIM_WIN_SIZE = 7
SSIM_MIN_WIN_SIZE = 3


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error on [0, 1] values (``inf`` for 0)."""
    return -10.0 * math.log10(mse) if mse > 0 else float('inf')

def _check_pair(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f'image shapes differ: pred {pred.shape} vs gt {gt.shape}')
    if pred.ndim != 3:
        raise ValueError(f'expected H x W x C images, got shape {pred.shape}')
    return pred, gt


def mse(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean squared error over all pixels and channels."""
    pred, gt = _check_pair(pred, gt)
    return float(np.mean((pred - gt) ** 2))


def psnr(pred: np.ndarray, gt: np.ndarray, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB (``inf`` for identical images)."""
    error = mse(pred, gt)
    if error == 0.0:
        return float('inf')
    return float(10.0 * np.log10(data_range ** 2 / error))


def masked_psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray, data_range: float = 1.0) -> float:
    """PSNR over the pixels where the ``H x W`` boolean ``mask`` is set (NaN where none is)."""
    pred, gt = _check_pair(pred, gt)
    mask = np.asarray(mask, bool)
    if mask.shape != pred.shape[:2]:
        raise ValueError(f'mask shape {mask.shape} does not match the images {pred.shape[:2]}')
    if not mask.any():
        return float('nan')
    return psnr(pred[mask][None], gt[mask][None], data_range)


def _ssim_win_size(height: int, width: int) -> int:
    """The largest odd window, at most 7, that fits in the image."""
    side = min(height, width, SSIM_WIN_SIZE)
    win_size = side if side % 2 else side - 1
    if win_size < SSIM_MIN_WIN_SIZE:
        raise ValueError(
            f'SSIM needs images of at least {SSIM_MIN_WIN_SIZE} x {SSIM_MIN_WIN_SIZE} pixels, '
            f'got {height} x {width}')
    return win_size


def ssim(pred: np.ndarray, gt: np.ndarray, data_range: float = 1.0) -> float:
    """Structural similarity (mean over the image and its channels)."""
    pred, gt = _check_pair(pred, gt)
    win_size = _ssim_win_size(*pred.shape[:2])
    return float(structural_similarity(
        pred, gt, win_size=win_size, channel_axis=-1, data_range=data_range))


# A foreground opacity strictly inside this band is "soft": neither in the matte nor out of it.
SOFT_ALPHA = (0.05, 0.95)
# Held-out soft-alpha fraction above which a run's foreground matte is reported as soft (issue
# 9's target for a clean matte: at most 15 % of the pixels). Measured on the default capture
# after 10 minutes: 3.4 % where the foreground owns the lawn (seed 0), 25.5 % where the
# background paints it behind a half-transparent foreground (seed 2).
SOFT_ALPHA_WARNING = 0.15


def soft_alpha_fraction(alpha: np.ndarray, soft: tuple[float, float] = SOFT_ALPHA) -> float:
    """Fraction of pixels whose foreground opacity lies strictly between ``soft[0]`` and
    ``soft[1]``: half-transparent foreground, which a compositor lays over a new plate as a
    veil. Object edges and motion blur are legitimately soft; a few percent of the pixels."""
    alpha = np.asarray(alpha, np.float64)
    return float(np.mean((alpha > soft[0]) & (alpha < soft[1])))


# A dark speckle: a pixel whose encoded luminance lies this far below the median of its 3x3
# neighbourhood (set on the realistic stand-in's ground truth, where 0.2-0.4 % of the foreground's
# pixels are that dark: edges of thin dark lines and of shadows).
SPECKLE_DEPTH = 0.1


def dark_speckle_share(image: np.ndarray, mask: np.ndarray | None = None,
                       depth: float = SPECKLE_DEPTH) -> float:
    """Share of the pixels (of ``mask``, where given) of the encoded RGB ``image`` (H, W, 3) whose
    luminance is more than ``depth`` below the median of their 3x3 neighbourhood: the dark
    isolated samples (floaters) a render can have over a surface; NaN where ``mask`` is empty.
    Thin dark lines and the convex corners of dark regions count too, so a render's share is
    read against its ground truth's."""
    luminance = np.asarray(image, np.float64)[..., :3] @ np.array([0.2126, 0.7152, 0.0722])
    dark = median_filter(luminance, size=3, mode='nearest') - luminance > depth
    if mask is None:
        return float(dark.mean())
    mask = np.asarray(mask, bool)
    return float(dark[mask].mean()) if mask.any() else float('nan')


def separation(alpha: np.ndarray, alpha_gt: np.ndarray, depth: np.ndarray | None = None,
               depth_gt: np.ndarray | None = None, soft: tuple[float, float] = SOFT_ALPHA) -> dict:
    """How cleanly a render splits foreground from background, against ground truth.

    ``alpha``: the foreground opacity (``fg.A``); ``alpha_gt``: the true mask (1 where the
    visible surface lies in the foreground sphere, as ``synth`` writes it). Returns
    ``alpha_error`` (mean absolute difference), ``leak`` (mean opacity where the mask is 0:
    the veil a compositor would lay over a new plate), ``soft_fraction`` (pixels with
    ``soft[0] < alpha < soft[1]``) and, given depths, ``depth_error`` (median relative
    error where the mask is 1). A quantity with no pixels to average is NaN.
    """
    alpha, alpha_gt = np.asarray(alpha, np.float64), np.asarray(alpha_gt, np.float64)
    if alpha.shape != alpha_gt.shape:
        raise ValueError(f'alpha shapes differ: {alpha.shape} vs {alpha_gt.shape}')
    empty, full = alpha_gt == 0, alpha_gt == 1
    out = {'alpha_error': float(np.mean(np.abs(alpha - alpha_gt))),
           'leak': float(np.mean(alpha[empty])) if empty.any() else float('nan'),
           'soft_fraction': soft_alpha_fraction(alpha, soft)}
    if depth is not None and depth_gt is not None:
        valid = full & (np.asarray(depth_gt) > 0)
        rel = np.abs(np.asarray(depth, np.float64) - depth_gt) / np.where(valid, depth_gt, 1.0)
        out['depth_error'] = float(np.median(rel[valid])) if valid.any() else float('nan')
    return out


# Search range, in pixels, of :func:`equivalent_blur`.
MAX_BLUR = 8.0


def equivalent_blur(pred: np.ndarray, reference: np.ndarray) -> float:
    """How blurred ``pred`` is, in pixels: the standard deviation of the Gaussian blur of
    ``reference`` whose PSNR against ``reference`` equals that of ``pred``. 0 for a perfect
    ``pred``; ``inf`` when even a blur of :data:`MAX_BLUR` pixels scores better (errors
    other than blur dominate). A single number for "renders are blurred", against a
    noise-free reference."""
    pred, reference = _check_pair(pred, reference)
    target = psnr(pred, reference)

    def score(sigma):
        return psnr(gaussian_filter(reference, (sigma, sigma, 0)), reference)
    if target == float('inf'):
        return 0.0
    if score(MAX_BLUR) > target:
        return float('inf')
    lo, hi = 0.0, MAX_BLUR
    for _ in range(30):          # the PSNR of a blur falls as it widens: bisect
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if score(mid) > target else (lo, mid)
    return 0.5 * (lo + hi)


# The scale (pixels, Gaussian sigma) that separates an error's low frequencies (what blur or a
# wrong colour leaves: it survives blurring) from its high frequencies (missing detail, noise).
SPLIT_SIGMA = 2.0


def error_split(pred: np.ndarray, gt: np.ndarray, regions: dict[str, np.ndarray],
                noise_mse: float = 0.0, sigma: float = SPLIT_SIGMA) -> dict[str, dict]:
    """Where an image's error is: per region and by frequency.

    ``regions``: ``{name: H x W boolean mask}`` (they may overlap; ``'all'`` is added). The error
    ``e = pred - gt`` splits into its low frequencies ``e_low = G_sigma * e`` (Gaussian blur per
    channel) and the residual ``e_high = e - e_low``. Per region: ``pixels`` (share of the
    image), ``mse``, ``low`` and ``high`` (mean squared ``e_low`` and ``e_high`` there; the two
    add up to ``mse`` up to their cross term, which is small where the split is clean),
    ``share`` (of the image's summed squared error), ``psnr``, and ``excess``: ``mse`` less
    ``noise_mse``, the error the test image's own noise leaves (its MSE against the converged
    image: half the MSE between two independent renders of the ground truth,
    ``benchmarks/noise_ceiling.py``), never below 0, with its PSNR ``excess_psnr``."""
    pred, gt = _check_pair(pred, gt)
    error = pred - gt
    low = np.stack([gaussian_filter(error[..., c], sigma, mode='reflect')
                    for c in range(error.shape[-1])], axis=-1)
    high = error - low
    squared = np.mean(error ** 2, axis=-1)
    total = float(squared.sum())
    regions = dict(regions, all=np.ones(pred.shape[:2], bool))
    out = {}
    for name, mask in regions.items():
        mask = np.asarray(mask, bool)
        if mask.shape != pred.shape[:2]:
            raise ValueError(f'region {name!r}: mask shape {mask.shape} does not match the '
                             f'images {pred.shape[:2]}')
        if not mask.any():
            out[name] = {'pixels': 0.0, 'mse': float('nan'), 'low': float('nan'),
                         'high': float('nan'), 'share': 0.0, 'psnr': float('nan'),
                         'excess': float('nan'), 'excess_psnr': float('nan')}
            continue
        m = float(squared[mask].mean())
        excess = max(m - noise_mse, 0.0)
        out[name] = {
            'pixels': float(mask.mean()), 'mse': m,
            'low': float(np.mean(low[mask] ** 2)), 'high': float(np.mean(high[mask] ** 2)),
            'share': float(squared[mask].sum() / total) if total > 0 else 0.0,
            'psnr': float(10 * np.log10(1.0 / m)) if m > 0 else float('inf'),
            'excess': excess,
            'excess_psnr': float(10 * np.log10(1.0 / excess)) if excess > 0 else float('inf')}
    return out
