"""Shared by the benchmarks that compare a training option off and on (``appearance.py``,
``poses.py``): the same run twice from scratch, each scored on the held-out views."""
import dataclasses
import os

from mi_nerfpp.evaluate import evaluate_split
from mi_nerfpp.train import Trainer


def without_and_with(dataset, cfg, out, option, fit_appearance=None):
    """Train ``cfg`` with ``option`` (a TrainConfig field name) False, then True, each in
    ``out/<option>_<on>``; yields ``(on, config, trainer, held-out result)``.
    ``fit_appearance`` (default: the run's ``appearance``) scores NeRF-W style."""
    for on in (False, True):
        run = dataclasses.replace(cfg, **{option: on})
        tr = Trainer(dataset, os.path.join(out, f'{option.split("_")[-1]}_{on}'), run)
        tr.run()
        fit = run.appearance if fit_appearance is None else fit_appearance
        yield on, run, tr, evaluate_split(tr.model, tr.test, os.path.join(tr.out, 'test'),
                                          run.sampling, fit_appearance=fit)
