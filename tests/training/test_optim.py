"""Colour losses (mi_nerfpp.training.optim): values against hand computation, gradients against central
finite differences, and the training option that picks one."""
from __future__ import annotations

import numpy as np
import pytest

import mi_nerfpp  # noqa: F401
import drjit as dr
import mitsuba as mi

from mi_nerfpp.training import optim
from mi_nerfpp.training.config import TrainConfig

PRED = np.array([[0.2, 0.5, 0.9, 0.31], [0.0, 0.25, 0.7, 0.6], [1.0, 0.4, 0.1, 0.3]])
GT = np.array([[0.25, 0.5, 0.3, 0.3], [0.1, 0.2, 0.7, 0.0], [0.9, 0.45, 0.15, 0.31]])


def color(a):
    return mi.Color3f(*[mi.Float(np.asarray(c, np.float32)) for c in a])


def loss_value(f, pred):
    return f(color(pred), color(GT)).array[0]


def test_charbonnier_value():
    eps, w = optim.CHARBONNIER_EPS, optim.CHARBONNIER_WEIGHT
    expected = w * np.mean(np.sqrt((PRED - GT) ** 2 + eps ** 2))
    assert loss_value(optim.charbonnier, PRED) == pytest.approx(expected, rel=1e-5)
    # Equal images cost w·ε, the floor of the loss.
    assert loss_value(optim.charbonnier, GT) == pytest.approx(w * eps, rel=1e-5)
    assert loss_value(optim.mse, PRED) == pytest.approx(np.mean((PRED - GT) ** 2), rel=1e-5)


@pytest.mark.parametrize('name', sorted(optim.COLOR_LOSSES))
def test_color_loss_gradient_matches_finite_differences(name):
    f = optim.COLOR_LOSSES[name]
    x = [mi.Float(np.asarray(c, np.float32)) for c in PRED]
    dr.enable_grad(x)
    dr.backward(f(mi.Color3f(*x), color(GT)))
    grad = np.array([np.array(dr.grad(c)) for c in x])
    h = 1e-3
    fd = np.zeros_like(PRED)
    for idx in np.ndindex(PRED.shape):
        hi, lo = PRED.copy(), PRED.copy()
        hi[idx] += h
        lo[idx] -= h
        fd[idx] = (loss_value(f, hi) - loss_value(f, lo)) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=2e-2, atol=2e-4)


def test_charbonnier_weighs_large_errors_less_than_the_squared_error():
    """Its gradient is bounded by w/n per entry: an error of 0.6 pulls no harder than one of 0.05,
    where the squared error pulls twelve times harder."""
    n = PRED.size
    x = [mi.Float(np.asarray(c, np.float32)) for c in PRED]
    dr.enable_grad(x)
    dr.backward(optim.charbonnier(mi.Color3f(*x), color(GT)))
    grad = np.abs(np.array([np.array(dr.grad(c)) for c in x]))
    assert grad.max() <= optim.CHARBONNIER_WEIGHT / n * (1 + 1e-5)
    big, small = (0, 2), (0, 0)      # errors 0.6 and 0.05
    assert grad[big] == pytest.approx(grad[small], rel=2e-3)


def test_unknown_color_loss_is_rejected():
    with pytest.raises(ValueError, match="--color-loss must be 'charbonnier' or 'mse', got l1"):
        TrainConfig.from_options(color_loss='l1')
    assert TrainConfig().losses.color_loss == 'charbonnier'


def test_adam_matches_drjit_adam_and_fuses_the_updates():
    """optim.Adam takes the steps of drjit.opt.Adam (learning rates as opaque arrays, as in
    training): the background's grids with a first-moment decay of
    optim.BACKGROUND_GRID_BETA1 (none stored), the foreground's grids and the MLPs with Adam's
    own; and it evaluates the updates of all parameters of one size in one kernel."""
    rng = np.random.default_rng(0)
    start = {'bg.grid0': rng.normal(size=(4, 4, 4, 2)).astype(np.float32),
             'fg.grid0': rng.normal(size=(4, 4, 4, 2)).astype(np.float32),
             'w': rng.normal(size=96).astype(np.float32)}
    ours = optim.adam({k: mi.TensorXf(v) if v.ndim > 1 else mi.Float(v) for k, v in start.items()})
    theirs = {'bg': dr.opt.Adam(lr=optim.LR_MLP, beta_1=optim.BACKGROUND_GRID_BETA1,
                                beta_2=optim.ADAM_BETA2),
              'rest': dr.opt.Adam(lr=optim.LR_MLP, beta_2=optim.ADAM_BETA2)}

    def holder(k):
        return theirs['bg' if k.startswith('bg.') else 'rest']
    for k, v in start.items():
        holder(k)[k] = mi.TensorXf(v) if v.ndim > 1 else mi.Float(v)
    assert type(ours) is optim.Adam and isinstance(ours, dr.opt.Adam)
    assert optim.BACKGROUND_GRID_BETA1 == 0.0 and optim.without_momentum('bg.sparse0')
    assert not optim.without_momentum('fg.grid1') and not optim.without_momentum('bg.color.w0')
    for it in range(5):
        for opts in ([ours], list(theirs.values())):
            for opt in opts:
                optim.set_learning_rates(opt, it / 5)
            get = (lambda k: ours[k]) if opts[0] is ours else (lambda k: holder(k)[k])
            x = get('bg.grid0').array
            loss = (dr.sum(dr.square(x - 0.3) * dr.select((dr.arange(mi.UInt32, dr.width(x)) + it) % 3 == 0,
                                                        0.0, 1.0))
                    + dr.sum(dr.exp(get('fg.grid0').array) * 0.1) + dr.sum(dr.sin(get('w'))))
            dr.backward(loss)
            if opts[0] is ours:
                with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
                    dr.eval()
                    dr.kernel_history_clear()
                    ours.step(eval=False)
                    dr.eval()
                    sizes = [k['size'] for k in dr.kernel_history() if k.get('size', 0) > 1]
                assert sorted(sizes) == [96, 128], sizes     # the two grids in one kernel
            else:
                for opt in opts:
                    opt.step()
        for k in start:
            np.testing.assert_allclose(np.array(ours[k]), np.array(holder(k)[k]), rtol=1e-5,
                                       atol=1e-6)
    # The background's grid stores no first moment (a one-entry placeholder), the others theirs.
    widths = {k: dr.width(ours.state[k][3][1]) for k in start}
    assert widths == {'bg.grid0': 1, 'fg.grid0': 128, 'w': 96}


def test_a_checkpoint_whose_grids_kept_a_first_moment_resumes_without_it():
    """Adam state saved by a version whose background grids kept a first moment: restored, they
    drop it for the placeholder (their steps take none from here on), the MLP keeps its own; a new
    checkpoint stores the placeholder and restores to the same steps."""
    rng = np.random.default_rng(1)
    params = {'bg.grid0': rng.normal(size=(2, 2, 2, 2)).astype(np.float32),
              'w': rng.normal(size=8).astype(np.float32)}
    old = {}
    for k, v in params.items():
        old[f'adam.t/{k}'] = np.array([5], np.uint32)
        old[f'adam.m/{k}'] = rng.normal(size=v.size).astype(np.float32)
        old[f'adam.v/{k}'] = rng.uniform(1, 2, size=v.size).astype(np.float32)
    opt = optim.adam({k: mi.TensorXf(v) if v.ndim > 1 else mi.Float(v) for k, v in params.items()})
    optim.restore_adam(opt, old)
    t, m, v, _ = opt.state['bg.grid0'][3]
    assert dr.width(m) == 1 and np.array_equal(v.numpy(), old['adam.v/bg.grid0'])
    assert t.numpy().tolist() == [5]
    np.testing.assert_array_equal(opt.state['w'][3][1].numpy(), old['adam.m/w'])
    saved = optim.adam_state(opt)
    assert saved['adam.m/bg.grid0'].size == 1 and saved['adam.m/w'].size == 8
    again = optim.adam({k: mi.TensorXf(v) if v.ndim > 1 else mi.Float(v) for k, v in params.items()})
    optim.restore_adam(again, saved)
    for o in (opt, again):
        dr.backward(dr.sum(dr.square(o['bg.grid0'].array)) + dr.sum(o['w']))
        o.step()
    for k in params:
        np.testing.assert_array_equal(np.array(opt[k]), np.array(again[k]))
