"""argparse types the commands share: clear messages instead of raw ``ValueError``s."""
from __future__ import annotations

import argparse
import math

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


def at_least(low: int):
    """argparse type of whole numbers of at least ``low``."""
    def whole(value: str) -> int:
        try:
            number = int(value)
        except ValueError:
            number = low - 1
        if number < low:
            raise argparse.ArgumentTypeError(f"expects a whole number of at least {low}, got "
                                             f"'{value}'")
        return number
    return whole


def thread_count(value: str) -> int:
    """argparse type of thread counts: -1 (every core) or a whole number of at least 1."""
    try:
        number = int(value)
    except ValueError:
        number = 0
    if number != -1 and number < 1:
        raise argparse.ArgumentTypeError(f"expects -1 (every core) or a whole number of at "
                                         f"least 1, got '{value}'")
    return number


def positive_float(value: str) -> float:
    """argparse type of finite numbers above 0."""
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not (math.isfinite(number) and number > 0):
        raise argparse.ArgumentTypeError(f"expects a finite number above 0, got '{value}'")
    return number
