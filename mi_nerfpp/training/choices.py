"""What a run's options leave to the capture, chosen in one place and announced from there: the
sparse foreground level, where the rays are drawn, whether each photo learns its exposure and
its camera's pose, what the photos' masks mean and the time budget (:func:`from_capture`). A
resumed run keeps what it chose before.

The resolution (``--downscale``) is chosen with the dataset's loading
(:func:`mi_nerfpp.jobs.run.prepare`): it decides which images are read at all.
"""
from __future__ import annotations

import os

import numpy as np

from mi_nerfpp.core import budget
from mi_nerfpp.core import occupancy as occ
from mi_nerfpp.data import DatasetError, masks
from mi_nerfpp.data.synth.capture import CAPTURE_FILE
from mi_nerfpp.training.config import TrainConfig, default_minutes

# What each meaning of the masks does, as the announcement says it.
MASK_MEANINGS = {'ignore': 'their black pixels are left out of the colour loss',
                 'object': "their white pixels are the object's silhouette, which the "
                           "foreground's opacity is fitted to",
                 'none': 'not used'}


def _quiet(line):
    pass


def from_capture(config: TrainConfig, dataset, stored: dict | None = None, notice=_quiet,
                 sparse: bool = True) -> TrainConfig:
    """``config`` with every option it leaves to the capture chosen: the sparse foreground
    level (with ``sparse``; :func:`choose_sparse_level`), the share of rays drawn by the error
    map (:func:`choose_error_rays`), the per-photo colour transforms and pose corrections
    (:func:`choose_for_photos`), the meaning of the masks (:func:`choose_masks`) and the
    budget (:func:`choose_budget`). ``stored``: the config of the checkpoint a run resumes
    (its choices are kept); ``notice(line)`` receives each announcement."""
    stored = stored or {}
    if sparse and config.model.grid_sparse is None:
        config = choose_sparse_level(config, dataset, stored, notice)
    if config.model.bg_grid_sparse is None:     # none chosen: none, or a resumed run's own
                                                # (older runs: none, their background dense)
        options = TrainConfig.stored_options(stored) if stored else {}
        config = config.replace(bg_grid_sparse=tuple(options.get('bg_grid_sparse') or ()))
    config = keep_sparse_schedule(config, stored)
    config = choose_error_rays(config, stored)
    config = choose_for_photos(config, dataset, stored, notice)
    config = choose_masks(config, dataset, stored, notice)
    return choose_budget(config, dataset, notice)


def centre_footprint(cameras) -> float:
    """The median width of a training pixel at the scene's centre, in the dataset's frame (the
    unit ball's units): each camera's distance to the origin over its focal length in pixels."""
    return float(np.median([np.linalg.norm(c.center) / c.K[0, 0] for c in cameras]))


def _finest_movable(levels, cells):
    """The finest of ``levels`` where it can go into bricks of one occupancy cell each
    (``cells`` along the grid's colatitude, or along every axis in the ball): a coarser level
    stays dense and it is a whole multiple of the cells, above one texel a cell; else None."""
    finest = max(levels)
    if len(levels) < 2 or finest % cells or finest <= cells:
        return None
    return finest


def finest_in_bricks(config: TrainConfig):
    """``(config, R)``: ``config`` with the foreground's finest dense level ``R`` (of
    ``--grid-levels``) moved into bricks, the background's dense levels as they were
    (:func:`background_in_bricks` moves its own finest); ``R`` None
    (``config`` as it was) where no coarser level would stay dense or ``R`` is no whole
    multiple of the occupancy cells (a brick each) above one texel a cell. On the embedded
    capture, gt_plaza and the 1/4-phone stand-in a 10-minute run made 1.02-1.25x the steps
    at equal or higher held-out PSNR (docs/experiments.md)."""
    m = config.model
    levels = tuple(m.levels('ball'))
    finest = _finest_movable(levels, occ.grid_shape('ball', config.sampling.occupancy_res)[0])
    if finest is None:
        return config, None
    return config.replace(grid_levels=tuple(r for r in levels if r != finest),
                          bg_grid_levels=tuple(m.levels('inverted_sphere'))), finest


def background_in_bricks(config: TrainConfig):
    """``(config, R)``: ``config`` with the background's finest dense level ``R`` (of
    ``--bg-grid-levels``) moved into bricks, which hold it where the training rays take their
    colour from (:class:`~mi_nerfpp.training.schedule.SparseAllocation`); ``R`` None (``config``
    as it was) where that grid has no such level (:func:`_finest_movable`) or its sparse levels
    are given."""
    m = config.model
    if m.bg_grid_sparse is not None or m.field_of('inverted_sphere') != 'grid':
        return config, None
    levels = tuple(m.levels('inverted_sphere'))
    cells = occ.grid_shape('inverted_sphere', config.sampling.occupancy_res)[1]
    finest = _finest_movable(levels, cells)
    if finest is None:
        return config, None
    return config.replace(bg_grid_levels=tuple(r for r in levels if r != finest),
                          bg_grid_sparse=(finest,)), finest


def choose_sparse_level(config: TrainConfig, dataset, stored: dict, notice=_quiet):
    """``config`` with its sparse foreground levels chosen (``--grid-sparse`` not given): a
    resumed run's own (with the dense levels it kept, and its background's), else the finest
    dense level in bricks (:func:`finest_in_bricks`, and the background's with it unless
    ``--bg-grid-sparse`` is given: :func:`background_in_bricks`) where its cells span at least
    :data:`~mi_nerfpp.core.budget.SPARSE_PIXELS` training pixels at the centre, and a finer one of
    :func:`~mi_nerfpp.core.budget.sparse_resolution` of the capture's
    :func:`centre_footprint`, announced."""
    if stored:
        return _stored_sparse_levels(config, TrainConfig.stored_options(stored))
    m = config.model
    if m.field != 'grid' or not config.sampling.occupancy:
        return config.replace(grid_sparse=())
    footprint = centre_footprint(dataset.train.cameras)
    finest = max(m.levels('ball'))
    r = budget.sparse_resolution(footprint, finest, config.sampling.occupancy_res)
    cells = f'{2 / finest / footprint:.1f} pixels per cell of the {finest}³ level'
    # (Only a level whose cells span two training pixels: on the 32x24 test capture, cells of
    # 0.7 pixels, 600 steps scored 20.0 dB held out in bricks against 23.2 dense, cause not
    # found: not the pruning, the brick size or the antialiasing; docs/experiments.md.)
    config, moved = (finest_in_bricks(config) if budget.spans_pixels(finest, footprint)
                     else (config, None))
    kept = (moved,) if moved else ()
    if moved:
        notice(f'foreground level {moved}³ stored in bricks where the surfaces are, the '
               f'coarser {" ".join(map(str, config.model.grid_levels))} dense; --grid-sparse '
               f'alone to keep it dense')
        config, behind = background_in_bricks(config)
        if behind:
            notice(f'background level {behind} stored in bricks where the training rays take '
                   f'their colour from, the coarser '
                   f'{" ".join(map(str, config.model.bg_grid_levels))} dense; --bg-grid-sparse '
                   f'alone to keep it dense')
    if r is None:
        notice(f'no {"finer " if moved else ""}sparse foreground level: a training pixel is '
               f'{footprint:.4f} of the unit ball wide at the centre ({cells}); --grid-sparse '
               f'{" ".join(map(str, kept + ("RES",)))} to add one')
        return config.replace(grid_sparse=kept)
    config = config.replace(grid_sparse=kept + (r,))
    entries = budget.sparse_level_entries(config.sizing(), 'ball')[-1]
    notice(f'sparse foreground level {r}³ (a training pixel is {footprint:.4f} of the unit '
           f'ball wide at the centre: {cells}), at most {entries / 1e6:.1f} M entries in '
           f'bricks where the surfaces are; --grid-sparse to change, --grid-sparse alone for '
           f'none')
    return config


def _stored_sparse_levels(config: TrainConfig, options: dict) -> TrainConfig:
    """``config`` with a resumed run's sparse foreground levels, and its dense levels where
    :func:`finest_in_bricks` had moved today's finest into bricks (``--grid-levels`` left at
    its default then stands for the levels the run was trained with)."""
    sparse = tuple(options.get('grid_sparse') or ())
    config = config.replace(grid_sparse=sparse)
    levels = tuple(options.get('grid_levels') or ())
    moved = finest_in_bricks(config)[1]
    if moved in sparse and levels and moved not in levels:
        config = config.replace(grid_levels=levels,
                                bg_grid_levels=options.get('bg_grid_levels'))
    return config


def keep_sparse_schedule(config: TrainConfig, stored: dict) -> TrainConfig:
    """``config`` with a resumed run's ``--sparse-at`` and ``--sparse-entries`` wherever it
    leaves today's defaults: the run's bricks were chosen with its own, which a default
    changed since must neither re-choose nor have refused when no allocation is ahead
    (:meth:`~mi_nerfpp.training.train.Trainer._check_allocations`)."""
    if not stored:
        return config
    options, default = TrainConfig.stored_options(stored), TrainConfig().schedule
    kept = {name: options[name] for name in ('sparse_at', 'sparse_entries')
            if name in options and getattr(config.schedule, name) == getattr(default, name)}
    return config.replace(**kept) if kept else config


def choose_error_rays(config: TrainConfig, stored: dict) -> TrainConfig:
    """``config`` with the error map's share of the rays chosen (``--error-rays`` not given):
    a resumed run draws as it did (runs from before the error map: uniformly), a new one
    uniformly (:mod:`.error_map`)."""
    if config.schedule.error_rays is not None:
        return config
    drawn = TrainConfig.stored_options(stored).get('error_rays') if stored else None
    return config.replace(error_rays=drawn or 0.0)


def rendered(dataset) -> bool:
    """Whether ``dataset`` is a capture that ``synth`` rendered (its ``capture.json`` beside it):
    every view of one exposure and white balance, unlike photos."""
    return os.path.isfile(os.path.join(os.fspath(dataset.root), CAPTURE_FILE))


# What a run learns for photos and not for a capture rendered by synth (exact exposure, exact
# poses), each with the line that announces it (:func:`choose_for_photos`).
FOR_PHOTOS = {
    'appearance': 'per-photo appearance on: each training photo learns a colour transform (its '
                  'exposure and white balance; held-out photos scored with theirs fitted on their '
                  'left half); --no-appearance for photos of one fixed exposure',
    'refine_poses': 'pose refinement on: each training camera learns a small turn and shift '
                    '(the errors structure from motion leaves), coarse to fine; held-out photos '
                    'keep their given poses; --no-refine-poses for exact poses (rendered or '
                    'tracked cameras)'}


def choose_for_photos(config: TrainConfig, dataset, stored: dict, notice=_quiet):
    """``config`` with what each photo learns of its own chosen where the options leave it
    (:data:`FOR_PHOTOS`: ``--appearance``, ``--refine-poses``; neither ``--x`` nor ``--no-x``
    given): a resumed run's own; on for photos, announced, off for a capture :func:`rendered`
    by ``synth``. On the realistic stand-in of a phone capture (auto-exposure, poses off by
    COLMAP-sized errors) the colour transforms are worth ~1.1 dB held out and the pose
    corrections 0.5-1.5 dB more (two scenes, docs/experiments.md)."""
    for name, line in FOR_PHOTOS.items():
        if getattr(config.model, name) is not None:
            continue
        if stored:
            value = bool(TrainConfig.stored_options(stored).get(name))
        else:
            value = not rendered(dataset)
            if value:
                notice(line)
        config = config.replace(**{name: value})
    return config


def choose_masks(config: TrainConfig, dataset, stored: dict, notice=_quiet) -> TrainConfig:
    """``config`` with the meaning of the photos' masks (:mod:`mi_nerfpp.data.masks`) chosen
    when ``--masks`` is not given (a resumed run's own; ``ignore`` when the training photos
    have masks) and announced; ``--masks ignore|object`` without masks is refused."""
    found = dataset.train.masks
    meaning = config.losses.masks
    if meaning is None:
        meaning = (TrainConfig.stored_options(stored).get('masks') if stored else None) or (
            masks.DEFAULT_MEANING if found is not None else 'none')
    if meaning != 'none' and found is None:
        raise DatasetError(f'{dataset.root}: --masks {meaning}, but no training photo has a '
                           f'mask (looked for masks/ beside images/, mask/ in each split '
                           f'folder, "mask_path" in transforms.json: docs/data.md, "Masks")')
    if found is None:           # (a capture without masks stores none)
        return config
    with_mask = sum(m is not None for m in found)
    notice(f'masks: {with_mask} of {len(found)} training photos have one; --masks {meaning}: '
           f'{MASK_MEANINGS[meaning]} (--masks ignore|object|none to change)')
    return config.replace(masks=meaning)


def choose_budget(config: TrainConfig, dataset, notice=_quiet) -> TrainConfig:
    """``config`` with a time budget when it gives neither iterations nor minutes:
    :func:`~mi_nerfpp.training.config.default_minutes` of the training pixels, announced."""
    schedule = config.schedule
    if schedule.iterations is not None or schedule.minutes is not None:
        return config
    cam = dataset.train.cameras[0]
    minutes = default_minutes(len(dataset.train) * cam.width * cam.height)
    notice(f'training for {minutes:g} minutes (chosen from {len(dataset.train)} views of '
           f'{cam.width}x{cam.height}; --minutes to change)')
    return config.replace(minutes=minutes)
