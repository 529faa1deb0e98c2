"""How an error reads in one line: what the command line prints, and a sweep records for a
failed run."""
from __future__ import annotations

import errno
import re

# What to do, after the operating system's reason, for the errors a user can fix.
ADVICE = {
    errno.ENOSPC: ': free space on that disk or write somewhere else (--out)',
    errno.EDQUOT: ': free space within your quota or write somewhere else (--out)',
    errno.EROFS: ': write somewhere else (--out)',
}
_EXCEPTION_LINE = re.compile(r'^(?:[A-Za-z_][\w.]*(?:Error|Exception)): (.+)$')
# The most characters of a value that an error message shows.
SHOWN_CHARS = 60


def shown(value) -> str:
    """A value as an error message shows it: its ``repr`` (a list, tuple or dict as ``str``
    writes it, as in JSON), cut to :data:`SHOWN_CHARS` with ``...``."""
    text = str(value) if isinstance(value, (list, tuple, dict)) else repr(value)
    return text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS - 3] + '...'


def error_line(error: BaseException) -> str:
    """One readable line for an error: an OSError's file and reason; for an error that wraps a
    Python traceback (Mitsuba's plugin errors) the innermost exception's message, with
    Mitsuba's location prefix (``At dictionary node ...`` / the scene file) kept in front."""
    while error.__cause__ is not None and '(see above)' in str(error):
        error = error.__cause__           # Dr.Jit wraps errors raised inside mi.render
    if isinstance(error, OSError) and error.strerror:
        where = f'{error.filename}: ' if error.filename else ''
        advice = ADVICE.get(error.errno, '')
        return f'{where}{error.strerror}{advice}'
    text = str(error).strip() or type(error).__name__
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    inner = [m.group(1) for m in map(_EXCEPTION_LINE.match, lines) if m]
    if len(lines) > 1 and inner:
        where = re.sub(r'^\[[\w.]+:\d+\]\s*', '', lines[0])
        where = where.split(': failed to instantiate')[0].split(': Traceback')[0]
        return f'{inner[-1]} ({where})' if where and where not in inner[-1] else inner[-1]
    return ' '.join(lines)


def interrupt_in(error: BaseException | None) -> KeyboardInterrupt | None:
    """The :class:`KeyboardInterrupt` that ``error`` is or wraps, or None. Dr.Jit re-raises an
    exception from Python code that it calls - a step being recorded by ``drjit.freeze``, a
    loop body, a search predicate - as a RuntimeError caused by it, once per level: a Ctrl-C
    or SIGTERM that lands there arrives as such a chain."""
    while error is not None:
        if isinstance(error, KeyboardInterrupt):
            return error
        error = error.__cause__
    return None
