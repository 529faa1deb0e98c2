"""The paper-reproduction scripts run end to end (on a tiny capture and budget)."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _run(script, tmp_path, *args):
    out = subprocess.run(
        [sys.executable, os.path.join(ROOT, 'experiments', script), '--out', str(tmp_path / 'runs'),
         '--figures', str(tmp_path / 'fig'), '--data-cache', str(tmp_path / 'data'), '--spp', '2',
         *args], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


@pytest.mark.parametrize('script, args, rows', [
    ('shape_radiance.py', ['--views', '8', '--res', '12x12', '--iterations', '3',
                           '--learned-iterations', '2'], 4),
    ('mlp_structure.py', ['--views', '6', '--res', '12x8', '--mlp-iterations', '2',
                          '--grid-iterations', '2'], 5),
])
def test_experiment_writes_its_table_figure_and_results(tmp_path, script, args, rows):
    stdout = _run(script, tmp_path, *args)
    name = script[:-3]
    for ext in ('md', 'json', 'png'):
        assert (tmp_path / 'fig' / f'{name}.{ext}').stat().st_size > 0
    table = (tmp_path / 'fig' / f'{name}.md').read_text().splitlines()
    assert len(table) == 2 + rows + 1            # header, rule, models, black-image reference
    assert table[-1].startswith('| black image')
    written = json.loads((tmp_path / 'fig' / f'{name}.json').read_text())
    results, black = written['results'], written['black_image']
    assert len(results) == rows
    for model, r in results.items():
        scored = {s: v for s, v in r.items() if isinstance(v, dict) and 'psnr' in v}
        assert set(scored) == set(black)
        for s, split in scored.items():
            assert split['psnr'] > 0 and -1 <= split['ssim'] <= 1
            # A score of a prediction against the capture: finite (not the ground truth scored
            # against itself), not the all-black reference, object PSNR scored too.
            assert np.isfinite(split['psnr']) and split['psnr'] < 60, (model, s, split)
            assert abs(split['psnr'] - black[s]['psnr']) > 1e-3, (model, s, split)
            assert np.isfinite(split['psnr_object']) and split['views'] > 0
        # The table shows the JSON's numbers.
        row = next(line for line in table if line.startswith(f'| {model} |'))
        first = next(iter(scored.values()))
        assert f"{first['psnr']:.2f}" in row, (row, first)
    assert 'wrote' in stdout
