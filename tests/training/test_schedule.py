"""The background's sparse bricks (:mod:`mi_nerfpp.training.schedule`): chosen where the
training rays take their colour from, in closed form on analytic fields, and end to end by
default alongside the foreground's."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_nerfpp.core.model import NeRFPPModel
from mi_nerfpp.core.render import Sampling
from mi_nerfpp.data import load_dataset
from mi_nerfpp.training.raybank import RayBank
from mi_nerfpp.training.schedule import BACKGROUND_SHARE, background_shares
from tests.helpers import AnalyticField

BLOCKS = (16, 8, 16)        # (s, colatitude, longitude)
SHELL = (0.5, 0.5625)       # the ninth slab of bricks along s


def shell(sigma):
    """An opaque shell of the background over ``SHELL`` in s, empty elsewhere."""
    return AnalyticField(lambda x: dr.select((x[3] >= SHELL[0]) & (x[3] < SHELL[1]), sigma, 0.0),
                         (0.5, 0.5, 0.5))


def shares(capture, fg_sigma, n_rays=4096):
    model = NeRFPPModel(AnalyticField(fg_sigma, (0.2, 0.2, 0.2)), shell(1e4),
                        color_space='linear', sampling=Sampling(16, 64, 32))
    return background_shares(model, RayBank(load_dataset(capture).train), BLOCKS, seed=3,
                             n_rays=n_rays)


def test_the_background_bricks_are_where_the_rays_take_their_colour(capture):
    """Behind an empty foreground every ray ends in the shell's front slab, where its first
    sample in the shell takes all of its colour: a brick there has a share near 1 where such a
    sample falls and near 0 where only the samples behind it do (a ray's direction in the
    inverted sphere turns with s), every other brick none; the bricks wanted are the first."""
    share = shares(capture, 0.0)
    slab = int(SHELL[0] * BLOCKS[0])
    front, rest = share[slab], np.delete(share, slab, axis=0)
    assert rest.max() < 1e-3
    hit = front > 0.9
    assert 0 < hit.sum() < front.size               # the directions the cameras look in
    assert (hit | (front < 0.01)).all()
    wanted = share >= BACKGROUND_SHARE
    assert np.array_equal(wanted[slab], hit) and not np.delete(wanted, slab, axis=0).any()


def test_a_foreground_takes_its_share_of_the_colour(capture):
    """Behind a foreground of opacity ``1 - exp(-σ·chord)`` the background's share is what it
    lets through: a denser foreground leaves every brick less, none more."""
    slab = int(SHELL[0] * BLOCKS[0])
    clear, thin, opaque = (shares(capture, sigma)[slab] for sigma in (0.0, 0.3, 1e4))
    reached = clear > 0
    assert (thin <= clear + 1e-6).all() and (opaque <= thin + 1e-6).all()
    assert thin[reached].sum() < 0.9 * clear[reached].sum()
    assert opaque[reached].sum() < 0.9 * thin[reached].sum()


def test_a_background_level_the_rays_do_not_need_is_emptied_and_training_goes_on(
        capture, tmp_path, monkeypatch, capsys):
    """Where no sample takes its share (here a threshold no share reaches), the level keeps no
    brick: its lookups read 0, the run trains on and its checkpoint loads."""
    from mi_nerfpp.commands.cli import main
    from mi_nerfpp.files.checkpoint import load_checkpoint
    from mi_nerfpp.training import schedule
    monkeypatch.setattr(schedule, 'BACKGROUND_SHARE', 2.0)
    out = tmp_path / 'run'
    assert main(['optimize', capture, '--out', str(out), '--iterations', '12', '--batch-rays',
                 '64', '--samples', '4', '4', '4', '--grid-levels', '8', '--occupancy-res',
                 '16', '--grid-sparse', '--bg-grid-sparse', '16', '--sparse-at', '0', '0.5',
                 '--preview-every', '0', '--checkpoint-every', '0']) == 0
    model, meta, _ = load_checkpoint(out / 'model.npz')
    assert model.allocated_bricks()['bg.sparse0'].size == 0 and meta['iteration'] == 12
    assert ('sparse level bg.sparse0: 0 bricks (0.0 M entries) where the training rays take '
            'their colour from, of 512') in capsys.readouterr().out
