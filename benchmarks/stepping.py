"""A training step as a version's ``optimize.py`` takes it, for the benchmarks that time steps
(``benchmarks/profile.py``, ``benchmarks/versus.py``): :func:`make_trainer` runs in a process
that imports the version measured (this checkout's or a base revision's package), so it reads
only what that version has.
"""
from __future__ import annotations

import os
import shutil
import tempfile


def make_trainer(data=None, options=None, at=0.6, resume=None, freeze=None):
    """``(trainer, rays per step)``: a trainer of the version this process imports, made as its
    ``optimize.py`` makes one (``jobs.run.prepare`` chooses what the options leave to the
    capture: the sparse levels, the error map's share, ...; older versions without it get the
    bare config), at fraction ``at`` of a run. ``data``: a dataset folder (None: the embedded
    default capture); ``options``: keyword options of the version's config; ``resume``: a
    trained run folder whose checkpoint the trainer continues (copied; a fresh model allocates
    every brick); ``freeze``: None for the version's default."""
    from mi_nerfpp.data import load_dataset
    try:            # the layered package (issue 48), or the flat one of older revisions
        import mi_nerfpp.training.train as T
        from mi_nerfpp.data.synth import default_capture
    except ImportError:
        import mi_nerfpp.train as T
        from mi_nerfpp.synth import default_capture
    options = dict(options or {})
    if freeze is not None:
        options['freeze'] = freeze
    # The flat config of older versions, or the option groups of newer ones (from_options).
    make = getattr(T.TrainConfig, 'from_options', T.TrainConfig)
    cfg = make(iterations=10 ** 9, checkpoint_every=0, preview_every=0, **options)
    data = data or default_capture(progress=False)
    out = tempfile.mkdtemp(prefix='mi_nerfpp_profile_')
    if resume:
        shutil.copy(os.path.join(resume, 'model.npz'), out)
    try:
        from mi_nerfpp.jobs.run import prepare
    except ImportError:
        if resume:
            raise SystemExit('--resume needs a version with mi_nerfpp.jobs.run.prepare')
        dataset = load_dataset(data)
    else:
        inputs = prepare(data, cfg, out=out, resume=bool(resume))
        dataset, cfg = inputs.dataset, inputs.config
    trainer = T.Trainer(dataset, out, cfg, **({'resume': True} if resume else {}))
    trainer.iteration = int(at * 10 ** 9)     # the phase of the run (see --at)
    batch = cfg.schedule.batch_rays if hasattr(cfg, 'schedule') else cfg.batch_rays
    return trainer, batch
