"""Find a libLLVM that Dr.Jit's LLVM (CPU) backend can use.

Dr.Jit 1.5 needs libLLVM >= 17: versions 15 and 16 abort inside LLVM's
instruction selection ("Cannot select ... fminimum") and 14 is refused. When
``DRJIT_LIBLLVM_PATH`` is unset, Dr.Jit takes the first ``libLLVM*.so.*`` it
finds, which on Debian 12 is an old one. So before Dr.Jit is imported we look
for the newest usable library ourselves and point the variable at it.

This module must not import drjit or mitsuba.
"""
from __future__ import annotations

import glob
import os
import re

MIN_VERSION = 17
ENV = 'DRJIT_LIBLLVM_PATH'

SEARCH_PATTERNS = [
    '/usr/lib/x86_64-linux-gnu/libLLVM*.so*',
    '/usr/lib/aarch64-linux-gnu/libLLVM*.so*',
    '/usr/lib/llvm-*/lib/libLLVM*.so*',
    '/usr/lib64/libLLVM*.so*',
    '/usr/lib64/llvm*/lib/libLLVM*.so*',
    '/usr/local/lib/libLLVM*.so*',
    '/usr/local/opt/llvm/lib/libLLVM*.dylib',
    '/opt/homebrew/opt/llvm/lib/libLLVM*.dylib',
]

INSTALL_HINT = (
    "Dr.Jit's CPU backend needs libLLVM >= {min} (15 and 16 crash, 14 is refused). "
    "On Debian/Ubuntu: `apt-get install -y libllvm19`; elsewhere install LLVM >= {min} "
    "and set DRJIT_LIBLLVM_PATH to its libLLVM shared library."
).format(min=MIN_VERSION)


class LLVMNotFoundError(ImportError):
    """No libLLVM >= 17 could be found for Dr.Jit's LLVM backend."""


def llvm_version(path: str) -> int | None:
    """Major LLVM version encoded in a library path, or None if it cannot be told.

    Handles ``libLLVM.so.19.1``, ``libLLVM-19.so.1``, ``libLLVM-17.so``,
    ``libLLVM.19.dylib`` and ``/usr/lib/llvm-19/lib/libLLVM.so.1``.
    """
    name = os.path.basename(path)
    m = re.match(r'^libLLVM-(\d+)', name)
    if m:
        return int(m.group(1))
    # /usr/lib/llvm-19/lib/libLLVM.so.1: the ".1" is an ABI number, the folder has the version.
    m = re.search(r'llvm-?(\d+)', os.path.dirname(path))
    if m:
        return int(m.group(1))
    m = re.match(r'^libLLVM\.so\.(\d+)', name) or re.match(r'^libLLVM\.(\d+)\.dylib', name)
    if m:
        return int(m.group(1))
    return None


def candidates(patterns=SEARCH_PATTERNS) -> list[tuple[int, str]]:
    """All (version, path) pairs found on this machine, newest first."""
    found = {}
    for pattern in patterns:
        for path in glob.glob(pattern):
            if not os.path.isfile(path):
                continue
            version = llvm_version(path)
            if version is not None:
                found[os.path.realpath(path)] = (version, path)
    return sorted(found.values(), key=lambda vp: (-vp[0], len(vp[1])))


def find_libllvm(patterns=SEARCH_PATTERNS) -> str | None:
    """Path of the newest libLLVM with version >= MIN_VERSION, or None."""
    for version, path in candidates(patterns):
        if version >= MIN_VERSION:
            return path
    return None


def configure(environ=os.environ, patterns=SEARCH_PATTERNS) -> str:
    """Make sure ``DRJIT_LIBLLVM_PATH`` names a usable libLLVM and return it.

    A path the user set is respected, but one whose version is known to be too
    old is an error. Raises :class:`LLVMNotFoundError` naming what to install.
    """
    path = environ.get(ENV)
    if path:
        if not os.path.exists(path):
            raise LLVMNotFoundError(f'{ENV}={path!r} does not exist. {INSTALL_HINT}')
        version = llvm_version(path)
        if version is not None and version < MIN_VERSION:
            raise LLVMNotFoundError(
                f'{ENV}={path!r} is LLVM {version}. {INSTALL_HINT}')
        return path
    path = find_libllvm(patterns)
    if path is None:
        seen = ', '.join(f'{p} ({v})' for v, p in candidates(patterns)) or 'none'
        raise LLVMNotFoundError(f'No libLLVM >= {MIN_VERSION} found (seen: {seen}). {INSTALL_HINT}')
    environ[ENV] = path
    return path

