"""The model the ``nerfpp`` integrator renders: a checkpoint found next to the scene file, its
appearance transforms."""
from __future__ import annotations

import os

import mitsuba as mi

from mi_nerfpp.core.appearance import single
from mi_nerfpp.files.checkpoint import load_checkpoint


def resolve_checkpoint(name: str) -> str:
    """The path of checkpoint ``name``: relative paths are found next to the scene file
    (Mitsuba's file resolver). Refuses a missing file, listing where it looked."""
    resolver = mi.file_resolver()
    path = str(resolver.resolve(name))
    if not os.path.isfile(path):
        places = [os.path.abspath(os.path.join(str(resolver[i]), name))
                  for i in range(len(resolver))] or [os.path.abspath(path)]
        raise ValueError(
            f"nerfpp: checkpoint '{name}' not found (looked for "
            f"{', '.join(dict.fromkeys(places))}; relative paths are resolved against "
            f"the scene file's folder)")
    return path


def load_model(name: str):
    """``(model, meta)`` of checkpoint ``name`` (:func:`resolve_checkpoint`)."""
    model, meta, _ = load_checkpoint(resolve_checkpoint(name))
    return model, meta


def check_appearance(model, index: int, flag: str | None = None):
    """Refuse an ``appearance_image`` the model has no colour transform or embedding for
    (``flag``: the command-line option that gave it, named instead of the parameter)."""
    n = max(model.appearance_images, model.embedding_images)
    if index >= n:
        have = (f'an appearance for training images 0..{n - 1}' if n else
                'no appearance per training image (train with --appearance or '
                '--appearance-embedding)')
        what = flag or "nerfpp: parameter 'appearance_image'"
        raise ValueError(f"{what} is {index} "
                         f"but the model has {have}; -1 renders neutral")


def appearance_transform(model, index: int):
    """``(gain, bias)`` (Color3f) of training image ``index``'s colour transform."""
    gain, bias = single(model.appearance.numpy(), index)
    return mi.Color3f(*map(float, gain)), mi.Color3f(*map(float, bias))
