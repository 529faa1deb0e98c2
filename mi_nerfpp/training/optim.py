"""The optimization core shared by training (:mod:`.train`) and the shape-radiance ambiguity
fit (:mod:`.ambiguity`): Adam (``drjit.opt``) over named parameters, learning rates by
parameter kind decaying exponentially over the run, and the colour losses.
"""
from __future__ import annotations

import contextlib

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_nerfpp.core.arrays import owned

LR_GRID = 0.1      # learning rate of feature grids
LR_MLP = 5e-3      # learning rate of everything else (MLP weights and biases)
LR_FINAL = 0.1     # learning rates decay exponentially to this fraction of their start
ADAM_BETA2 = 0.999  # decay of Adam's second-moment estimate (drjit.opt's default)
# Decay of Adam's first moment for the background's feature grids (:func:`without_momentum`):
# none, so such a grid's step is its gradient over the root of its second moment, debiased as
# Adam's (RMSProp with Adam's bias correction), and no first moment is stored. A step's samples
# touch 4 % of the background's 128 level (8.4 M entries), the largest array Adam streams;
# without momentum Adam reads and writes five of its arrays instead of seven. Default capture,
# 5,000 steps, seeds 0 / 1: 27.06 / 27.08 dB held out against 27.18 / 26.96 with it. The
# foreground's grids keep Adam's β₁: without it the tests' 600-step run of a 32×24 capture
# textured its proxy 1.4-2.6 dB above flat grey instead of 4.5-5.3 (three runs each;
# docs/experiments.md).
BACKGROUND_GRID_BETA1 = 0.0
CHARBONNIER_EPS = 1e-3   # the Charbonnier loss's ε (mip-NeRF 360's)
# The Charbonnier loss's weight: the priors' weights (sparsity, distortion) were tuned against
# the squared error, whose gradient is ~10x smaller at typical errors. Measured at 1,500 steps
# on the default capture: weight 1 leaves the priors too weak (floaters, soft mattes), 0.08
# makes them too strong (the foreground paints the distance), 0.3 keeps the mattes.
CHARBONNIER_WEIGHT = 0.3
# The colour loss's weight in a training step, against the priors (distortion, sparsity): they
# were tuned when the loss had two colour terms, of the coarse and the fine composite; the coarse
# pass now only places samples and the one term of the image weighs 3 (on the default capture,
# 2,800 steps of 1,024 rays: weights 1 / 2 / 3 / 4 gave 23.5 / 26.3 / 26.8 / 26.5 dB held out).
COLOR_LOSS_WEIGHT = 3.0
# The weight of the silhouette loss (--masks object) beside the colour loss.
SILHOUETTE_WEIGHT = 0.1


@contextlib.contextmanager
def colour_weights_attached(model):
    """Inside the block, ``model``'s colour networks' weights take gradients (they are never
    updated). A fit of something else through the fields (a held-out photo's code, a camera)
    needs it: Dr.Jit 1.5.0 aborts ("jit_assemble(): dirty variable") evaluating a gradient that
    reached the colour networks' ray inputs through their matrix products unless their weights
    take gradients too."""
    colour = {k: dr.detach(v) for k, v in model.parameters().items() if '.color.' in k}
    for v in colour.values():
        dr.enable_grad(v)
    model.set_parameters(colour)
    try:
        yield
    finally:
        model.set_parameters({k: dr.detach(v) for k, v in colour.items()})


def without_momentum(name: str) -> bool:
    """Whether parameter ``name`` learns without Adam's first moment
    (:data:`BACKGROUND_GRID_BETA1`): the background's grids (``bg.grid1``, ``bg.sparse0``, ...)."""
    return name.startswith('bg.') and is_grid(name)


def is_grid(name: str) -> bool:
    """Whether a parameter is a feature grid (a dense level ``grid0``, ``fg.grid1``, ..., a
    plane of a plane level, ``fg.plane0xy``, ..., or the bricks of a sparse level,
    ``fg.sparse0``), not an MLP array: it learns at the grids' rate."""
    return name.rsplit('.', 1)[-1].startswith(('grid', 'plane', 'sparse'))


class Adam(dr.opt.Adam):
    """``drjit.opt.Adam`` whose step schedules every parameter's update before evaluating any,
    with a first-moment decay of its own for the parameters that ``momentless(key)`` names
    (:data:`BACKGROUND_GRID_BETA1`, 0: no first moment stored, a one-entry placeholder in its
    place).

    Dr.Jit's step makes each parameter's step size (learning rate times the debiasing factor)
    opaque as it reaches the parameter, and evaluating it evaluates everything scheduled so far:
    the update of the parameter before. Each parameter's update was then a kernel of its own,
    and a check that reads the new values (:func:`mi_nerfpp.training.train.flag_non_finite`) one more
    pass over them. Here the step sizes of all parameters are evaluated first, together; the
    updates (the same arithmetic as Dr.Jit's Adam) are then evaluated by the caller's next
    ``dr.eval()``, one kernel per array size, with whatever else reads them fused in."""

    def __init__(self, lr, *, momentless=None, **kwargs):
        self.momentless = momentless or (lambda key: False)
        super().__init__(lr, **kwargs)

    def beta_1_of(self, key) -> float:
        return BACKGROUND_GRID_BETA1 if self.momentless(key) else self.beta_1

    def _reset(self, key, value, promoted):
        super()._reset(key, value, promoted)
        if not self.beta_1_of(key):
            self.state[key] = without_first_moment(self.state[key])

    def step(self, *, eval=True, grad_scale=None, active=None):
        if self.amsgrad or self.uniform:        # (variants not used here: Dr.Jit's own step)
            return super().step(eval=eval, grad_scale=grad_scale, active=active)
        scales, betas = [], []
        for key, (value, _, lr, extra) in self.state.items():
            t = extra[0] + 1
            beta_1 = self.beta_1_of(key)
            Base = dr.leaf_t(dr.detach(value).array)
            High = dr.float64_array_t(Base)
            debias = Base(-dr.sqrt(1 - High(self.beta_2) ** t) / (1 - High(beta_1) ** t))
            scales.append(debias * (lr if lr is not None else self.lr))
            betas.append(beta_1)
        dr.eval(scales)
        # Read by _step, parameter by parameter in this order.
        self._scales, self._betas = iter(scales), iter(betas)
        try:
            super().step(eval=eval, grad_scale=grad_scale, active=active)
        finally:
            del self._scales, self._betas

    def _step(self, cache, value, grad, lr, extra):
        if self.amsgrad or self.uniform:
            return super()._step(cache, value, grad, lr, extra)
        t_p, m_p, v_p, v_max_p = extra
        beta_1 = next(self._betas)
        m_t = dr.lerp(grad, m_p, beta_1) if beta_1 else grad
        v_t = dr.lerp(dr.square(grad), v_p, self.beta_2)
        if self.epsilon <= 1e-6:
            step = m_t * dr.rsqrt(v_t + self.epsilon ** 2)
        else:
            step = m_t / (dr.sqrt(v_t) + self.epsilon)
        # (Without a first moment its placeholder stays: nothing is stored.)
        return dr.fma(step, next(self._scales), value), (t_p + 1, m_t if beta_1 else m_p,
                                                         v_t, v_max_p)


def without_first_moment(state):
    """An Adam ``state`` entry ``(value, promoted, lr, (t, m, v, v_max))`` whose first moment is
    a one-entry placeholder (a parameter of :data:`BACKGROUND_GRID_BETA1` 0 keeps none)."""
    value, promoted, lr, (t, m, v, v_max) = state
    return value, promoted, lr, (t, dr.zeros(type(m), 1), v, v_max)


def adam(params: dict, lr: float = LR_MLP, beta_2: float = ADAM_BETA2):
    """An Adam optimizer holding ``params`` (name -> array), the background's grids without a
    first moment (:func:`without_momentum`); ``beta_2``: decay of the second-moment estimate
    (instant-ngp uses 0.99 for its sparsely touched grids)."""
    opt = Adam(lr=lr, beta_2=beta_2, momentless=without_momentum)
    for k, v in params.items():
        opt[k] = v
    return opt


def write_back(opt, model, detach: bool = True):
    """The one place where the parameters that ``opt`` owns reach the ``model``'s fields:
    detached for renders, refreshes and checkpoints; attached (``detach=False``) inside a
    step, so that the loss differentiates them."""
    model.set_parameters({k: dr.detach(opt[k]) if detach else opt[k] for k in opt.keys()})


def adam_state(opt) -> dict:
    """The Adam state of ``opt`` as NumPy arrays (``adam.t/<name>``, ``adam.m/<name>``,
    ``adam.v/<name>``), for a checkpoint."""
    state = {}
    for k, (_, _, _, (t, m, v, _)) in opt.state.items():
        state[f'adam.t/{k}'] = np.array(t, dtype=np.uint32)
        state[f'adam.m/{k}'] = np.array(m, dtype=np.float32)
        state[f'adam.v/{k}'] = np.array(v, dtype=np.float32)
    return state


def restore_adam(opt, state: dict):
    """Give ``opt`` the Adam state of :func:`adam_state` for each parameter that has one."""
    # drjit.opt.Adam keeps (value, promoted, lr, (t, m, v, v_max)) per key (drjit 1.5).
    for k in list(opt.keys()):
        if f'adam.m/{k}' not in state:
            continue
        value, promoted, lr, _ = opt.state[k]
        # Owned copies: the first frozen step releases them (see :mod:`..core.arrays`).
        opt.state[k] = (value, promoted, lr,
                        (dr.opaque(mi.UInt32, int(np.ravel(state[f'adam.t/{k}'])[0])),
                         owned(state[f'adam.m/{k}'], mi.Float),
                         owned(state[f'adam.v/{k}'], mi.Float), None))
        if not opt.beta_1_of(k):    # (a checkpoint of a version whose grids kept one)
            opt.state[k] = without_first_moment(opt.state[k])


def set_learning_rates(opt, progress: float, lr_grid: float = LR_GRID, lr_mlp: float = LR_MLP,
                       lr_final: float = LR_FINAL, by_name: dict | None = None) -> None:
    """Grid or MLP rate by name (``by_name``: the rate of particular parameters), times
    ``lr_final ** progress`` (progress clamped to [0, 1]).

    The rates are opaque arrays, not Python floats: a frozen training step
    (:func:`drjit.freeze`) reads them as inputs, so it sees each step's rate instead of the
    one it was recorded with, and no kernel is compiled per rate."""
    decay = lr_final ** min(max(progress, 0.0), 1.0)
    by_name = by_name or {}
    opt.set_learning_rate({k: dr.opaque(dr.leaf_t(opt[k]),
                                        by_name.get(k, lr_grid if is_grid(k) else lr_mlp) * decay)
                           for k in opt.keys()})


def squared_error(a, b):
    """Per ray, the squared error of two ``Color3f`` batches averaged over the channels."""
    return (dr.square(a.x - b.x) + dr.square(a.y - b.y) + dr.square(a.z - b.z)) / 3.0


def luminance(c):
    """Per ray, the Rec. 709 luminance of a ``Color3f`` batch (in its own encoding)."""
    return 0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z


def ray_mean(values, kept=None):
    """The mean of per-ray ``values``; with ``kept`` (a weight per ray in [0, 1], a mask's
    coverage), the mean over the kept rays, ``Σ kept·v / Σ kept``, so that a kept pixel
    weighs as much as without masks."""
    if kept is None:
        return dr.mean(values)
    return dr.sum(kept * values) / dr.maximum(dr.sum(kept), 1.0)


def mse(a, b, kept=None):
    """Mean squared error of two ``Color3f`` batches, averaged over (the ``kept``, see
    :func:`ray_mean`) rays and channels."""
    return ray_mean(squared_error(a, b), kept)


def charbonnier(a, b, kept=None, eps: float = CHARBONNIER_EPS,
                weight: float = CHARBONNIER_WEIGHT):
    """mip-NeRF 360's robust colour loss: ``weight`` times the mean of ``sqrt((a - b)² + ε²)``
    over (the ``kept``, see :func:`ray_mean`) rays and channels of two ``Color3f`` batches.
    Like an absolute error, it weighs the large errors of a few pixels (a capture's Monte
    Carlo noise, specular glints) less than the squared error does."""
    c = dr.sqrt(dr.square(a - b) + eps * eps)
    return weight * ray_mean(c.x + c.y + c.z, kept) / 3.0


def silhouette_loss(opacity, mask):
    """The squared error of each ray's foreground opacity against its object mask's coverage
    (``--masks object``), averaged over the rays."""
    return dr.mean(dr.square(opacity - mask))


COLOR_LOSSES = {'charbonnier': charbonnier, 'mse': mse}
COLOR_LOSS_NAMES = {'charbonnier': 'Charbonnier', 'mse': 'squared error'}   # for labels
