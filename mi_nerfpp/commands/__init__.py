"""The commands of ``python -m mi_nerfpp``: one module per command, each with
``add_parser(subparsers)`` and ``run(args)``; library code lives in the package modules."""
from __future__ import annotations

import argparse

from . import colmap, evaluate, export, optimize, render, sweep, synth, video

COMMANDS = (render, optimize, synth, evaluate, video, sweep, colmap, export)


def resolution(value: str) -> tuple[int, int]:
    """argparse type of ``WxH`` options: a clear message instead of a raw ValueError."""
    from ..synth import parse_res
    try:
        return parse_res(value)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def positive_int(value: str) -> int:
    """argparse type of counts that must be at least 1."""
    try:
        number = int(value)
    except ValueError:
        number = 0
    if number < 1:
        raise argparse.ArgumentTypeError(f"expects a whole number of at least 1, got '{value}'")
    return number

