"""Which Mitsuba variant - which Dr.Jit backend - mi_nerfpp runs on.

Two variants are accepted: ``llvm_ad_rgb`` (the CPU, Dr.Jit's LLVM backend; the default) and
``cuda_ad_rgb`` (an NVIDIA GPU, Dr.Jit's CUDA backend). Importing :mod:`mi_nerfpp` selects, in
this order of precedence (:func:`choose`):

1. the variant the caller already selected with ``mi.set_variant`` before the import;
2. on the command line, its option ``--variant NAME`` (before or after the command);
3. the environment variable ``MI_NERFPP_VARIANT``;
4. ``llvm_ad_rgb``: the CPU stays the default, CUDA only when asked for.

The command line's ``--variant`` is read here, from ``sys.argv``, when the package is imported
as the start of the command line (:func:`command_line`), because the import selects the variant
before argparse reads the arguments: so ``--variant cuda_ad_rgb`` needs no libLLVM, and the
process starts once. It is passed on as ``MI_NERFPP_VARIANT`` to the processes the command
starts (Ray workers on this machine, say). (Should argparse still find another variant, e.g. from an abbreviated
``--var``, the command runs anew in a process that selects it: :mod:`mi_nerfpp.commands.cli`.)
A CUDA variant is checked when it is selected: without a CUDA
driver or GPU the import raises :class:`VariantError` with one line that says so and what to do,
and the command line (``python -m mi_nerfpp``, ``mi-nerfpp``, ``optimize.py``) prints that line
as ``error: <command>: ...`` and exits with status 1 (:func:`exit_if_command_line`).

This module must not import drjit or mitsuba at module level: the choice is made before Dr.Jit
loads (it reads ``DRJIT_LIBLLVM_PATH``, which :mod:`mi_nerfpp._llvm` sets, when it loads).
"""
from __future__ import annotations

import ctypes
import os
import sys
import traceback

from mi_nerfpp import _llvm
from mi_nerfpp._start import PROGRAMS, command_line  # noqa: F401 - where the command line starts

ENV = 'MI_NERFPP_VARIANT'
DEFAULT = 'llvm_ad_rgb'
# The variants mi_nerfpp runs on, and what each runs on.
VARIANTS = {'llvm_ad_rgb': 'the CPU', 'cuda_ad_rgb': 'an NVIDIA GPU'}
# Where a choice came from, as messages name it.
SELECTED, OPTION = 'mi.set_variant', '--variant'


class VariantError(ImportError):
    """A variant mi_nerfpp does not run on, or one this machine cannot run (no CUDA)."""


def allowed() -> str:
    """The accepted variants, for messages: ``llvm_ad_rgb (the CPU), cuda_ad_rgb (...)``."""
    return ', '.join(f'{name} ({what})' for name, what in VARIANTS.items())


def is_llvm(variant: str) -> bool:
    """Whether ``variant`` runs on Dr.Jit's LLVM (CPU) backend."""
    return variant.startswith('llvm_')


def choose(selected: str | None = None, environ=os.environ,
           option: str | None = None) -> tuple[str, str]:
    """``(variant, where the choice came from)``: ``selected`` (the variant the caller selected
    in Mitsuba, or None), else ``option`` (the command line's ``--variant``, when it names one
    of :data:`VARIANTS`; argparse refuses other values), else ``MI_NERFPP_VARIANT``, else
    :data:`DEFAULT`. Raises :class:`VariantError` for a variant mi_nerfpp does not run on."""
    if selected is not None:
        if selected not in VARIANTS:
            raise VariantError(
                f"mi_nerfpp needs a differentiable RGB Mitsuba variant, {allowed()}, but "
                f"'{selected}' is selected: select one of them before importing mi_nerfpp, or "
                f"none ({ENV} then chooses)")
        return selected, SELECTED
    if option in VARIANTS:
        return option, OPTION
    value = environ.get(ENV, '').strip()
    if not value:
        return DEFAULT, 'default'
    if value not in VARIANTS:
        raise VariantError(f'{ENV}={value!r} is not a variant mi_nerfpp runs on: set it to one '
                           f'of {allowed()}, or unset it for {DEFAULT}')
    return value, ENV


def cuda_missing(source: str) -> VariantError:
    """The error of a CUDA variant asked for (by ``source``) on a machine that cannot run it."""
    try:
        ctypes.CDLL('libcuda.so.1')
        why = ('the NVIDIA driver (libcuda.so.1) loads, but Dr.Jit could not initialize CUDA '
               'with it (no GPU visible to this process, or a driver too old for Dr.Jit)')
    except OSError:
        why = 'no NVIDIA driver (libcuda.so.1) could be loaded'
    undo = {OPTION: 'leave out --variant cuda_ad_rgb (or pass --variant llvm_ad_rgb)',
            ENV: f'unset {ENV} (or set it to llvm_ad_rgb)'}.get(source, f"select '{DEFAULT}'")
    return VariantError(f'cuda_ad_rgb was asked for ({source}) but no CUDA driver/GPU was '
                        f'found: {why}. To run on the CPU, {undo}; for the GPU, install the '
                        f'NVIDIA driver on a machine with an NVIDIA GPU')


def check_available(variant: str, source: str) -> None:
    """Raise :class:`VariantError` when this machine cannot run ``variant``: a CUDA variant
    without a CUDA backend in Dr.Jit (no driver, no GPU). Imports Dr.Jit."""
    if is_llvm(variant):
        return
    import drjit as dr  # deferred: Dr.Jit loads after DRJIT_LIBLLVM_PATH is set (select)
    if not dr.has_backend(dr.JitBackend.CUDA):
        raise cuda_missing(source)


def select(environ=os.environ, argv=None) -> str:
    """Choose the variant (:func:`choose`; ``--variant`` from ``argv``, default ``sys.argv``,
    when it is the command line's), make its backend ready and select it in Mitsuba; returns
    it. An LLVM variant needs libLLVM (:func:`mi_nerfpp._llvm.configure`, which raises
    :class:`~mi_nerfpp._llvm.LLVMNotFoundError`); a CUDA variant a CUDA backend
    (:func:`check_available`), and libLLVM only if one is there, so that Dr.Jit's CPU backend,
    which it starts as well, does not pick an old one."""
    mi = sys.modules.get('mitsuba')
    selected = None
    if mi is not None:
        try:
            selected = mi.variant()
        except Exception:
            selected = None
    argv = sys.argv if argv is None else argv
    option = option_value(argv) if command_line(argv)[0] else None
    variant, source = choose(selected, environ, option)
    if source == OPTION:       # the processes the command starts (Ray workers) choose the same
        environ[ENV] = variant
    if is_llvm(variant):
        _llvm.configure(environ)
    else:
        try:
            _llvm.configure(environ)
        except _llvm.LLVMNotFoundError:
            pass
    check_available(variant, source)
    import mitsuba as mi  # deferred: Dr.Jit reads DRJIT_LIBLLVM_PATH (set above) when it loads
    if selected is None:
        try:
            mi.set_variant(variant)
        except ImportError as e:       # a backend that fails past Dr.Jit's own check
            if is_llvm(variant):
                raise
            raise cuda_missing(source) from e
    return variant


def option_value(argv) -> str | None:
    """The value of ``--variant NAME`` / ``--variant=NAME`` in ``argv[1:]`` (the last one given,
    as argparse takes it), up to a ``--``; None without one."""
    value, words = None, iter(argv[1:])
    for word in words:
        if word == '--':
            break
        if word == '--variant':
            value = next(words, None)
        elif word.startswith('--variant='):
            value = word.partition('=')[2]
    return value


def exit_if_command_line(error: ImportError, argv=None) -> None:
    """On the command line, end the process with ``error`` as one line (``error: <command>:
    <message>``, exit status 1) instead of an import traceback; elsewhere return (the caller
    re-raises: a library's import fails with the exception)."""
    argv = sys.argv if argv is None else argv
    program, command = command_line(argv)
    if not program:
        return
    if '--debug' in argv[1:] or os.environ.get('MI_NERFPP_DEBUG', '').strip() not in ('', '0'):
        traceback.print_exception(error)         # as the command line's --debug shows it
    where = f'{command}: ' if command else ''
    text = ' '.join(str(error).split())
    sys.exit(f'error: {where}{text}')
