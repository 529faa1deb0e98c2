#!/usr/bin/env bash
# Idempotent set-up of what the main job needs: libLLVM >= 17 (Dr.Jit's CPU backend), a virtual
# environment in .venv, and this package installed in it (editable) with its dependencies from
# pyproject.toml (among them pycolmap and PyAV, for photos and videos in: wheels that bring COLMAP
# and FFmpeg). `scripts/setup.sh --test` adds what the tests use: oiiotool (the compositing tests
# composite the EXR layers with it), Blender (the export test builds its camera from the USD
# headless), Blender 4.2 as a Python module in .venv-bpy (its USD importer, which Debian's Blender
# lacks, reads the export), Chromium and its driver (the viewer tests open the page headless) and
# the package's test, cluster, export and viewer extras (the Ray, usd-core, xatlas and viser tests
# run).
set -euo pipefail
cd "$(dirname "$0")/.."
tests=0
[ "${1:-}" = "--test" ] && tests=1

# apt_install "PACKAGE..." WHY: install Debian packages quietly (sudo when not root); 1 without apt-get.
apt_install() {
    command -v apt-get >/dev/null 2>&1 || return 1
    local sudo=""; [ "$(id -u)" -ne 0 ] && sudo="sudo"
    echo "setup: installing $1 ($2)"
    $sudo apt-get update -qq || exit 1
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq $1 >/dev/null || exit 1  # word-split: several packages
}

have_llvm() {
    python3 -c "import sys; sys.path.insert(0, 'mi_nerfpp'); import _llvm; sys.exit(0 if _llvm.find_libllvm() else 1)"
}

if [ -z "${DRJIT_LIBLLVM_PATH:-}" ] && ! have_llvm; then
    if ! apt_install libllvm19 "Dr.Jit needs libLLVM >= 17"; then
        echo "setup: no libLLVM >= 17 found and no apt-get: install LLVM >= 17 and set DRJIT_LIBLLVM_PATH" >&2
        exit 1
    fi
fi

if [ "$tests" = 1 ]; then
    # oiiotool (OpenImageIO): the tests composite the EXR layers with it, as a real client.
    if ! command -v oiiotool >/dev/null 2>&1; then
        if ! apt_install openimageio-tools "oiiotool, used by the compositing tests"; then
            echo "setup: oiiotool not found and no apt-get: install OpenImageIO's oiiotool, or set" \
                 "MI_NERFPP_NO_OIIOTOOL=1 to skip the compositing checks that use it" >&2
        fi
    fi
    # Blender (Debian's 3.4, ~50 s to install): the export test checks the USD camera in it.
    if ! command -v blender >/dev/null 2>&1; then
        if ! apt_install blender "used headless by the export test"; then
            echo "setup: blender not found and no apt-get: install Blender, or set" \
                 "MI_NERFPP_NO_BLENDER=1 to skip the Blender camera check" >&2
        fi
    fi
    # Chromium and chromedriver (Debian's, same version): the viewer tests drive the page with them.
    if ! command -v chromium >/dev/null 2>&1 || ! command -v chromedriver >/dev/null 2>&1; then
        if ! apt_install "chromium chromium-driver" "headless browser of the viewer tests"; then
            echo "setup: chromium not found and no apt-get: install Chromium and chromedriver, or" \
                 "set MI_NERFPP_NO_BROWSER=1 to skip the viewer's browser tests" >&2
        fi
    fi
fi

if [ ! -x .venv/bin/python ]; then
    python3 -m venv .venv
fi
extras=""
[ "$tests" = 1 ] && extras="[test,cluster,export,viewer]"
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".${extras}"

# Blender 4.2 as a Python module (pip bpy, Python 3.11 only) in its own environment: its USD
# importer reads the export in the tests.
if [ "$tests" = 1 ] && [ ! -x .venv-bpy/bin/python ]; then
    if python3 -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else 1)'; then
        echo "setup: installing bpy 4.2 into .venv-bpy (Blender's USD importer, for the tests)"
        python3 -m venv .venv-bpy
        .venv-bpy/bin/python -m pip install -q --disable-pip-version-check 'bpy==4.2.23' \
            || { rm -rf .venv-bpy; echo "setup: could not install bpy 4.2" >&2; exit 1; }
    else
        echo "setup: bpy 4.2 needs Python 3.11: the Blender USD import test will fail" >&2
    fi
fi
