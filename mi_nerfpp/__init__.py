"""mi-nerfpp: NeRF++ (Zhang, Riegler, Snavely, Koltun 2020) as a Mitsuba 3 integrator.

Importing the package

1. points Dr.Jit at a libLLVM >= 17 when ``DRJIT_LIBLLVM_PATH`` is unset (and
   fails with :class:`LLVMNotFoundError` saying what to install when none exists),
2. selects the ``llvm_ad_rgb`` variant unless the caller already chose one
   (``cuda_ad_rgb`` is accepted but untested: ``drjit.nn`` inside a Mitsuba plugin is
   reported to crash on CUDA, mitsuba3 issue 1825),
3. registers the ``nerfpp`` integrator with Mitsuba.
"""
from __future__ import annotations

import sys

from mi_nerfpp import _llvm
from mi_nerfpp._llvm import LLVMNotFoundError
from mi_nerfpp.version import __version__

DEFAULT_VARIANT = 'llvm_ad_rgb'


def _chosen_variant():
    """The Mitsuba variant the caller already selected, or None."""
    mi = sys.modules.get('mitsuba')
    if mi is None:
        return None
    try:
        return mi.variant()
    except Exception:
        return None


def _setup():
    chosen = _chosen_variant()
    if chosen is None or chosen.startswith('llvm'):
        _llvm.configure()
    import mitsuba as mi  # deferred: Dr.Jit reads DRJIT_LIBLLVM_PATH (set above) when it loads
    if chosen is None:
        mi.set_variant(DEFAULT_VARIANT)
    variant = mi.variant()
    if '_ad_' not in variant or not variant.endswith('rgb'):
        raise ImportError(
            f"mi_nerfpp needs a differentiable RGB Mitsuba variant (llvm_ad_rgb or "
            f"cuda_ad_rgb), but '{variant}' is selected. Call "
            f"mi.set_variant('{DEFAULT_VARIANT}') before importing mi_nerfpp.")
    from mi_nerfpp.integrator import \
        register  # deferred: its module needs the variant set
    register()


_setup()

from mi_nerfpp.files.checkpoint import load_checkpoint  # noqa: E402
from mi_nerfpp.files.checkpoint import save_checkpoint
from mi_nerfpp.integrator import NeRFPPIntegrator  # noqa: E402

__all__ = ['NeRFPPIntegrator', 'LLVMNotFoundError', '__version__', 'load_checkpoint', 'save_checkpoint']
