"""Generate the bitmap textures of the ground-truth scenes (run from anywhere; deterministic).

    python scenes/textures/make_textures.py

paving.png (256 x 256, sRGB): 4 x 4 stone slabs in a running-bond layout (alternate rows offset by
half a slab), each slab with its own tint, fine grain noise, and dark mortar joints. The plaza
scene (gt_plaza.xml) tiles it over the ground with `to_uv`; one tile covers 4 x 4 world units.
Only numpy and imageio are used, with a fixed seed, so the file is reproducible.
"""
import os

import imageio.v3 as iio
import numpy as np

SIZE = 256
SLABS = 4
JOINT = 3          # mortar width in texels


def paving(seed: int = 7) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:SIZE, 0:SIZE]
    slab = SIZE // SLABS
    row = y // slab
    xs = (x + (row % 2) * slab // 2) % SIZE           # running bond: odd rows shifted by half
    col = xs // slab
    tint = rng.uniform(0.85, 1.15, size=(SLABS, SLABS))
    hue = rng.uniform(-0.04, 0.04, size=(SLABS, SLABS))
    base = np.array([0.62, 0.55, 0.46])              # warm sandstone (sRGB)
    img = base[None, None, :] * tint[row, col][..., None]
    img[..., 0] += hue[row, col]
    img[..., 2] -= hue[row, col]
    # grain: band-limited noise (white noise filtered in the Fourier domain, so it wraps and the
    # tile is seamless), coarse blotches plus finer speckle
    f = np.fft.fftfreq(SIZE)
    radius = np.hypot(*np.meshgrid(f, f))
    grain = np.zeros((SIZE, SIZE))
    for cutoff, amp in ((0.02, 0.06), (0.12, 0.03)):
        spectrum = np.fft.fft2(rng.normal(size=(SIZE, SIZE))) * np.exp(-(radius / cutoff) ** 2)
        g = np.real(np.fft.ifft2(spectrum))
        grain += amp * g / g.std()
    img += grain[..., None]
    joint = ((y % slab) < JOINT) | ((xs % slab) < JOINT)
    img[joint] = np.array([0.24, 0.22, 0.2])
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


if __name__ == '__main__':
    here = os.path.dirname(os.path.abspath(__file__))
    iio.imwrite(os.path.join(here, 'paving.png'), paving())
    print('wrote', os.path.join(here, 'paving.png'))
