"""The terminal view of a run (mi_nerfpp.jobs.console): its progress bar on a terminal and in a log."""
import io
from types import SimpleNamespace

from mi_nerfpp.jobs import console


class Terminal(io.StringIO):
    def isatty(self):
        return True


def fake_run(iterations):
    """A trainer and run inputs with what the console reads of them."""
    trainer = SimpleNamespace(cfg=SimpleNamespace(schedule=SimpleNamespace(
        iterations=iterations, minutes=None)), iteration=0, elapsed=0.0,
        rays=SimpleNamespace(size=1000))
    dataset = SimpleNamespace(format='nerfpp', train=[0] * 4, validation=[0], test=[0])
    inputs = SimpleNamespace(dataset=dataset, data='data/x', out='runs/x')
    return trainer, inputs


def test_bars_keep_tqdms_intervals_on_a_terminal_and_redraw_seldom_in_a_log():
    assert console.bar_refresh(Terminal()) == {}
    assert console.bar_refresh(io.StringIO()) == {'mininterval': console.LOG_REFRESH,
                                                  'maxinterval': console.LOG_REFRESH}


def test_a_training_bar_written_to_a_log_is_not_redrawn_at_every_loss_update(capsys):
    # Under pytest standard error is captured, not a terminal: a log. The loss and PSNR are
    # set every 10 iterations; each used to redraw the bar (here 200 redraws).
    trainer, inputs = fake_run(2000)
    observer = console.ConsoleObserver()
    observer.started(trainer, inputs)
    for i in range(1, 2001):
        trainer.iteration = i
        observer.step(trainer, loss=0.01, psnr=30.0)
    observer.trained(trainer, True)
    err = capsys.readouterr().err
    draws = err.count('\r') + err.count('\n')
    assert draws <= 4, err
    assert '2000/2000' in err and 'psnr=30.00' in err      # the last state is still shown
