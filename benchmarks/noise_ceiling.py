"""The noise ceiling of a synthetic capture: its test views rendered again with other seeds.

    python benchmarks/noise_ceiling.py [DATA]

A capture's images are Monte Carlo renders (``synth --spp``), so no model can match them better
than a second render of the same view does. For every test view this renders the ground-truth
scene again at the capture's spp with another sampler seed and prints the PSNR between the two
(8-bit sRGB, as the capture's PNGs). Two independent renders differ by twice the noise of one,
so each capture image lies about 3 dB further from the converged image than that figure.
Without DATA, the embedded default capture is used.
"""
import argparse
import json
import os

import numpy as np

import mi_nerfpp  # noqa: F401
import mitsuba as mi
from mi_nerfpp.data import load_dataset, mitsuba_sensor_dict
from mi_nerfpp.frame import MITSUBA_NEAR_CLIP
from mi_nerfpp.metrics import psnr
from mi_nerfpp.color import to_srgb8
from mi_nerfpp.synth import default_capture


def render_encoded(scene, world_camera, spp, seed):
    """The ground-truth scene seen by ``world_camera`` at ``spp``, in the capture's 8-bit sRGB
    encoding (as floats in [0, 1]), with the sensor ``synth`` renders through."""
    desc = mitsuba_sensor_dict(world_camera, spp=spp, pixel_format='rgb')
    desc['near_clip'] = MITSUBA_NEAR_CLIP
    image = np.array(mi.render(scene, sensor=mi.load_dict(desc), spp=spp, seed=seed))
    return to_srgb8(image[..., :3]).astype(np.float64) / 255.0


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('data', nargs='?')
    a = ap.parse_args()
    data = a.data or default_capture()
    with open(os.path.join(data, 'capture.json')) as f:
        capture = json.load(f)
    dataset = load_dataset(data)
    scene = mi.load_file(capture['scene_path'])
    spp = int(capture['spp'])
    scores = []
    for i, camera in enumerate(dataset.test.cameras):
        again = render_encoded(scene, dataset.normalization.to_world_camera(camera), spp,
                               7919 + i)
        scores.append(psnr(again, dataset.test.images[i]))
        print(f'test view {i}: {scores[-1]:.2f} dB between two {spp}-spp renders')
    print(f'mean {np.mean(scores):.2f} dB: each capture image is ~{np.mean(scores) + 3:.1f} dB '
          f'from the converged render')


if __name__ == '__main__':
    main()
