"""The command line's first and last moments: signals while it starts, and its exit.

Importing the package and a command takes seconds (Mitsuba, Dr.Jit, LLVM, viser) before
:func:`mi_nerfpp.commands.cli.main` and its handler run. On the command line (:func:`command_line`),
:func:`catch_signals_while_starting` - the first thing the package does - lets Ctrl-C (SIGINT)
or SIGTERM in that time end the process with ``interrupted`` and the shell's status of the
signal (:func:`interrupted_status`: 130 for Ctrl-C, 143 for SIGTERM), not an import traceback
(or an ImportError of an extension whose start-up it broke). The command's own handling takes
over in :func:`end_of_start`, where SIGTERM raises KeyboardInterrupt as Ctrl-C does, so that
every command stops as when interrupted (its outputs whole or absent, a run's checkpoint
saved) with that status. A signal that is ignored (a background job) or handled by
the caller is left as it is; a library's import of the package is left alone.

After the command, :func:`exit_now` ends the process at once with its status: Python's
finalization (Dr.Jit's and Mitsuba's shutdown, ~0.4 s) resets the signal handlers, and a signal
then killed the process without a word.

This module imports nothing of the package's: it runs before any of it is loaded.
"""
from __future__ import annotations

import os
import signal
import sys
import threading

# The names under which the command line starts (``sys.argv[0]`` while the package is
# imported): ``python -m mi_nerfpp`` (``-m`` while Python locates the module), the installed
# ``mi-nerfpp`` script, and ``optimize.py`` (the ``optimize`` command).
PROGRAMS = {'-m': None, 'mi-nerfpp': None, 'optimize.py': 'optimize'}
# The status of a command stopped by a signal: 128 + its number, as a shell reports a process
# the signal ended (Ctrl-C: 130, SIGTERM: 143), so that a scheduler tells the two apart.
SIGNAL_STATUS_BASE = 128
# The signal that stopped the command (:func:`note_stop`); a KeyboardInterrupt of no signal
# (raised by code) counts as Ctrl-C.
_stopped_by = signal.SIGINT


def note_stop(signum) -> None:
    """Remember that signal ``signum`` stops the command (its handler calls this)."""
    global _stopped_by
    _stopped_by = signum


def interrupted_status() -> int:
    """The exit status of a command stopped by a signal (:data:`SIGNAL_STATUS_BASE` + the
    signal that :func:`note_stop` last heard of, Ctrl-C's by default)."""
    return SIGNAL_STATUS_BASE + int(_stopped_by)


def command_line(argv=None) -> tuple[bool, str | None]:
    """``(whether the process is mi_nerfpp's command line, its command or None)``, from
    ``argv`` (default ``sys.argv``) while the package is being imported: see :data:`PROGRAMS`.
    The command is the first word after the options ``--debug`` and ``--variant NAME``."""
    argv = sys.argv if argv is None else argv
    if not argv:
        return False, None
    name = argv[0] if argv[0] == '-m' else os.path.basename(argv[0])
    if name not in PROGRAMS:
        return False, None
    if PROGRAMS[name]:
        return True, PROGRAMS[name]
    words = iter(argv[1:])
    for word in words:
        if word == '--variant':
            next(words, None)
        elif not word.startswith('-'):
            return True, word
    return True, None


def _stopped_while_starting(signum, frame):
    """A signal while the command line starts: end the process as an interrupted command."""
    try:
        sys.stdout.flush()
    except Exception:     # noqa: BLE001 - a closed or broken stream: exit all the same
        pass
    try:
        print('interrupted', file=sys.stderr, flush=True)
    finally:
        os._exit(SIGNAL_STATUS_BASE + int(signum))


def _terminate(signum, frame):
    """SIGTERM while a command runs: stop as Ctrl-C stops it."""
    note_stop(signum)
    raise KeyboardInterrupt


# Each signal the start catches, with the disposition it is caught from (the default).
_DEFAULTS = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}


def catch_signals_while_starting(argv=None) -> None:
    """On the command line, let SIGINT and SIGTERM end the process with one line and the
    signal's status until :func:`end_of_start` (module docs)."""
    if not command_line(argv)[0] or threading.current_thread() is not threading.main_thread():
        return
    for signum, default in _DEFAULTS.items():
        if signal.getsignal(signum) is default:
            signal.signal(signum, _stopped_while_starting)


def end_of_start() -> None:
    """The command runs: Ctrl-C raises KeyboardInterrupt again, and so does SIGTERM (the
    status, :func:`interrupted_status`, then comes from the command line's boundary, which may
    save a checkpoint first)."""
    note_stop(signal.SIGINT)        # a command of its own: no earlier command's signal
    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGINT) is _stopped_while_starting:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if signal.getsignal(signal.SIGTERM) is _stopped_while_starting:   # the command line's
        signal.signal(signal.SIGTERM, _terminate)


def exit_now(status: int):
    """End the command-line process with ``status`` at once (module docs), its standard
    streams flushed."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:     # noqa: BLE001 - a closed or broken stream: exit all the same
            pass
    os._exit(status if isinstance(status, int) else 1)


def run_and_exit(main, *args, **kwargs):
    """Run the command line's ``main`` and end the process with its status (:func:`exit_now`):
    argparse's exits (usage, ``--help``) and a Ctrl-C before ``main``'s own handler end as
    they would, with their line."""
    try:
        status = main(*args, **kwargs)
    except SystemExit as e:
        if e.code is None or isinstance(e.code, int):
            status = e.code or 0
        else:
            print(e.code, file=sys.stderr)
            status = 1
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        status = interrupted_status()
    exit_now(status)
