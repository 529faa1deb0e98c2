"""The layer table (mi_nerfpp.core.layers): one definition that the integrator, the readers of a
render, the EXR writer and the docs all follow."""
from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.files import exr
from mi_nerfpp.core import layers
from mi_nerfpp.integrator import NeRFPPIntegrator
from mi_nerfpp.output.views import render_layers
from tests.helpers import scene_dict, tiny_model


def test_channels_follow_the_table():
    assert layers.BEAUTY == ('R', 'G', 'B', 'A')
    assert layers.LAYERS[:4] == layers.BEAUTY
    assert [l.name for l in layers.LAYER_TABLE] == ['', 'fg', 'bg', 'depth', 'distance', 'obj',
                                                    'obj_depth', 'shadow']
    assert layers.LAYERS_BY_NAME['obj'].channels == ('obj.R', 'obj.G', 'obj.B', 'obj.A')
    assert layers.LAYERS_BY_NAME['obj_depth'].full_precision == ('obj_depth.Z',)
    assert layers.FULL_PRECISION_CHANNELS == {'depth.Z', 'distance.Y', 'obj_depth.Z'}
    assert len(set(layers.LAYERS)) == len(layers.LAYERS)
    # Nuke and Blender take at most four channels per layer (issue 35).
    assert max(len(l.channels) for l in layers.LAYER_TABLE) == 4
    # The sample channels: plain layers by their own names, weighted ones by <name>_w, and
    # the beauty's alpha.
    assert layers.AOVS == ('fg.R', 'fg.G', 'fg.B', 'fg.A', 'bg_w.R', 'bg_w.G', 'bg_w.B',
                           'depth.Z', 'distance.Y', 'obj.R', 'obj.G', 'obj.B', 'obj.A',
                           'obj_depth_w.Z', 'shadow.R', 'shadow.G', 'shadow.B', 'alpha.A')


def test_integrator_reports_the_table_and_renders_every_channel():
    scene = mi.load_dict(scene_dict())
    scene.integrator().set_model(tiny_model())
    assert scene.integrator().aov_names() == list(layers.AOVS)
    image = np.array(mi.render(scene))
    assert image.shape[2] == 4 + len(layers.AOVS)


def test_layer_channels_and_aov_list():
    values = layers.layer_channels(fg=(1, 2, 3, 4), depth=(5,))
    assert values == {'fg.R': 1, 'fg.G': 2, 'fg.B': 3, 'fg.A': 4, 'depth.Z': 5}
    ordered = layers.aov_list(values, missing=lambda: 0)
    assert ordered == [1, 2, 3, 4, 0, 0, 0, 5] + [0] * (len(layers.AOVS) - 8)
    # A weighted layer's values are its premultiplied samples.
    assert layers.layer_channels(bg=(1, 2, 3), A=(0.5,)) == {
        'bg_w.R': 1, 'bg_w.G': 2, 'bg_w.B': 3, 'alpha.A': 0.5}
    with pytest.raises(ValueError, match="layer 'fg' has 4 channels"):
        layers.layer_channels(fg=(1, 2, 3))
    with pytest.raises(ValueError, match="unknown layer 'alpha'"):
        layers.layer_channels(alpha=(1,))
    with pytest.raises(ValueError, match='not AOV channels: R'):
        layers.aov_list({'R': 1}, missing=lambda: 0)


class _Reordered:
    """An integrator stand-in whose AOVs come in another order."""
    background = True

    def __init__(self, names):
        self.names = names

    def aov_names(self):
        return self.names


def test_render_layers_reads_channels_by_name():
    h, w = 2, 3
    names = list(reversed(layers.AOVS))
    image = np.random.default_rng(0).uniform(size=(h, w, 3 + len(names))).astype(np.float32)
    out = render_layers(image, _Reordered(names))
    assert tuple(out) == layers.LAYERS
    for i, name in enumerate(names):
        if name in layers.LAYERS:       # the plain layers: the film's averages as they are
            np.testing.assert_array_equal(out[name], image[..., 3 + i])
    np.testing.assert_array_equal(out['A'], image[..., 3 + names.index('alpha.A')])
    # The weighted layers: ratios of averages.
    bg = image[..., 3 + names.index('bg_w.R')] / (1 - out['fg.A'] + 1e-6)
    np.testing.assert_allclose(out['bg.R'], bg, rtol=1e-6)
    np.testing.assert_allclose(out['obj_depth.Z'], image[..., 3 + names.index('obj_depth_w.Z')]
                               / out['obj.A'], rtol=1e-6)
    with pytest.raises(ValueError, match='pixel_format'):
        render_layers(image[..., 1:], _Reordered(names))


def test_docs_are_made_from_the_table():
    for doc in (exr.__doc__, NeRFPPIntegrator.__doc__):
        assert '{layer_table}' not in doc
        for layer in layers.LAYER_TABLE:
            # The content's first words and every channel name appear in the table.
            assert ' '.join(layer.content.split()[:4]) in ' '.join(doc.split())
    table = layers.rst_table()
    for channel in layers.LAYERS:
        assert channel in table
    assert table.count('always float32') == 3
