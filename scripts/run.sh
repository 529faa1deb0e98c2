#!/usr/bin/env bash
# The main job on the embedded default: render scenes/render_random.xml (a seeded random
# NeRF++ model) to a multi-layer EXR and a PNG preview in out/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
mkdir -p out
.venv/bin/python -m mi_nerfpp render scenes/render_random.xml -o out/render.exr --preview out/render.png "$@"
