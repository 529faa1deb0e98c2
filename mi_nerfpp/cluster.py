"""Running on a Ray cluster: video frames on actors, one ``optimize`` run per task.

Ray is an optional dependency (``pip install -e '.[cluster]'``); nothing here imports it
before a command asks for ``--ray``. ``--ray auto`` joins the cluster this machine belongs to
(``ray start --head`` / ``ray start --address=...``) or starts a local one; ``--ray ADDRESS``
joins that cluster.

Frames. A :class:`FramePool` holds one actor per worker: each loads the checkpoint and builds
its :class:`~mi_nerfpp.views.ViewRenderer` once (its kernels compile once, Dr.Jit threads =
the actor's CPUs) and renders chunks of frames with :func:`mi_nerfpp.video.render_frames`, the
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
import tempfile

INSTALL_HINT = "pip install -e '.[cluster]'"
# Restarts of a frame worker whose process died, and retries of its chunk, before its chunks
# go to the other workers.
WORKER_RESTARTS = 3


def import_ray():
    """The ``ray`` module, or a RuntimeError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise RuntimeError(f'--ray needs the ray package, an optional extra: {INSTALL_HINT}') \
            from None
    return ray


@contextlib.contextmanager
def session(address: str):
    """Ray connected for the block: ``'auto'`` joins this machine's running cluster or starts a
    local one, else the cluster at ``address``. A connection made here is closed after."""
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    try:
        ray.init(address=None if address == 'auto' else address, include_dashboard=False,
                 log_to_driver=True, configure_logging=False)
    except ConnectionError as e:
        raise RuntimeError(f'--ray {address}: no Ray cluster there ({e}); start one with '
                           f'`ray start --head`, or use --ray auto') from None
    try:
        yield ray
    finally:
        ray.shutdown()


def cluster_cpus(ray) -> int:
    return int(ray.cluster_resources().get('CPU', 1))


def set_threads(cpus):
    """Dr.Jit's CPU threads for this process (a worker uses the CPUs Ray gave it)."""
    import drjit as dr
    dr.set_thread_count(max(1, int(cpus)))


class FrameWorker:
    """A model's renderer, loaded once (on the first frames): a worker of a
    :class:`FramePool` (a Ray actor with ``threads`` CPUs), or the renderer of the
    single-process command (``threads=None``)."""

    def __init__(self, checkpoint, threads=None):
        import mi_nerfpp  # noqa: F401  (libLLVM, llvm_ad_rgb, the nerfpp plugin)
        if threads:
            set_threads(threads)
        self.checkpoint, self.renderer = checkpoint, None

    def load(self, checkpoint_data=None):
        """Build the renderer of the checkpoint: from its path where this process sees it,
        else from ``checkpoint_data`` (``[ObjectRef]`` of the file's bytes)."""
        from .checkpoint import load_checkpoint
        from .views import ViewRenderer
        if self.renderer is not None:
            return self.renderer
        if os.path.isfile(self.checkpoint) or checkpoint_data is None:
            model, _, _ = load_checkpoint(self.checkpoint)
        else:                                    # not on shared storage: the copy Ray sent
            import ray
            with tempfile.TemporaryDirectory() as tmp:
                local = os.path.join(tmp, 'model.npz')
                with open(local, 'wb') as f:
                    f.write(ray.get(checkpoint_data[0]))
                model, _, _ = load_checkpoint(local)
        self.renderer = ViewRenderer(model)         # with the model's render settings
        return self.renderer

    def pid(self):
        return os.getpid()

    def render(self, cameras, frames_dir, exr=False, checkpoint_data=None, on_frame=None):
        """:func:`mi_nerfpp.video.render_frames` of ``cameras`` (index -> camera)."""
        from .video import render_frames
        if not os.path.isdir(frames_dir):
            import socket
            raise RuntimeError(f'{frames_dir} is not visible on node {socket.gethostname()}: '
                               f'write the frames to storage every node shares')
        return render_frames(self.load(checkpoint_data), cameras, frames_dir, exr, on_frame)


class FramePool:
    """``workers`` Ray actors of ``cpus`` CPUs each rendering frames of the checkpoint at
    ``checkpoint`` (a path on the driver)."""

    def __init__(self, checkpoint, workers, cpus=1):
        ray = import_ray()
        self.ray = ray
        checkpoint = os.path.abspath(checkpoint)
        with open(checkpoint, 'rb') as f:
            self.data = [ray.put(f.read())]   # fetched only by workers that cannot see the path
        actor = ray.remote(FrameWorker).options(num_cpus=cpus, max_restarts=WORKER_RESTARTS,
                                                max_task_retries=WORKER_RESTARTS)
        self.actors = [actor.remote(checkpoint, cpus) for _ in range(workers)]

    def pids(self):
        """The process ids of the workers (after they started)."""
        return self.ray.get([a.pid.remote() for a in self.actors])

    def render(self, cameras, indices, frames_dir, exr=False, chunk=None, on_frames=None):
        """Render frames ``indices`` of ``cameras`` to ``frames_dir`` across the workers, in
        chunks of ``chunk`` frames (default: about four chunks per worker, at most 8 frames);
        ``on_frames(n)`` after each chunk. A worker that dies for good leaves its chunks to
        the others; RuntimeError when none is left."""
        ray = self.ray
        from ray.exceptions import RayActorError
        indices = list(indices)
        if chunk is None:
            chunk = max(1, min(8, len(indices) // (4 * len(self.actors))))
        queue = [indices[i:i + chunk] for i in range(0, len(indices), chunk)]
        running, idle, alive = {}, list(self.actors), list(self.actors)

        def submit():
            while queue and idle:
                actor, part = idle.pop(), queue.pop(0)
                ref = actor.render.remote({i: cameras[i] for i in part}, frames_dir, exr,
                                          self.data)
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


def run_tasks(function, items, failed, address=None, cpus=1):
    """``function(item, threads)`` for each item, as Ray tasks of ``cpus`` CPUs on the
    cluster at ``address`` (see :func:`session`; Ray retries a task whose worker died), else
    one after the other here. Yields ``(item, result)`` as each finishes; a task that fails
    anyway gives ``failed(item, error)`` as its result, and the others go on."""
    if address is None:
        for item in items:
            yield item, function(item, None)
        return
    with session(address) as ray:
        task = ray.remote(function).options(num_cpus=cpus)
        running = {task.remote(item, cpus): item for item in items}
        while running:
            (ref,), _ = ray.wait(list(running), num_returns=1)
            item = running.pop(ref)
            try:
                yield item, ray.get(ref)
            except ray.exceptions.RayError as e:
                yield item, failed(item, e)
