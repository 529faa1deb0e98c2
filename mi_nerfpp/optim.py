"""The optimization core shared by training (:mod:`.train`) and the shape-radiance ambiguity
fit (:mod:`.ambiguity`): Adam (``drjit.opt``) over named parameters, learning rates by
parameter kind decaying exponentially over the run, and the colour losses.
"""
from __future__ import annotations

import drjit as dr

LR_GRID = 0.1      # learning rate of feature grids
LR_MLP = 5e-3      # learning rate of everything else (MLP weights and biases)
LR_FINAL = 0.1     # learning rates decay exponentially to this fraction of their start
ADAM_BETA2 = 0.999  # decay of Adam's second-moment estimate (drjit.opt's default)
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


def is_grid(name: str) -> bool:
    """Whether a parameter is a feature grid (``grid0``, ``fg.grid1``, ...), not an MLP array."""
    return name.rsplit('.', 1)[-1].startswith('grid')


# Arrays of at least this many entries take the sparse path of :class:`LazyAdam`.
SPARSE_ADAM_MIN_ENTRIES = 1 << 16


def adam(params: dict, lr: float = LR_MLP, lazy: bool = False, beta_2: float = ADAM_BETA2):
    """An Adam optimizer holding ``params`` (name -> array).

    ``lazy``: entries whose gradient is zero in a step are left alone, moments included
    (``mask_updates``, as instant-ngp does for its grids): a grid cell that no sample
    touched does not keep drifting on stale momentum; the large arrays (the grids) are then
    updated where the gradient is nonzero only (:class:`LazyAdam`). ``beta_2``: decay of the
    second-moment estimate (instant-ngp uses 0.99 for its sparsely touched grids).
    """
    opt = LazyAdam(lr=lr, beta_2=beta_2) if lazy else dr.opt.Adam(lr=lr, beta_2=beta_2)
    for k, v in params.items():
        opt[k] = v
    return opt


class LazyAdam(dr.opt.Adam):
    """``drjit.opt.Adam`` with ``mask_updates``, which reads and writes only the touched entries
    of large arrays.

    The masked update of ``drjit.opt.Adam`` still streams every entry of every array (the
    parameter, its gradient and both moments, read and written): for the feature grids, 17 M
    entries of which a step of 1,024 rays touches a few per cent, that pass was most of a step.
    Here an array of at least :data:`SPARSE_ADAM_MIN_ENTRIES` entries is updated through the
    indices of its nonzero gradient (``drjit.compress``, which a frozen step records): the
    gradient is read once, the rest only where it is nonzero. The arithmetic is Adam's own
    (``_step``) on the gathered entries, so the result equals the masked update's exactly;
    smaller arrays take that masked update.
    """

    def __init__(self, lr=LR_MLP, beta_2=ADAM_BETA2, **kwargs):
        super().__init__(lr=lr, beta_2=beta_2, mask_updates=True, **kwargs)

    def step(self, *, eval=True, grad_scale=None, active=None):
        if grad_scale is not None or active is not None:
            raise ValueError('LazyAdam takes no grad_scale or active mask')
        large = {k: entry for k, entry in self.state.items()
                 if dr.width(entry[0].array) >= SPARSE_ADAM_MIN_ENTRIES}
        for k in large:
            del self.state[k]
        try:
            super().step(eval=False)          # the small arrays, masked
        finally:
            cache = dr.opt._LRCache()
            updated = {k: self._sparse_step(cache, k, large) for k in list(large)}
            self.state.update(updated)
        if eval:
            dr.eval()

    def _sparse_step(self, cache, key, entries):
        """The update of array ``key``, taken out of ``entries`` first: its moments are then
        referenced here alone and are updated in place."""
        value, promoted, lr, extra = entries.pop(key)
        t_p, m, v, v_max = extra
        del extra
        if v_max is not None:
            raise ValueError('LazyAdam does not do AMSGrad')
        grad = value.grad.array
        Float = type(grad)
        touched = dr.compress(grad != 0)
        new_value, (t, m_i, v_i, _) = self._step(
            cache, dr.gather(Float, dr.detach(value).array, touched),
            dr.gather(Float, grad, touched), lr if lr is not None else self.lr,
            (t_p, dr.gather(Float, m, touched), dr.gather(Float, v, touched), None))
        flat = Float(dr.detach(value).array)
        dr.scatter(flat, new_value, touched)
        dr.scatter(m, m_i, touched)
        dr.scatter(v, v_i, touched)
        new = type(value)(flat, value.shape) if dr.is_tensor_v(value) else type(value)(flat)
        dr.enable_grad(new)
        state = (new, promoted, lr, (t, m, v, None))
        dr.schedule(state)
        return state


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


def mse(a, b):
    """Mean squared error of two ``Color3f`` batches, averaged over rays and channels."""
    return dr.mean(dr.square(a.x - b.x) + dr.square(a.y - b.y) + dr.square(a.z - b.z)) / 3.0


def charbonnier(a, b, eps: float = CHARBONNIER_EPS, weight: float = CHARBONNIER_WEIGHT):
    """mip-NeRF 360's robust colour loss: ``weight`` times the mean of ``sqrt((a - b)² + ε²)``
    over rays and channels of two ``Color3f`` batches. Like an absolute error, it weighs the
    large errors of a few pixels (a capture's Monte Carlo noise, specular glints) less than
    the squared error does."""
    c = dr.sqrt(dr.square(a - b) + eps * eps)
    return weight * dr.mean(c.x + c.y + c.z) / 3.0


COLOR_LOSSES = {'charbonnier': charbonnier, 'mse': mse}
COLOR_LOSS_NAMES = {'charbonnier': 'Charbonnier', 'mse': 'squared error'}   # for labels
