#!/usr/bin/env bash
# The main job on the embedded default: synthesize (once, cached in ~/.cache/mi-nerfpp/default) a
# 60-view capture of scenes/gt_garden.xml and fit a NeRF++ to it for about ten minutes.
# Results (metrics, EXRs, previews, plot, render.xml) land in runs/default/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh         # libLLVM, .venv and the package: what the job needs, no test tools
.venv/bin/python optimize.py --out runs/default "$@"
