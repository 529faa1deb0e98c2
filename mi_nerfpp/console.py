"""A training run shown on the terminal (the ``optimize`` and ``evaluate`` commands, the
benchmarks and the experiments): a progress bar, and the run's notices and evaluations above
it."""
from __future__ import annotations

from .run import RunObserver


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

    def started(self, trainer, inputs):
        from tqdm import tqdm

        from .run import dataset_line
        print(dataset_line(trainer, inputs), flush=True)
        schedule = trainer.cfg.schedule
        self.by_time = schedule.iterations is None
        self.bar = tqdm(total=round(60 * schedule.minutes) if self.by_time else
                        schedule.iterations, unit='s' if self.by_time else 'it',
                        desc=self.desc, dynamic_ncols=True,
                        initial=round(trainer.elapsed) if self.by_time else trainer.iteration)

    def step(self, trainer, loss, psnr):
        self.bar.update(round(trainer.elapsed) - self.bar.n if self.by_time else 1)
        if trainer.iteration % 10 == 0:
            self.bar.set_postfix(it=trainer.iteration, loss=f'{loss:.4f}', psnr=f'{psnr:.2f}')

    def evaluated(self, point):
        from .run import evaluation_line
        self._print(evaluation_line(point))

    def trained(self, trainer, finished):
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def track(self, iterable, desc='', unit='it', leave=True):
        from tqdm import tqdm
        return tqdm(iterable, desc=desc, unit=unit, leave=leave)
