"""`python -m mi_nerfpp sweep` in one process: option sets, finished runs kept, bad options."""
import json

import pytest

from mi_nerfpp.commands.cli import main
from tests.helpers import TINY_RUN


def test_sweep_option_sets_in_one_process(capture, tmp_path, capsys):
    runs = tmp_path / 'runs'
    argv = ['sweep', capture, '--out', str(runs), '--set', '--seed 3'] + TINY_RUN
    assert main(argv) == 0
    run = runs / 'data_seed-3'
    config = json.loads((run / 'metrics.json').read_text())['config']
    assert config['schedule']['seed'] == 3 and config['schedule']['iterations'] == 5
    first = capsys.readouterr().out
    assert 'data_seed-3' in first and ' ok' in first
    log = (run / 'optimize.log').read_text()        # the run's progress, in its folder
    assert 'run folder' in log and 'training finished at iteration 5' in log
    assert 'held-out views: PSNR' in log and 'training finished' not in first
    # A finished run is reported, not trained again.
    mtime = (run / 'model.npz').stat().st_mtime_ns
    assert main(argv) == 0
    assert (run / 'model.npz').stat().st_mtime_ns == mtime
    assert 'finished before' in capsys.readouterr().out


def test_sweep_refuses_bad_options_before_any_run(capture, tmp_path, capsys):
    assert main(['sweep', capture, '--out', str(tmp_path), '--set', '--batch-rays 0']) == 1
    assert '--batch-rays' in capsys.readouterr().err
    assert not (tmp_path / 'data').exists()
    with pytest.raises(SystemExit):
        main(['sweep', capture, '--out', str(tmp_path), '--set', '--no-such-option 1'])
