"""A training run shown on the terminal (the ``optimize`` and ``evaluate`` commands, the
benchmarks and the experiments): a progress bar, and the run's notices and evaluations above
it."""
from __future__ import annotations

import sys

from tqdm import tqdm

from mi_nerfpp.jobs.run import RunObserver, dataset_line, evaluation_line

# Seconds between redraws of a progress bar written to a file or a pipe (a cluster job's log,
# CI), where each redraw is a line's worth of text: the bar of a 10-minute run redrawn 3-4 times
# a second made a 273 KB log. On a terminal, tqdm's own intervals.
LOG_REFRESH = 60.0


def bar_refresh(stream=None) -> dict:
    """tqdm's redraw intervals for a bar drawn on ``stream`` (default: standard error, where
    tqdm draws): its defaults on a terminal; elsewhere at most one redraw per
    :data:`LOG_REFRESH` seconds (``maxinterval`` too: tqdm's monitor thread would otherwise
    redraw a slow bar every 10 seconds)."""
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, 'isatty', None)
    if isatty is not None and isatty():
        return {}
    return {'mininterval': LOG_REFRESH, 'maxinterval': LOG_REFRESH}


class ConsoleObserver(RunObserver):
    """Shows a run on the terminal: a progress bar of training (iterations, or seconds with a
    time budget) with loss and batch PSNR, the notices and evaluations above it."""

    shows_progress = True

    def __init__(self, desc='optimize'):
        self.desc, self.bar, self.by_time = desc, None, False

    def _print(self, text):
        if self.bar is not None:
            self.bar.write(text)
        else:
            print(text, flush=True)

    def notice(self, text):
        self._print(text)

    def planned(self, plan):
        self._print(plan.describe())

    def started(self, trainer, inputs):

        print(dataset_line(trainer, inputs), flush=True)
        schedule = trainer.cfg.schedule
        self.by_time = schedule.iterations is None
        self.bar = tqdm(total=round(60 * schedule.minutes) if self.by_time else
                        schedule.iterations, unit='s' if self.by_time else 'it',
                        desc=self.desc, dynamic_ncols=True, **bar_refresh(),
                        initial=round(trainer.elapsed) if self.by_time else trainer.iteration)

    def step(self, trainer, loss, psnr):
        self.bar.update(round(trainer.elapsed) - self.bar.n if self.by_time else 1)
        if trainer.iteration % 10 == 0:
            # Shown at the bar's next redraw (set_postfix would redraw it at once, ignoring
            # the interval).
            self.bar.set_postfix(it=trainer.iteration, loss=f'{loss:.4f}', psnr=f'{psnr:.2f}',
                                 refresh=False)

    def evaluated(self, point):
        self._print(evaluation_line(point))

    def trained(self, trainer, finished):
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def track(self, iterable, desc='', unit='it', leave=True):
        return tqdm(iterable, desc=desc, unit=unit, leave=leave, **bar_refresh())
