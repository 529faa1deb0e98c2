"""Command-line entry point: ``python -m mi_nerfpp <command>`` (also installed as ``mi-nerfpp``).

The commands live in :mod:`mi_nerfpp.commands`, one module each.
"""
from __future__ import annotations

import argparse
import sys


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
