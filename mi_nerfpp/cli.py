"""Command-line entry point: ``python -m mi_nerfpp <command>`` (also installed as ``mi-nerfpp``).

The commands live in :mod:`mi_nerfpp.commands`, one module each. This is their common
boundary: the project's errors (dataset, checkpoint, training and option errors are
``ValueError`` / ``RuntimeError`` subclasses), Mitsuba's (``RuntimeError``, with the
plugin's own message inside) and the operating system's (``OSError``: missing, read-only,
full) end the command with one line ``error: <command>: <what>`` on stderr and exit status 1,
never a traceback. Ctrl-C ends it with status 130.
"""
from __future__ import annotations

import argparse
import sys

from .errors import error_line


def build_parser():
    from .commands import COMMANDS
    p = argparse.ArgumentParser(prog='python -m mi_nerfpp',
                                description='NeRF++ for Mitsuba 3: render, optimize, evaluate.')
    sub = p.add_subparsers(dest='command', required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        return args.func(args) or 0
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        return 130
    except (ValueError, RuntimeError, OSError) as e:
        print(f'error: {args.command}: {error_line(e)}', file=sys.stderr)
        return 1
