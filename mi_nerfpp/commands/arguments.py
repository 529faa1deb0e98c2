"""argparse types the commands share: clear messages instead of raw ``ValueError``s."""
from __future__ import annotations

import argparse

from mi_nerfpp.data.synth import parse_res


def resolution(value: str) -> tuple[int, int]:
    """argparse type of ``WxH`` options: a clear message instead of a raw ValueError."""
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

