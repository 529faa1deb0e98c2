"""mi-nerfpp: NeRF++ (Zhang, Riegler, Snavely, Koltun 2020) as a Mitsuba 3 integrator.

Importing the package

1. chooses the Mitsuba variant (:mod:`mi_nerfpp.variant`): the one the caller already selected,
   else ``MI_NERFPP_VARIANT``, else ``llvm_ad_rgb`` (the CPU); ``cuda_ad_rgb`` runs on an
   NVIDIA GPU, and fails here with :class:`VariantError` where there is no CUDA driver or GPU,
2. for ``llvm_ad_rgb``, points Dr.Jit at a libLLVM >= 17 when ``DRJIT_LIBLLVM_PATH`` is unset
   (and fails with :class:`LLVMNotFoundError` saying what to install when none exists),
3. selects the variant and registers the ``nerfpp`` integrator with Mitsuba.

On the command line (``python -m mi_nerfpp``, ``mi-nerfpp``, ``optimize.py``) these errors end
the process with one line, ``error: <command>: ...``, and exit status 1.
"""
from __future__ import annotations

from mi_nerfpp import _start

_start.catch_signals_while_starting()   # Ctrl-C or SIGTERM from here to the command: one line

from mi_nerfpp import variant  # noqa: E402
from mi_nerfpp._llvm import LLVMNotFoundError  # noqa: E402
from mi_nerfpp.variant import VariantError  # noqa: E402
from mi_nerfpp.version import __version__  # noqa: E402

DEFAULT_VARIANT = variant.DEFAULT


def _setup():
    variant.select()
    from mi_nerfpp.integrator import register  # deferred: its module needs the variant set
    register()


try:
    _setup()
except (LLVMNotFoundError, VariantError) as e:
    variant.exit_if_command_line(e)
    raise

from mi_nerfpp.files.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from mi_nerfpp.integrator import NeRFPPIntegrator  # noqa: E402

__all__ = ['NeRFPPIntegrator', 'LLVMNotFoundError', 'VariantError', '__version__',
           'load_checkpoint', 'save_checkpoint']
