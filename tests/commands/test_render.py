"""`python -m mi_nerfpp render`: multi-layer EXR and PNG preview from a scene XML."""
import subprocess
import sys

import numpy as np
import OpenEXR

from mi_nerfpp.files.exr import read_exr
from mi_nerfpp.data.synth import scene_file



def test_render_command_writes_layered_exr_and_preview(tmp_path):
    out, png = tmp_path / 'out.exr', tmp_path / 'out.png'
    r = subprocess.run([sys.executable, '-m', 'mi_nerfpp', 'render',
                        scene_file('render_random.xml'), '-o', str(out),
                        '--preview', str(png), '-D', 'res_x=12', '-D', 'res_y=8'],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert str(out) in r.stdout
    names = set(OpenEXR.File(str(out)).channels().keys())
    # OpenEXR groups R,G,B,A and layers
    assert names == {'RGBA', 'fg', 'bg', 'depth.Z', 'distance.Y', 'obj', 'obj_depth.Z', 'shadow'}
    c = read_exr(out)
    assert set(c) == {'R', 'G', 'B', 'A', 'fg.R', 'fg.G', 'fg.B', 'fg.A', 'bg.R', 'bg.G', 'bg.B',
                      'depth.Z', 'distance.Y', 'obj.R', 'obj.G', 'obj.B', 'obj.A', 'obj_depth.Z',
                      'shadow.R', 'shadow.G', 'shadow.B'}
    assert c['R'].shape == (8, 12)
    for ch in 'RGB':     # a scene without shapes: the objects' layers are 0
        assert not c[f'obj.{ch}'].any() and not c[f'shadow.{ch}'].any()
        np.testing.assert_allclose(c[ch], c[f'fg.{ch}'] + (1 - c['fg.A']) * c[f'bg.{ch}'],
                                   atol=2e-6)
    assert png.stat().st_size > 0


def test_render_command_reports_missing_scene(tmp_path):
    r = subprocess.run([sys.executable, '-m', 'mi_nerfpp', 'render', str(tmp_path / 'x.xml')],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and 'x.xml: scene file not found' in r.stderr
