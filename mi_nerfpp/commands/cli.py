"""Command-line entry point: ``python -m mi_nerfpp <command>`` (also installed as ``mi-nerfpp``).

The commands live in :mod:`mi_nerfpp.commands`, one module each. This is their common
boundary: any error ends the command with one line ``error: <command>: <what>`` on stderr and
exit status 1, never a traceback. The project's errors (dataset, checkpoint, training and
option errors are ``ValueError`` / ``RuntimeError`` subclasses), Mitsuba's (``RuntimeError``,
with the plugin's own message inside) and the operating system's (``OSError``: missing,
read-only, full) say what was wrong and what to do; any other exception (a bug) is named with
the input the command was working on (:func:`subject`). ``--debug`` (before or after the
command) or ``MI_NERFPP_DEBUG=1`` prints the traceback above the line. Ctrl-C ends a command
with status 130. Usage errors (an unknown option, a value of the wrong type) are argparse's:
usage and message, status 2.
"""
from __future__ import annotations

import argparse
import os
import sys
import traceback

from mi_nerfpp.commands import (colmap, evaluate, export, optimize, render,
                                sweep, synth, video, view)
from mi_nerfpp.errors import error_line

DEBUG_ENV = 'MI_NERFPP_DEBUG'
COMMANDS = (render, optimize, synth, evaluate, video, sweep, colmap, export, view)


def build_parser():
    p = argparse.ArgumentParser(prog='python -m mi_nerfpp',
                                description='NeRF++ for Mitsuba 3: render, optimize, evaluate.')
    p.add_argument('--debug', action='store_true',
                   help=f'print the traceback of an error (also: {DEBUG_ENV}=1)')
    sub = p.add_subparsers(dest='command', required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    for parser in sub.choices.values():     # also after the command: optimize ... --debug
        parser.add_argument('--debug', action='store_true', default=argparse.SUPPRESS,
                            help=f'print the traceback of an error (also: {DEBUG_ENV}=1)')
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
    if isinstance(error, (ValueError, RuntimeError, OSError)):
        return error_line(error)
    what = subject(args)
    where = f' while working on {what}' if what else ''
    if isinstance(error, MemoryError):
        return (f'out of memory{where}: lower the sizes (images, --batch-rays, --samples, '
                f'resolutions) or use a machine with more memory')
    return (f'unexpected {type(error).__name__}{where}: {error_line(error)} (a bug: rerun with '
            f'--debug for the traceback and report it)')


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        return args.func(args) or 0
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        return 130
    except Exception as e:
        if debugging(args):
            traceback.print_exc()
        print(f'error: {args.command}: {describe(e, args)}', file=sys.stderr)
        return 1
