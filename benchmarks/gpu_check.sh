#!/usr/bin/env bash
# The GPU check of issue 51 in one command, on a GPU machine (under 8 minutes with the defaults):
#
#     bash benchmarks/gpu_check.sh [--no-install | --install-only] [--cpu-only] [options of gpu_check.py]
#
# 1. installs from the working tree: the wheels in .whl/ (scripts/pack_gpu_wheels.sh: Mitsuba
#    re-packed with its RGB variants, Dr.Jit, OpenEXR; pip --no-index, nothing fetched), then the
#    package itself (pip install --no-deps .; where that fails, the children use the working tree
#    through PYTHONPATH all the same), and checks that what the commands import is there;
# 2. runs benchmarks/gpu_check.py: the test subset on cuda_ad_rgb, the default capture trained
#    for --steps on both backends (PSNR at equal steps), gt_plaza 512x384 for 5 minutes on CUDA,
#    a 1280x720 frame at 1 spp, the packed-network probe; one JSON of the figures,
#    benchmarks/results/gpu_check.json (--json FILE elsewhere). Then run
#    `python scripts/benchmarks_page.py` to show it on docs/benchmarks.md.
#
# --cpu-only is the check's CPU half (llvm_ad_rgb alone, its JSON in the work folder; pass smaller
# sizes on a small machine, e.g. --steps 200 --plaza-res 128x96 --plaza-views 20 --plaza-spp 16
# --plaza-minutes 0.5 --render-res 640x360). PYTHON chooses the interpreter (default python3).
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
export PIP_ROOT_USER_ACTION=ignore PIP_DISABLE_PIP_VERSION_CHECK=1

install=1
check=1
args=()
for arg in "$@"; do
    case "$arg" in
        --no-install) install=0 ;;
        --install-only) check=0 ;;
        -h|--help) sed -n '2,19p' "$0"; exec "$PYTHON" benchmarks/gpu_check.py --help ;;
        *) args+=("$arg") ;;
    esac
done

start=$(date +%s)
if [ "$install" = 1 ]; then
    if [ -d .whl ]; then
        echo "gpu_check: installing $(ls .whl | tr '\n' ' ')"
        "$PYTHON" -m pip install --quiet --no-index --find-links .whl \
            mitsuba==3.9.1 drjit==1.5.0 OpenEXR==3.5.3
    fi
    if ! "$PYTHON" -m pip install --quiet --no-index --no-deps --no-build-isolation . ; then
        echo "gpu_check: the package did not install; its commands run from the working tree"
    fi
    echo "gpu_check: installed in $(( $(date +%s) - start )) s"
fi
missing=$("$PYTHON" - <<'EOF'
import importlib.util
need = ['mitsuba', 'drjit', 'OpenEXR', 'numpy', 'imageio', 'skimage', 'scipy', 'tqdm',
        'matplotlib', 'pytest']
print(' '.join(n for n in need if importlib.util.find_spec(n) is None))
EOF
)
if [ -n "$missing" ]; then
    echo "error: gpu_check: $PYTHON lacks $missing (bring them as wheels in .whl/:" \
         "scripts/pack_gpu_wheels.sh)" >&2
    exit 1
fi
if [ "$check" = 0 ]; then
    exit 0
fi
"$PYTHON" benchmarks/gpu_check.py ${args[@]+"${args[@]}"}
echo "gpu_check: all in $(( $(date +%s) - start )) s"
