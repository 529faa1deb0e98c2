"""argparse types the commands share: clear messages instead of raw ``ValueError``s."""
from __future__ import annotations

import argparse
import math
import os

from mi_nerfpp.data.synth import parse_res
from mi_nerfpp.output.tracked_camera import parse_frame_range


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


def whole_between(low: int, high: int, why: str = ''):
    """argparse type of whole numbers from ``low`` to ``high`` (``why``: what sets the
    largest, for the message)."""
    def whole(value: str) -> int:
        try:
            number = int(value)
        except ValueError:
            number = low - 1
        if not low <= number <= high:
            because = f' ({why})' if why else ''
            raise argparse.ArgumentTypeError(f"expects a whole number from {low} to {high}"
                                             f"{because}, got '{value}'")
        return number
    return whole


# The most threads a count may ask for, per core of this machine: a count that fits COLMAP's C
# int but not the machine (2147483647) made the library allocate gigabytes before failing
# (issue 63); COLMAP's work is CPU-bound: more than a few threads per core gains nothing, and
# each extraction thread holds buffers of its own.
THREADS_PER_CORE = 4


def max_threads() -> int:
    """The most threads a thread count may ask for: :data:`THREADS_PER_CORE` per core of this
    machine."""
    return THREADS_PER_CORE * (os.cpu_count() or 1)


def thread_count(value: str) -> int:
    """argparse type of thread counts: -1 (every core) or a whole number from 1 to
    :func:`max_threads`."""
    try:
        number = int(value)
    except ValueError:
        number = 0
    high = max_threads()
    if number != -1 and not 1 <= number <= high:
        raise argparse.ArgumentTypeError(
            f"expects -1 (every core) or a whole number from 1 to {high} ({THREADS_PER_CORE} "
            f"per core of this machine's {os.cpu_count() or 1}), got '{value}'")
    return number


# The ports a server may listen on: 1 to 65535 (0 would be any free port, and the URL printed
# would not be known in advance). A port beyond reached socket.bind's OverflowError (issue 63).
MAX_PORT = 65535

port = whole_between(1, MAX_PORT, 'a TCP port')


def positive_float(value: str) -> float:
    """argparse type of finite numbers above 0."""
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not (math.isfinite(number) and number > 0):
        raise argparse.ArgumentTypeError(f"expects a finite number above 0, got '{value}'")
    return number


def float_between(low: float, high: float, unit: str = ''):
    """argparse type of finite numbers strictly between ``low`` and ``high`` (``unit``: shown
    after them)."""
    def number_in(value: str) -> float:
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not (math.isfinite(number) and low < number < high):
            raise argparse.ArgumentTypeError(f"expects a number between {low:g} and "
                                             f"{high:g}{unit}, got '{value}'")
        return number
    return number_in


def frame_range(value: str) -> tuple[int, int]:
    """argparse type of ``FIRST-LAST`` frame ranges (or one frame number)."""
    try:
        return parse_frame_range(value)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
