"""The noise ceiling of a synthetic capture: its test views rendered again with other seeds.

    python benchmarks/noise_ceiling.py [DATA]

A capture's images are Monte Carlo renders (``synth --spp``), so no model can match them better
than a second render of the same view does. For every test view this renders the ground-truth
scene again at the capture's spp with another sampler seed and prints the PSNR between the two
(8-bit sRGB, as the capture's PNGs). Two independent renders differ by twice the noise of one,
so each capture image lies about 3 dB further from the converged image than that figure.
Without DATA, the embedded default capture is used. Results:
``benchmarks/results/noise_ceiling.json``.
"""
import argparse
import json
import os

import numpy as np

import mi_nerfpp  # noqa: F401
import mitsuba as mi
from mi_nerfpp.jobs import bench
from mi_nerfpp.jobs.bench import render_encoded
from mi_nerfpp.data import load_dataset
from mi_nerfpp.training.metrics import psnr
from mi_nerfpp.data.synth import default_capture


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
    bench.write_results('noise_ceiling', 'Noise ceiling of the capture', [
        bench.table(f'PSNR between two {spp}-spp renders of each test view',
                    ['test view', 'PSNR (dB)'],
                    [[i, p] for i, p in enumerate(scores)] + [['mean', np.mean(scores)]],
                    note='Each capture image lies about 3 dB further from the converged render '
                         'than these figures.')],
        notes=f'Capture {data}.')


if __name__ == '__main__':
    main()
