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
import re
import sys


def build_parser():
    from .commands import COMMANDS
    p = argparse.ArgumentParser(prog='python -m mi_nerfpp',
                                description='NeRF++ for Mitsuba 3: render, optimize, evaluate.')
    sub = p.add_subparsers(dest='command', required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    return p


_EXCEPTION_LINE = re.compile(r'^(?:[A-Za-z_][\w.]*(?:Error|Exception)): (.+)$')


def error_line(error: BaseException) -> str:
    """One readable line for an error: an OSError's file and reason; for an error that wraps a
    Python traceback (Mitsuba's plugin errors) the innermost exception's message, with
    Mitsuba's location prefix (``At dictionary node ...`` / the scene file) kept in front."""
    while error.__cause__ is not None and '(see above)' in str(error):
        error = error.__cause__           # Dr.Jit wraps errors raised inside mi.render
    if isinstance(error, OSError) and error.strerror:
        where = f'{error.filename}: ' if error.filename else ''
        return f'{where}{error.strerror}'
    text = str(error).strip() or type(error).__name__
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    inner = [m.group(1) for m in map(_EXCEPTION_LINE.match, lines) if m]
    if len(lines) > 1 and inner:
        where = re.sub(r'^\[[\w.]+:\d+\]\s*', '', lines[0])
        where = where.split(': failed to instantiate')[0].split(': Traceback')[0]
        return f'{inner[-1]} ({where})' if where and where not in inner[-1] else inner[-1]
    return ' '.join(lines)


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
