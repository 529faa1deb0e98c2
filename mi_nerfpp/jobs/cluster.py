"""Running on a Ray cluster: video frames on actors, one ``optimize`` run per task.

Ray is an optional dependency (``pip install -e '.[cluster]'``); nothing here imports it
before a command asks for ``--ray``. ``--ray auto`` joins the cluster this machine belongs to
(``ray start --head`` / ``ray start --address=...``) or starts a local one; ``--ray ADDRESS``
joins that cluster.

Frames. A :class:`FramePool` holds one actor per worker: each loads the checkpoint and builds
its :class:`~mi_nerfpp.output.views.ViewRenderer` once (its kernels compile once, Dr.Jit threads =
the actor's CPUs) and renders chunks of frames with :func:`mi_nerfpp.output.video.render_frames`, the
function the single-process command runs. The checkpoint is read from the run folder where a
worker sees that path (shared storage), else sent through Ray's object store. A worker whose
process dies is restarted by Ray and its chunk retried; a chunk whose actor cannot come back
goes to the others. Frames are written atomically and done frames are skipped, so a retried
chunk only renders what is missing.

Captures. :func:`run_tasks` runs a function over many inputs as Ray tasks (or in this process
without a cluster), yielding each result as it comes.
"""
from __future__ import annotations

import contextlib
import os
import socket
import sys
import tempfile
import threading

import drjit as dr

from mi_nerfpp.core.arrays import llvm_backend
from mi_nerfpp.files.checkpoint import load_checkpoint
from mi_nerfpp.output.video import FRAME_NAME, render_frames
from mi_nerfpp.output.views import ViewRenderer

INSTALL_HINT = "pip install -e '.[cluster]'"
# Seconds to wait for a cluster address to answer (--ray ADDRESS) before giving up, and for
# joining the cluster there (the environment variable overrides the latter).
CONNECT_TIMEOUT = 10.0
INIT_TIMEOUT = 60.0
INIT_TIMEOUT_ENV = 'MI_NERFPP_RAY_TIMEOUT'
# Restarts of a frame worker whose process died, and retries of its chunk, before its chunks
# go to the other workers.
WORKER_RESTARTS = 3


def import_ray():
    """The ``ray`` module, or a RuntimeError saying how to install it."""
    try:
        import ray  # deferred: ray is the optional extra [cluster]
    except ImportError:
        raise RuntimeError(f'--ray needs the ray package, an optional extra: {INSTALL_HINT}') \
            from None
    return ray


def check_address(address: str):
    """Refuse, before any work, ``--ray ADDRESS`` when the ray package is missing or no Ray
    cluster answers at the address within :data:`CONNECT_TIMEOUT` seconds: Ray's own client
    retries an address for ever when nothing (or something else) answers there. A Ray head
    (its GCS) and a Ray Client server speak gRPC: they answer the HTTP/2 preface with a
    SETTINGS frame. ``auto`` is left to Ray (it joins this machine's cluster or starts one),
    unless ``RAY_ADDRESS`` names a cluster for it. Raises RuntimeError with one line saying
    what to do."""
    import_ray()
    given = address
    if address in (None, 'auto', 'local'):
        address = os.environ.get('RAY_ADDRESS', '')
        if address in ('', 'auto', 'local'):
            return
    shown = f'--ray {given}' + (f' (RAY_ADDRESS={address})' if address != given else '')
    host, _, port = address.split('://', 1)[-1].rpartition(':')
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise RuntimeError(f'{shown}: not a cluster address: give HOST:PORT (the head node\'s '
                           f'address, as `ray start --head` prints it) or auto')
    try:
        with socket.create_connection((host.strip('[]'), int(port)),
                                      timeout=CONNECT_TIMEOUT) as s:
            s.settimeout(CONNECT_TIMEOUT)
            s.sendall(_HTTP2_PREFACE)
            reply = b''
            while len(reply) < 9:
                chunk = s.recv(9 - len(reply))
                if not chunk:
                    break
                reply += chunk
    except OSError as e:
        reason = (f'no answer within {CONNECT_TIMEOUT:g} s' if isinstance(e, socket.timeout)
                  else (e.strerror or str(e)).lower())
        raise RuntimeError(f'{shown}: no Ray cluster answers there ({reason}): start one with '
                           f'`ray start --head` and give the address it prints, or use '
                           f'--ray auto') from None
    if len(reply) < 9 or reply[3] != _HTTP2_SETTINGS:
        raise RuntimeError(f'{shown}: something answers there, but not a Ray cluster (no gRPC '
                           f'reply): give the address `ray start --head` prints, or use '
                           f'--ray auto')


# The client's HTTP/2 connection preface and an empty SETTINGS frame; a gRPC server answers
# with its SETTINGS frame (frame type 4, the fourth byte of the 9-byte frame header).
_HTTP2_PREFACE = b'PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n' + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
_HTTP2_SETTINGS = 4


@contextlib.contextmanager
def session(address: str, exit_line: str | None = None):
    """Ray connected for the block: ``'auto'`` joins this machine's running cluster or starts a
    local one, else the cluster at ``address`` (:func:`check_address` first). A connection
    made here is closed after.

    ``exit_line`` (the command line's): when joining ``address`` has not finished after
    :func:`init_timeout` seconds - something at the address speaks gRPC but is no Ray
    cluster, and Ray's client retries for ever, out of reach of Python's signal handlers -
    the process prints this line to stderr and exits with status 1 (nothing has been written
    yet)."""
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    check_address(address)
    watchdog = None
    if exit_line and address not in (None, 'auto', 'local'):
        def give_up():                           # on a line of its own, under a progress bar
            sys.stderr.write(f'\n{exit_line}\n')
            sys.stderr.flush()
            os._exit(1)
        watchdog = threading.Timer(init_timeout(), give_up)
        watchdog.daemon = True
        watchdog.start()
    try:
        ray.init(address=None if address == 'auto' else address, include_dashboard=False,
                 log_to_driver=True, configure_logging=False)
    except ConnectionError as e:
        raise RuntimeError(f'--ray {address}: no Ray cluster there ({e}); start one with '
                           f'`ray start --head`, or use --ray auto') from None
    finally:
        if watchdog is not None:
            watchdog.cancel()
    try:
        yield ray
    finally:
        ray.shutdown()


def init_timeout() -> float:
    """Seconds that joining a cluster may take (:func:`session`): ``MI_NERFPP_RAY_TIMEOUT``,
    else :data:`INIT_TIMEOUT`."""
    try:
        value = float(os.environ.get(INIT_TIMEOUT_ENV, INIT_TIMEOUT))
    except ValueError:
        value = INIT_TIMEOUT
    return value if value > 0 else INIT_TIMEOUT


def timeout_line(command: str, address: str) -> str:
    """The line a command ends with when joining the cluster at ``address`` times out."""
    return (f'error: {command}: --ray {address}: no Ray cluster came up there within '
            f'{init_timeout():g} s (something answers, but Ray cannot join it): check the '
            f'address `ray start --head` printed, or use --ray auto')


def cluster_cpus(ray) -> int:
    return int(ray.cluster_resources().get('CPU', 1))


def set_threads(cpus):
    """Dr.Jit's CPU threads for this process (a worker uses the CPUs Ray gave it), on the CPU
    backend; on CUDA the GPU runs the kernels and the thread pool is left as it is."""
    if llvm_backend():
        dr.set_thread_count(max(1, int(cpus)))


class FrameWorker:
    """A model's renderer, loaded once (on the first frames): a worker of a
    :class:`FramePool` (a Ray actor with ``threads`` CPUs), or the renderer of the
    single-process command (``threads=None``)."""

    def __init__(self, checkpoint, threads=None, look=None):
        if threads:
            set_threads(threads)
        # How the frames are rendered: ViewRenderer's skip_empty and appearance_image.
        self.checkpoint, self.renderer, self.look = checkpoint, None, dict(look or {})

    def load(self, checkpoint_data=None):
        """Build the renderer of the checkpoint: from its path where this process sees it,
        else from ``checkpoint_data`` (``[ObjectRef]`` of the file's bytes)."""
        if self.renderer is not None:
            return self.renderer
        if os.path.isfile(self.checkpoint) or checkpoint_data is None:
            model, _, _ = load_checkpoint(self.checkpoint)
        else:                                    # not on shared storage: the copy Ray sent
            import ray  # deferred: ray is the optional extra [cluster]
            with tempfile.TemporaryDirectory() as tmp:
                local = os.path.join(tmp, 'model.npz')
                with open(local, 'wb') as f:
                    f.write(ray.get(checkpoint_data[0]))
                model, _, _ = load_checkpoint(local)
        # With the model's render settings (whole rays without ``skip_empty``).
        self.renderer = ViewRenderer(model, **self.look)
        return self.renderer

    def pid(self):
        return os.getpid()

    def render_frames(self, cameras, frames_dir, exr=False, checkpoint_data=None, on_frame=None,
                      name=FRAME_NAME):
        """:func:`mi_nerfpp.output.video.render_frames` of ``cameras`` (index -> camera), the
        files named by ``name``."""
        if not os.path.isdir(frames_dir):
            raise RuntimeError(f'{frames_dir} is not visible on node {socket.gethostname()}: '
                               f'write the frames to storage every node shares')
        return render_frames(self.load(checkpoint_data), cameras, frames_dir, exr, on_frame,
                             name)


class FramePool:
    """``workers`` Ray actors of ``cpus`` CPUs each rendering frames of the checkpoint at
    ``checkpoint`` (a path on the driver)."""

    def __init__(self, checkpoint, workers, cpus=1, look=None):
        ray = import_ray()
        self.ray = ray
        checkpoint = os.path.abspath(checkpoint)
        with open(checkpoint, 'rb') as f:
            self.data = [ray.put(f.read())]   # fetched only by workers that cannot see the path
        actor = ray.remote(FrameWorker).options(num_cpus=cpus, max_restarts=WORKER_RESTARTS,
                                                max_task_retries=WORKER_RESTARTS)
        self.actors = [actor.remote(checkpoint, cpus, look) for _ in range(workers)]

    def pids(self):
        """The process ids of the workers (after they started)."""
        return self.ray.get([a.pid.remote() for a in self.actors])

    def render_frames(self, cameras, indices, frames_dir, exr=False, chunk=None, on_frames=None,
                      name=FRAME_NAME):
        """Render frames ``indices`` of ``cameras`` (a list, or a dict of index -> camera) to
        ``frames_dir`` (files named by ``name``) across the workers, in chunks of ``chunk``
        frames (default: about four chunks per worker, at most 8 frames);
        ``on_frames(n)`` after each chunk. A worker that dies for good leaves its chunks to
        the others; RuntimeError when none is left."""
        ray = self.ray
        from ray.exceptions import \
            RayActorError  # deferred: ray is the optional extra [cluster]
        indices = list(indices)
        if chunk is None:
            chunk = max(1, min(8, len(indices) // (4 * len(self.actors))))
        queue = [indices[i:i + chunk] for i in range(0, len(indices), chunk)]
        running, idle, alive = {}, list(self.actors), list(self.actors)

        def submit():
            while queue and idle:
                actor, part = idle.pop(), queue.pop(0)
                ref = actor.render_frames.remote({i: cameras[i] for i in part}, frames_dir, exr,
                                          self.data, None, name)
                running[ref] = (actor, part)

        submit()
        while running:
            (ref,), _ = ray.wait(list(running), num_returns=1)
            actor, part = running.pop(ref)
            try:
                ray.get(ref)
            except RayActorError as e:
                alive.remove(actor)
                if not alive:
                    raise RuntimeError(f'every frame worker died; the last: {e}') from None
                queue.insert(0, part)
            else:
                idle.append(actor)
                if on_frames is not None:
                    on_frames(len(part))
            submit()

    def close(self):
        for actor in self.actors:
            self.ray.kill(actor)


def run_tasks(function, items, failed, address=None, cpus=1, exit_line=None):
    """``function(item, threads)`` for each item, as Ray tasks of ``cpus`` CPUs on the
    cluster at ``address`` (see :func:`session`, also for ``exit_line``; Ray retries a task
    whose worker died), else one after the other here. Yields ``(item, result)`` as each
    finishes; a task that fails anyway gives ``failed(item, error)`` as its result, and the
    others go on."""
    if address is None:
        for item in items:
            yield item, function(item, None)
        return
    with session(address, exit_line) as ray:
        task = ray.remote(function).options(num_cpus=cpus)
        running = {task.remote(item, cpus): item for item in items}
        while running:
            (ref,), _ = ray.wait(list(running), num_returns=1)
            item = running.pop(ref)
            try:
                yield item, ray.get(ref)
            except ray.exceptions.RayError as e:
                yield item, failed(item, e)
