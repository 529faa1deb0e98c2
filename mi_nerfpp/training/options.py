"""Command-line options generated from dataclass fields: one home for each default and its help.

A field declared with :func:`option` carries its help text (and, where needed, argparse
details) in its metadata; :func:`add_options` turns every such field into a ``--field-name``
option whose default is the field's default, and :func:`values` reads them back. Adding an
option to a command is adding one field::

    distortion: float = option(0.0, 'weight of the distortion loss (0: off)')

A config made of groups (a dataclass whose fields are declared with :func:`group`, each
holding an options dataclass) gives one titled section of ``--help`` per group; the options
stay flat on the command line, each named after its field, so every option's name (its
*option name*, the flag without dashes, e.g. ``batch_rays`` for ``--batch-rays``) is unique
across the groups. :func:`values` returns them by option name.

Metadata keys besides ``help``: ``choices``, ``metavar``, ``type`` (a parser of one string),
``nargs``, ``flag`` (instead of ``--field-name``; the option name follows it), ``exclusive``
(options with the same name form a mutually exclusive group), ``joint`` (fields with the same
joint flag are set together by one option taking one value per field, e.g. ``--samples FG BG
FINE``). Tuple defaults take ``nargs='+'`` values of their elements' type; ``None`` defaults
need a ``type``.
"""
from __future__ import annotations

import argparse
import dataclasses
import numbers

from mi_nerfpp.errors import shown


def option(default, help, **cli):
    """A dataclass field with a default and its command-line description."""
    if isinstance(default, (list, dict, set)):
        raise TypeError('use a tuple for sequence defaults')
    return dataclasses.field(default=default, metadata=dict(cli, help=help))


def group(cls, title, description=''):
    """A field of a config that holds the options dataclass ``cls`` (its defaults), shown as
    one section ``title`` of ``--help``."""
    return dataclasses.field(default_factory=cls,
                             metadata={'group': title, 'description': description})


def groups(cls):
    """``[(field name, options dataclass, metadata)]`` of a config of groups (empty for a
    plain options dataclass)."""
    return [(f.name, f.default_factory, f.metadata) for f in dataclasses.fields(cls)
            if 'group' in f.metadata]


def options_of(cls):
    """``[(group field name or None, field)]``: every option of ``cls``, in order."""
    parts = groups(cls)
    if not parts:
        return [(None, f) for f in dataclasses.fields(cls) if 'help' in f.metadata]
    return [(name, f) for name, sub, _ in parts for _, f in options_of(sub)]


# What a value of each declared type is, for messages: one value, several.
KINDS = {bool: ('true or false', 'true/false values'), int: ('a whole number', 'whole numbers'),
         float: ('a number', 'numbers'), str: ('text', 'texts')}


def declared(f):
    """``(type, sequence, optional)`` of option field ``f``: the type of its value (of each of
    its values for a sequence: ``bool``, ``int``, ``float`` or ``str``), whether it takes a
    sequence (``'+'``: one or more values, ``'*'``: any number), and whether ``None`` (unset)
    is a value. Read from its metadata and its default as :func:`add_options` reads them."""
    meta, default = f.metadata, f.default
    parser = meta.get('type')
    sequence = meta.get('nargs') or ('+' if isinstance(default, tuple) else None)
    if isinstance(default, bool) or parser is bool:
        kind = bool
    elif parser in KINDS:
        kind = parser
    elif isinstance(default, tuple):
        kind = type(default[0]) if default else float
    else:
        kind = type(default)
    return kind, sequence, default is None


def _of_kind(value, kind):
    """``value`` as a value of ``kind``, or None when it is not one (a bool is no number, a
    number with a fraction no whole number)."""
    if kind is bool:
        return value if isinstance(value, bool) else None
    if kind is str:
        return value if isinstance(value, str) else None
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return None
    if kind is int:
        return int(value) if isinstance(value, numbers.Integral) else None
    return float(value)


def check_value(f, value):
    """The value of option field ``f`` that ``value`` gives (from Python or from JSON: lists
    become tuples, one number may be given bare for a sequence of numbers, NumPy scalars
    become Python's), or ValueError saying what it must be; ranges are checked by the option's
    group. ``choices`` are checked here."""
    kind, sequence, optional = declared(f)
    if value is None and optional:
        return None
    one, several = KINDS[kind]
    unset = ' (or unset)' if optional else ''
    if sequence:
        if isinstance(value, numbers.Real) and not isinstance(value, bool) and kind in (
                int, float):
            value = (value,)
        items = tuple(_of_kind(v, kind) for v in value) if isinstance(
            value, (list, tuple)) else None
        if items is None or None in items or (sequence == '+' and not items):
            need = f'one or more {several}' if sequence == '+' else f'a list of {several}'
            raise ValueError(f'{_spelled(f)} must be {need}{unset}, got {shown(value)}')
        return items
    checked = _of_kind(value, kind)
    if checked is None:
        raise ValueError(f'{_spelled(f)} must be {one}{unset}, got {shown(value)}')
    choices = f.metadata.get('choices')
    if choices and checked not in choices:
        raise ValueError(f'{_spelled(f)} must be {" or ".join(map(repr, choices))}, got '
                         f'{checked}')
    return checked


def _spelled(f):
    """The flag of field ``f`` in a message (a joint option with its value's name)."""
    if 'joint' in f.metadata:
        return f"{f.metadata['joint']} ({f.metadata['metavar']})"
    return _flag(f)


def _flag(f):
    return f.metadata.get('flag', '--' + f.name.replace('_', '-'))


def option_name(f) -> str:
    """The name of field ``f``'s option: its flag without the dashes (``batch_rays``)."""
    return _flag(f)[2:].replace('-', '_')


def _describe(default):
    if isinstance(default, tuple):
        return ' '.join(str(v) for v in default) or 'none'
    return default


def add_options(parser, cls):
    """Add an option for every field of dataclass ``cls`` that has a help text; a config of
    :func:`group` fields gets one argument group (a section of ``--help``) per group."""
    parts = groups(cls)
    if not parts:
        _add_fields(parser, parser, cls)
        return
    for _, sub, meta in parts:
        section = parser.add_argument_group(meta['group'], meta['description'] or None)
        _add_fields(parser, section, sub)


def _add_fields(parser, section, cls):
    exclusive = {}
    fields = [f for f in dataclasses.fields(cls) if 'help' in f.metadata]
    for f in fields:
        meta = f.metadata
        if 'joint' in meta:         # one option for its fields, where the first of them is
            joint = [g for g in fields if g.metadata.get('joint') == meta['joint']]
            if f is joint[0]:
                _add_joint(section, meta['joint'], joint)
            continue
        kwargs = {'dest': option_name(f), 'default': f.default}
        default_text = f'(default: {_describe(f.default)})' if f.default is not None else ''
        kwargs['help'] = f"{meta['help']} {meta.get('default_help', default_text)}".strip()
        for key in ('choices', 'metavar', 'nargs', 'type'):
            if key in meta:
                kwargs[key] = meta[key]
        if isinstance(f.default, bool) or meta.get('type') is bool:   # bool: --x / --no-x
            kwargs.pop('type', None)
            kwargs['action'] = argparse.BooleanOptionalAction
        elif isinstance(f.default, tuple) and 'type' not in meta:
            kwargs.setdefault('nargs', '+')
            kwargs['type'] = type(f.default[0])
        elif 'type' not in meta:
            if f.default is None:
                raise TypeError(f'{cls.__name__}.{f.name}: a None default needs a type')
            kwargs['type'] = type(f.default)
        target = section
        if 'exclusive' in meta:
            if meta['exclusive'] not in exclusive:
                exclusive[meta['exclusive']] = section.add_mutually_exclusive_group()
            target = exclusive[meta['exclusive']]
        target.add_argument(_flag(f), **kwargs)


def _add_joint(section, flag, fs):
    section.add_argument(
        flag, dest=_joint_dest(flag), nargs=len(fs),
        type=type(fs[0].default), metavar=tuple(f.metadata['metavar'] for f in fs),
        default=[f.default for f in fs],
        help='; '.join(f"{f.metadata['metavar']}: {f.metadata['help']}" for f in fs)
        + ' (default: ' + ' '.join(str(f.default) for f in fs) + ')')


def _joint_dest(flag):
    return '_joint' + flag.replace('-', '_')


def values(args, cls) -> dict:
    """The values of ``cls``'s options in parsed ``args``, by option name (for a plain options
    dataclass these are its keyword arguments)."""
    out = {}
    fields = [f for _, f in options_of(cls)]
    for f in fields:
        meta = f.metadata
        if 'joint' in meta:
            joint = getattr(args, _joint_dest(meta['joint']))
            siblings = [g.name for g in fields if g.metadata.get('joint') == meta['joint']]
            out[option_name(f)] = joint[siblings.index(f.name)]
            continue
        value = getattr(args, option_name(f))
        out[option_name(f)] = tuple(value) if isinstance(value, list) else value
    return out


def flag(cls, name: str) -> str:
    """The command-line spelling of the option of ``cls`` whose field or option name is
    ``name`` (for messages)."""
    f = next(f for _, f in options_of(cls) if name in (f.name, option_name(f)))
    return f.metadata.get('joint') or _flag(f)
