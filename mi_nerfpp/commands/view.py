"""``python -m mi_nerfpp view RUN``: a web viewer of a run folder (finished, interrupted or being
trained): the model rendered from the browser's camera through the integrator, its layers, the
capture's cameras, and a camera-path editor whose paths ``video --path FILE`` renders.

The viewer (:mod:`mi_nerfpp.jobs.viewer`) needs the optional extra ``[viewer]`` (viser). It only
reads the run folder, never locks it: a run may train there meanwhile (``model.npz`` is reloaded
when it changes). Ctrl-C stops it.
"""
from __future__ import annotations

import contextlib
import signal
import threading

from mi_nerfpp.commands.arguments import port, positive_int
from mi_nerfpp.jobs.viewer import DEFAULT_MAX_WIDTH, open_viewer

DEFAULT_PORT = 8080


def add_port_options(p, prefix=''):
    """``--[view-]port`` and ``--[view-]host`` (shared with ``optimize --view``)."""
    p.add_argument(f'--{prefix}port', type=port, default=DEFAULT_PORT,
                   help=f'the port to serve the viewer on (default {DEFAULT_PORT}; a busy port '
                        f'is refused)')
    p.add_argument(f'--{prefix}host', default='127.0.0.1',
                   help='the address to listen on (default 127.0.0.1: this machine only; '
                        '0.0.0.0: every network interface)')
    p.add_argument(f'--{prefix}max-width', type=positive_int, default=DEFAULT_MAX_WIDTH,
                   metavar='PIXELS',
                   help=f'the widest render of a still view (default {DEFAULT_MAX_WIDTH}; the '
                        f'view is rendered 320 pixels across while the camera moves)')


def add_parser(sub):
    p = sub.add_parser('view', help='a web viewer of a run: the model, its layers, the cameras, '
                       'a camera-path editor', description=__doc__)
    p.add_argument('run', help='run folder written by optimize (holds model.npz)')
    add_port_options(p)
    p.set_defaults(func=run)
    return p


def subject(args):
    return f'run folder {args.run}'


def _interrupt(signum, frame):
    raise KeyboardInterrupt


@contextlib.contextmanager
def stop_signals():
    """SIGINT and SIGTERM raise KeyboardInterrupt inside (the command's status 130), also in a
    process started with SIGINT ignored (``view RUN &`` in a script); handlers restored after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)


def run(args):
    with stop_signals():
        viewer = open_viewer(args.run, args.host, args.port, args.max_width)
        try:
            print(f'viewer of {args.run}: {viewer.url} (Ctrl-C to stop)', flush=True)
            viewer.serve()
        finally:
            viewer.close()
    return 0
