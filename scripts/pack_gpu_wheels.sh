#!/usr/bin/env bash
# The wheels a GPU machine without a package index needs to run mi-nerfpp, in one folder:
#
#     bash scripts/pack_gpu_wheels.sh [--python-version 3.12] [--out .whl]
#
# Downloads (here, where PyPI is reachable) mitsuba 3.9.1, drjit 1.5.0 and OpenEXR for CPython
# <version> on manylinux x86_64, and re-packs Mitsuba's wheel with only the variants mi-nerfpp
# runs (scalar_rgb, llvm_ad_rgb, cuda_ad_rgb): the spectral, mono and polarized modules, the C++
# headers and build files (include/, cmake/, pkgconfig/) and data/srgb.coeff (the spectral
# variants' RGB upsampling table; the RGB variants never read it) are left out, config.py lists
# the variants kept, and RECORD is rewritten (hashes and sizes of what is left). The other
# dependencies (numpy, imageio, scikit-image, scipy, tqdm, matplotlib, pytest) are on the GPU
# image already; pycolmap (the `colmap` command) and imageio-ffmpeg (videos) are not needed by
# the check. benchmarks/gpu_check.sh installs from the folder with pip --no-index. The folder is
# ignored by git; the device tool carries it when named (carry: [".whl"]), within its 64 MiB.
set -euo pipefail
cd "$(dirname "$0")/.."

PYVER=3.12
OUT=.whl
PYTHON=${PYTHON:-}
while [ $# -gt 0 ]; do
    case "$1" in
        --python-version) PYVER=$2; shift 2 ;;
        --out) OUT=$2; shift 2 ;;
        -h|--help) sed -n '2,16p' "$0"; exit 0 ;;
        *) echo "error: pack_gpu_wheels: unknown argument $1" >&2; exit 2 ;;
    esac
done
if [ -z "$PYTHON" ]; then
    if [ -x .venv/bin/python ]; then PYTHON=.venv/bin/python; else PYTHON=python3; fi
fi
TAG=cp${PYVER/./}
mkdir -p "$OUT"
rm -f "$OUT"/mitsuba-*.whl "$OUT"/drjit-*.whl "$OUT"/openexr-*.whl "$OUT"/OpenEXR-*.whl
RAW=$(mktemp -d)
trap 'rm -rf "$RAW"' EXIT
"$PYTHON" -m pip download --quiet --no-deps --only-binary=:all: --python-version "$PYVER" \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d "$RAW" mitsuba==3.9.1 drjit==1.5.0 'OpenEXR==3.5.3'
cp "$RAW"/drjit-*.whl "$RAW"/openexr-*.whl "$OUT"/
"$PYTHON" - "$RAW"/mitsuba-3.9.1-"$TAG"-*.whl "$OUT" <<'EOF'
"""Re-pack Mitsuba's wheel with the RGB variants only (see pack_gpu_wheels.sh)."""
import base64
import hashlib
import os
import re
import sys
import zipfile

source, out = sys.argv[1], sys.argv[2]
KEEP = ['scalar_rgb', 'llvm_ad_rgb', 'cuda_ad_rgb']
DROP = re.compile(r'^mitsuba/(?:'
                  r'(?:scalar|llvm_ad|cuda_ad)_(?:mono|spectral)[^/]*$'
                  r'|include/|cmake/|pkgconfig/|data/srgb\.coeff$)')


def record_line(name, data):
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b'=').decode()
    return f'{name},sha256={digest},{len(data)}'


target = os.path.join(out, os.path.basename(source))
kept, dropped, record, record_name = 0, 0, [], None
with zipfile.ZipFile(source) as src, zipfile.ZipFile(target, 'w', zipfile.ZIP_DEFLATED,
                                                     compresslevel=9) as dst:
    for info in src.infolist():
        name = info.filename
        if name.endswith('.dist-info/RECORD'):
            record_name = name
            continue
        if DROP.match(name):
            dropped += info.file_size
            continue
        data = src.read(info)
        if name == 'mitsuba/config.py':
            text = data.decode()
            text, n = re.subn(r'MI_VARIANTS = \[[^\]]*\]', f'MI_VARIANTS = {KEEP!r}', text)
            assert n == 1, 'MI_VARIANTS not found in mitsuba/config.py'
            data = text.encode()
        copy = zipfile.ZipInfo(name, info.date_time)
        copy.external_attr = info.external_attr
        copy.compress_type = zipfile.ZIP_DEFLATED
        dst.writestr(copy, data, compresslevel=9)
        record.append(record_line(name, data))
        kept += len(data)
    assert record_name, 'no RECORD in the wheel'
    record.append(f'{record_name},,')
    dst.writestr(zipfile.ZipInfo(record_name, (2026, 1, 1, 0, 0, 0)),
                 '\n'.join(record) + '\n')
print(f'{target}: {os.path.getsize(target) / 1e6:.1f} MB (from {os.path.getsize(source) / 1e6:.1f} '
      f'MB; {dropped / 1e6:.1f} MB uncompressed left out, {kept / 1e6:.1f} MB kept)')
EOF
ls -l "$OUT"
du -sh "$OUT"
