"""Command-line options generated from dataclass fields: one home for each default and its help.

A field declared with :func:`option` carries its help text (and, where needed, argparse
details) in its metadata; :func:`add_options` turns every such field into a ``--field-name``
option whose default is the field's default, and :func:`values` reads them back. Adding an
option to a command is adding one field::

    distortion: float = option(0.0, 'weight of the distortion loss (0: off)')

Metadata keys besides ``help``: ``choices``, ``metavar``, ``type`` (a parser of one string),
``nargs``, ``flag`` (instead of ``--field-name``), ``exclusive`` (options with the same name
form a mutually exclusive group), ``joint`` (fields with the same joint flag are set together
by one option taking one value per field, e.g. ``--samples FG BG FINE``). Tuple defaults take
``nargs='+'`` values of their elements' type; ``None`` defaults need a ``type``.
"""
from __future__ import annotations

import argparse
import dataclasses


def option(default, help, **cli):
    """A dataclass field with a default and its command-line description."""
    if isinstance(default, (list, dict, set)):
        raise TypeError('use a tuple for sequence defaults')
    return dataclasses.field(default=default, metadata=dict(cli, help=help))


def _flag(f):
    return f.metadata.get('flag', '--' + f.name.replace('_', '-'))


def _describe(default):
    if isinstance(default, tuple):
        return ' '.join(str(v) for v in default)
    return default


def add_options(parser, cls):
    """Add an option for every field of dataclass ``cls`` that has a help text."""
    groups, joints = {}, {}
    for f in dataclasses.fields(cls):
        meta = f.metadata
        if 'help' not in meta:
            continue
        if 'joint' in meta:
            joints.setdefault(meta['joint'], []).append(f)
            continue
        kwargs = {'dest': f.name, 'default': f.default}
        default_text = f'(default: {_describe(f.default)})' if f.default is not None else ''
        kwargs['help'] = f"{meta['help']} {meta.get('default_help', default_text)}".strip()
        for key in ('choices', 'metavar', 'nargs', 'type'):
            if key in meta:
                kwargs[key] = meta[key]
        if isinstance(f.default, bool):
            kwargs['action'] = argparse.BooleanOptionalAction
        elif isinstance(f.default, tuple) and 'type' not in meta:
            kwargs.setdefault('nargs', '+')
            kwargs['type'] = type(f.default[0])
        elif 'type' not in meta:
            if f.default is None:
                raise TypeError(f'{cls.__name__}.{f.name}: a None default needs a type')
            kwargs['type'] = type(f.default)
        target = parser
        if 'exclusive' in meta:
            if meta['exclusive'] not in groups:
                groups[meta['exclusive']] = parser.add_mutually_exclusive_group()
            target = groups[meta['exclusive']]
        target.add_argument(_flag(f), **kwargs)
    for flag, fs in joints.items():
        parser.add_argument(
            flag, dest='_joint' + flag.replace('-', '_'), nargs=len(fs),
            type=type(fs[0].default), metavar=tuple(f.metadata['metavar'] for f in fs),
            default=[f.default for f in fs],
            help='; '.join(f"{f.metadata['metavar']}: {f.metadata['help']}" for f in fs)
            + ' (default: ' + ' '.join(str(f.default) for f in fs) + ')')


def values(args, cls) -> dict:
    """The values of ``cls``'s options in parsed ``args``, as keyword arguments of ``cls``."""
    out = {}
    for f in dataclasses.fields(cls):
        meta = f.metadata
        if 'help' not in meta:
            continue
        if 'joint' in meta:
            joint = getattr(args, '_joint' + meta['joint'].replace('-', '_'))
            siblings = [g.name for g in dataclasses.fields(cls)
                        if g.metadata.get('joint') == meta['joint']]
            out[f.name] = joint[siblings.index(f.name)]
            continue
        value = getattr(args, f.name)
        out[f.name] = tuple(value) if isinstance(value, list) else value
    return out


def flag(cls, name: str) -> str:
    """The command-line spelling of field ``name`` of ``cls`` (for messages)."""
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    return f.metadata.get('joint') or _flag(f)
