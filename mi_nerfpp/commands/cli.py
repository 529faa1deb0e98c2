"""Command-line entry point: ``python -m mi_nerfpp <command>`` (also installed as ``mi-nerfpp``).

The commands live in :mod:`mi_nerfpp.commands`, one module each. This is their common
boundary: any error ends the command with one line ``error: <command>: <what>`` on stderr and
exit status 1, never a traceback. The project's errors (dataset, checkpoint, training and
option errors are ``ValueError`` / ``RuntimeError`` subclasses), Mitsuba's (``RuntimeError``,
with the plugin's own message inside) and the operating system's (``OSError``: missing,
read-only, full) say what was wrong and what to do; any other exception (a bug) is named with
the input the command was working on (:func:`subject`). ``--debug`` (before or after the
command) or ``MI_NERFPP_DEBUG=1`` prints the traceback above the line. Ctrl-C ends a command
with status 130, SIGTERM with 143 (128 + the signal, as a shell reports it). Usage errors (an unknown option, a value of the wrong type) are argparse's:
usage and message, status 2.

``--variant {llvm_ad_rgb,cuda_ad_rgb}`` (before or after the command) chooses the backend, over
``MI_NERFPP_VARIANT``. Importing the package selects the variant, before these arguments are
parsed, so the package reads ``--variant`` from the command line itself
(:mod:`mi_nerfpp.variant`). A process keeps its variant (Mitsuba's classes, the integrator's
among them, belong to one), so should the parsed ``--variant`` still differ from the selected
one (an abbreviated ``--var``), it is checked here (no CUDA: the one-line error) and the command
runs anew, ``python -m mi_nerfpp ARGS`` with ``MI_NERFPP_VARIANT`` set, in place of this process
(``os.execve``). A caller of :func:`main` from Python (``argv`` given) chooses the variant before
importing mi_nerfpp, and gets the error line for another one.
"""
from __future__ import annotations

import argparse
import io
import os
import sys
import traceback

import mitsuba as mi

from mi_nerfpp import _start, variant
from mi_nerfpp._llvm import LLVMNotFoundError
from mi_nerfpp.commands import (colmap, evaluate, export, optimize, render,
                                sweep, synth, video, view)
from mi_nerfpp.errors import error_line, interrupt_in

DEBUG_ENV = 'MI_NERFPP_DEBUG'
COMMANDS = (render, optimize, synth, evaluate, video, sweep, colmap, export, view)
VARIANT_HELP = (f'the backend: llvm_ad_rgb, the CPU (default), or cuda_ad_rgb, an NVIDIA GPU '
                f'(also: {variant.ENV}=NAME)')


def build_parser():
    p = argparse.ArgumentParser(prog='python -m mi_nerfpp',
                                description='NeRF++ for Mitsuba 3: render, optimize, evaluate.')
    p.add_argument('--debug', action='store_true',
                   help=f'print the traceback of an error (also: {DEBUG_ENV}=1)')
    p.add_argument('--variant', choices=tuple(variant.VARIANTS), default=None,
                   help=VARIANT_HELP)
    sub = p.add_subparsers(dest='command', required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    for parser in sub.choices.values():     # also after the command: optimize ... --debug
        parser.add_argument('--debug', action='store_true', default=argparse.SUPPRESS,
                            help=f'print the traceback of an error (also: {DEBUG_ENV}=1)')
        parser.add_argument('--variant', choices=tuple(variant.VARIANTS),
                            default=argparse.SUPPRESS, help=VARIANT_HELP)
    return p


def debugging(args=None) -> bool:
    """Whether errors show their traceback: ``--debug`` or ``MI_NERFPP_DEBUG`` set (not 0)."""
    return bool(getattr(args, 'debug', False)) or \
        os.environ.get(DEBUG_ENV, '').strip() not in ('', '0')


def subject(args) -> str:
    """What the command was working on, for the line of an unexpected error."""
    for command in COMMANDS:
        if getattr(args, 'func', None) is command.run and hasattr(command, 'subject'):
            return command.subject(args)
    return ''


def describe(error: BaseException, args) -> str:
    """The one line of an error (without ``error: <command>: ``)."""
    if isinstance(error, (ValueError, RuntimeError, OSError, variant.VariantError,
                          LLVMNotFoundError)):
        return error_line(error)
    what = subject(args)
    where = f' while working on {what}' if what else ''
    if isinstance(error, MemoryError):
        return (f'out of memory{where}: lower the sizes (images, --batch-rays, --samples, '
                f'resolutions) or use a machine with more memory')
    return (f'unexpected {type(error).__name__}{where}: {error_line(error)} (a bug: rerun with '
            f'--debug for the traceback and report it)')


def print_any_path() -> None:
    """Let standard output and error print any path. A Linux name may be any bytes but ``/``
    and NUL; Python gives one that is not UTF-8 as a ``str`` with surrogate escapes, which a
    stream that encodes strictly (a UTF-8 locale other than C.UTF-8, ``PYTHONIOENCODING``)
    refuses with UnicodeEncodeError, and which standard error (``backslashreplace``) prints as
    ``\\udcXX``. The process's own streams print such a path as its bytes
    (``surrogateescape``), so that it can be copied back; a stream put in their place (a
    caller's capture) that encodes strictly prints it escaped (``backslashreplace``)."""
    for name in ('stdout', 'stderr'):
        stream = getattr(sys, name)
        if not isinstance(stream, io.TextIOWrapper):
            continue
        if stream is getattr(sys, f'__{name}__'):
            stream.reconfigure(errors='surrogateescape')
        elif stream.errors == 'strict':
            stream.reconfigure(errors='backslashreplace')


def run_in_variant(args, argv, replace: bool) -> None:
    """For a ``--variant`` other than this process's: raise :class:`~mi_nerfpp.variant.VariantError`
    when this machine cannot run it, or when ``replace`` is false (a caller from Python); else
    replace this process by ``python -m mi_nerfpp ARGV`` that selects it (does not return)."""
    wanted, current = getattr(args, 'variant', None), mi.variant()
    if not wanted or wanted == current:
        return
    variant.check_available(wanted, variant.OPTION)
    if not replace:
        raise variant.VariantError(
            f'--variant {wanted}: this process runs {current}, selected when mi_nerfpp was '
            f'imported, and a process keeps its variant: set {variant.ENV}={wanted} (or call '
            f"mi.set_variant('{wanted}')) before importing mi_nerfpp")
    command = [sys.executable, '-m', 'mi_nerfpp', *argv]
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, command, dict(os.environ, **{variant.ENV: wanted}))


def main(argv=None, *, replace=None):
    """Run the command of ``argv`` (default: this program's arguments) and return its exit
    status. ``replace``: whether a ``--variant`` other than this process's may replace the
    process by one that selects it (default: when ``argv`` is None, i.e. main is the program;
    ``optimize.py`` passes True)."""
    print_any_path()
    _start.end_of_start()       # Ctrl-C and SIGTERM raise KeyboardInterrupt, handled below
    args = build_parser().parse_args(argv)
    try:
        run_in_variant(args, sys.argv[1:] if argv is None else list(argv),
                       argv is None if replace is None else replace)
        return args.func(args) or 0
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        return _start.interrupted_status()
    except Exception as e:
        if interrupt_in(e) is not None:     # a Ctrl-C in Python code that Dr.Jit called
            print('interrupted', file=sys.stderr)
            return _start.interrupted_status()
        if debugging(args):
            traceback.print_exc()
        print(f'error: {args.command}: {describe(e, args)}', file=sys.stderr)
        return 1


def entry_point():
    """The installed ``mi-nerfpp`` script and ``python -m mi_nerfpp``: :func:`main`, then the
    process ends at once with its status (:func:`mi_nerfpp._start.run_and_exit`)."""
    _start.run_and_exit(main)
