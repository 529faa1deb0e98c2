"""What a run can tell a user about their capture: the signs of what holds it back.

A real capture falls short of a clean one for reasons a user can act on: a view whose pose is
wrong, which is blurred or which has a person in it; photos whose exposure differs; content no
consistent scene explains. :class:`CaptureSigns` keeps, per training view, moving sums of the
training rays' squared error and of their predicted and photographed luminance (encoded, as
the loss compares them) over the last few thousand steps, and :meth:`CaptureSigns.summary`
turns them into figures (``metrics.json``'s ``capture_signs``) and :func:`sign_lines` into the
lines a run ends with:

- **views that fit far worse than the rest**: a view error at least :data:`OUTLIER` times the
  median view's (a wrong pose, a large transient, another lens, or content that is hard to
  fit); the :data:`NAMED` worst are checked for a wrong pose by fitting their cameras alone
  (:mod:`.pose_check`, ``pose_checks``) and named apart. Motion blur does not show:
  a blurred photo is smooth and fits as well as the rest (0.6-1.1x the median on the
  realistic stand-in), and the stand-in's passers-by (5-15 % of a photo) fit 1.0-1.7x;
- **exposure**: each view's brightness against the model's, in stops (a log2 ratio of linear
  light, from the encoded ratio through sRGB's exponent), in ``metrics.json`` only: the model
  absorbs most of an exposure difference into its view-dependent colour, so the figure is a
  lower bound (on the stand-in, 0.04 stops of spread for 0.23 applied, correlation 0.72), too
  weak a sign to advise on;
- **what no consistent scene explains**: with an error map, the share of the training pixels in
  tiles whose error stays above :data:`~mi_nerfpp.training.error_map.CAP` times their image's
  median (transients, glints, misregistration).

docs/training.md ("What the end of a run tells you about the capture") explains each to a user.
"""
from __future__ import annotations

import numpy as np

from mi_nerfpp.training.error_map import CAP

# The weight a step's sums keep at the next step: the signs describe the last ~1,000 steps.
DECAY = 0.999
# A view is an outlier from this many times the median view's mean squared error.
OUTLIER = 3.0
# sRGB's encoded ratio to linear ratio: linear ~ encoded^2.2.
SRGB_EXPONENT = 2.2
# The views named in a line, at most.
NAMED = 8


class CaptureSigns:
    """Per-view moving sums of a run's training rays (see the module docstring)."""

    def __init__(self, views: int):
        self.sums = np.zeros((int(views), 4))       # weight, squared error, predicted Y, photo Y

    def update(self, images: np.ndarray, squared_error, predicted, photographed):
        """Fold one batch in: per ray its training view, squared error and luminances."""
        n = len(self.sums)
        images = np.asarray(images, np.int64)
        self.sums *= DECAY
        for column, values in enumerate((None, squared_error, predicted, photographed)):
            weights = None if values is None else np.asarray(values, np.float64)
            self.sums[:, column] += np.bincount(images, weights=weights, minlength=n)[:n]

    def summary(self, names=None, error_map=None) -> dict:
        """The figures of the signs: per view its error relative to the median view and its
        exposure in stops against the model; the outliers; the spread; the unexplained
        share (with ``error_map``)."""
        seen = self.sums[:, 0] > 0
        if not seen.any():
            return {}
        weight = np.where(seen, self.sums[:, 0], 1.0)
        error = self.sums[:, 1] / weight
        relative = error / max(float(np.median(error[seen])), 1e-12)
        ratio = np.maximum(self.sums[:, 3], 1e-9) / np.maximum(self.sums[:, 2], 1e-9)
        stops = SRGB_EXPONENT * np.log2(ratio)
        names = list(names) if names is not None else [str(i) for i in range(len(error))]
        outliers = [int(i) for i in np.argsort(-relative) if seen[i] and relative[i] >= OUTLIER]
        out = {
            'views': [{'name': names[i], 'relative_error': round(float(relative[i]), 3),
                       'stops': round(float(stops[i]), 3)} for i in range(len(error))],
            'outliers': [names[i] for i in outliers],
            'exposure_spread_stops': round(float(np.std(stops[seen])), 3),
        }
        if error_map is not None and error_map.visited.any():
            out['unexplained_share'] = round(error_map.unexplained_share(), 4)
        return out

    def state(self) -> dict:
        return {'capture_signs': self.sums.copy()}

    def restore(self, state: dict):
        stored = state.get('capture_signs')
        if stored is not None and np.shape(stored) == self.sums.shape:
            self.sums[:] = np.asarray(stored, np.float64)


def sign_lines(signs: dict) -> list[str]:
    """The lines a run ends with about its capture (empty when nothing stands out)."""
    lines = []
    if not signs:
        return lines
    views = {v['name']: v for v in signs['views']}
    checks = signs.get('pose_checks')
    if checks is None:              # (runs from before the pose check)
        if signs['outliers']:
            lines.append(f'training views that fit far worse than the median view: '
                         f'{_named(signs["outliers"], views)}; a wrong pose (--refine-poses) '
                         f'or a large passer-by: look at them (docs/training.md)')
    else:
        wrong = [n for n in signs['outliers'] if n in checks and checks[n]['wrong_pose']]
        other = [n for n in signs['outliers'] if n in checks and n not in wrong]
        unchecked = [n for n in signs['outliers'] if n not in checks]
        if wrong:
            lines.append('training views whose pose looks wrong (each fits far worse than the '
                         'median view, and its camera fitted alone against the model turns by '
                         'the degrees given and keeps the share of its error given): '
                         + _named(wrong, views, checks)
                         + ('; wrong beyond what the run refined: leave them out, or run '
                            'structure from motion again (docs/training.md)'
                            if signs.get('poses_refined') else
                            '; --refine-poses, or leave them out (docs/training.md)'))
        if other:
            lines.append('training views that fit far worse than the median view, though not '
                         'for their pose (their cameras fitted alone keep most of their error): '
                         + _named(other, views)
                         + '; content the other photos do not explain (a passer-by: '
                         '--transients) or that is hard to fit: look at them (docs/training.md)')
        if unchecked:           # (beyond the NAMED worst, which alone are checked)
            lines.append(f'training views that fit far worse than the median view, their poses '
                         f'not checked (only the {NAMED} worst are): {_named(unchecked, views)}')
    share = signs.get('unexplained_share')
    if share is not None and share >= 0.01:
        lines.append(f'{100 * share:.1f} % of the training pixels fit more than {CAP:g}x worse '
                     f'than their photo\'s median: what no consistent scene explains '
                     f'(passers-by, glints, misregistered edges)')
    return lines


def _named(names, views, checks=None) -> str:
    """``name (5.3x), ...`` for at most :data:`NAMED` views (with ``checks``: ``name (5.3x,
    0.8°, 35 %)``), and how many more."""
    parts = []
    for name in names[:NAMED]:
        text = f'{views[name]["relative_error"]:.1f}x'
        if checks is not None:
            c = checks[name]
            text += f', {c["turn_degrees"]:.2f}°, {100 * c["error_kept"]:.0f} %'
        parts.append(f'{name} ({text})')
    more = len(names) - NAMED
    return ', '.join(parts) + (f' and {more} more' if more > 0 else '')
