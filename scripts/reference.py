#!/usr/bin/env python3
"""Write docs/reference.md from the code: every command's ``--help``, the integrator's
XML parameters and the package's modules.

    python scripts/reference.py            # (re)write docs/reference.md
    python scripts/reference.py --check    # exit 1 if docs/reference.md is not up to date

The page has two parts, both generated, nothing hand-written:

* the help of ``python -m mi_nerfpp`` and of each of its subcommands, exactly as argparse
  prints it (``mi_nerfpp.commands.cli.build_parser()``), at a fixed terminal width (``COLUMNS``) so that
  the output does not depend on the terminal the script runs in. Option groups, new commands
  and new options appear as argparse prints them;
* the parameters of ``<integrator type="nerfpp">``, parsed from the ``.. pluginparameters::``
  list in the integrator class's docstring (Mitsuba's own format). The class is found through
  Mitsuba's plugin registry (``type="nerfpp"``), wherever it lives in the package.
* the package's modules, each with the first paragraph of its docstring (read with ``ast``).

``tests/test_docs.py`` regenerates the page and fails when the committed file differs.
"""
from __future__ import annotations

import argparse
import ast
import contextlib
import os
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / 'docs' / 'reference.md'
COLUMNS = 100            # the terminal width the help is formatted for
PROG = 'python -m mi_nerfpp'
REGENERATE = 'python scripts/reference.py'


# ---------------------------------------------------------------------------------------------
# Commands: whatever argparse prints
# ---------------------------------------------------------------------------------------------

@contextlib.contextmanager
def _fixed_terminal():
    """argparse wraps help at the terminal width (``shutil.get_terminal_size``, which reads
    ``COLUMNS``): fix it for the duration, and keep colour codes out of the text."""
    saved = {key: os.environ.get(key) for key in ('COLUMNS', 'NO_COLOR', 'FORCE_COLOR')}
    os.environ.update(COLUMNS=str(COLUMNS), NO_COLOR='1')
    os.environ.pop('FORCE_COLOR', None)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def _subcommands(parser: argparse.ArgumentParser):
    """(name, parser) of each subcommand, in the order ``--help`` lists them (nested ones
    too, as ``parent child``)."""
    for action in parser._actions:                       # argparse keeps no public list
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield name, sub
                for child, subsub in _subcommands(sub):
                    yield f'{name} {child}', subsub


def command_helps() -> list[tuple[str, str]]:
    """(command, help text) for ``python -m mi_nerfpp`` and every subcommand."""
    sys.path.insert(0, str(ROOT))
    from mi_nerfpp.commands.cli import build_parser
    with _fixed_terminal():
        parser = build_parser()
        helps = [('', parser.format_help())]
        helps += [(name, sub.format_help()) for name, sub in _subcommands(parser)]
    return helps


def _anchor(title: str) -> str:
    """The anchor GitHub gives a heading (lower case, punctuation dropped, spaces to '-')."""
    return re.sub(r'[^\w\- ]', '', title.strip().lower()).replace(' ', '-')


# ---------------------------------------------------------------------------------------------
# Integrator parameters: the docstring's pluginparameters list
# ---------------------------------------------------------------------------------------------

def integrator_class():
    """The class registered as ``type="nerfpp"`` (importing the package registers it)."""
    sys.path.insert(0, str(ROOT))
    import mi_nerfpp  # noqa: F401  (selects a variant, registers the plugin)
    import mitsuba as mi
    return type(mi.load_dict({'type': 'nerfpp'}))


_TYPES = {'|string|': 'string', '|int|': 'integer', '|float|': 'float', '|bool|': 'boolean',
          '|spectrum|': 'spectrum', '|texture|': 'texture', '|transform|': 'transform',
          '|point|': 'point', '|vector|': 'vector', '|tensor|': 'tensor', '|volume|': 'volume'}


def rst_to_markdown(text: str) -> str:
    """Inline reStructuredText of a docstring as Markdown: ``code`` to `code`, roles such as
    :meth:`set_model` or :data:`~a.B` to `set_model` / `B`, |substitutions| to words."""
    text = re.sub(r':[\w:]+:`(~?)([^`]+)`',
                  lambda m: f'`{m.group(2).split(".")[-1] if m.group(1) else m.group(2)}`', text)
    text = re.sub(r'``([^`]+)``', r'`\1`', text)
    text = re.sub(r'\|(\w+)\|', lambda m: _TYPES.get(m.group(0), m.group(1)), text)
    return text.replace('|', '\\|')


def plugin_parameters(doc: str) -> list[list[str]]:
    """The rows of the ``.. pluginparameters::`` list table in a docstring: one list of cells
    per parameter (name, type, description, then any further columns), whitespace joined."""
    lines = (doc or '').expandtabs().splitlines()
    start = next((i for i, line in enumerate(lines)
                  if line.strip() == '.. pluginparameters::'), None)
    if start is None:
        raise ValueError('the integrator docstring has no ".. pluginparameters::" list')
    indent = len(lines[start]) - len(lines[start].lstrip())
    rows: list[list[str]] = []
    for line in lines[start + 1:]:
        stripped = line.strip()
        if stripped and len(line) - len(line.lstrip()) <= indent:
            break                                         # the directive's block has ended
        if stripped.startswith('* - '):
            rows.append([stripped[4:]])
        elif stripped.startswith('- ') and rows:
            rows[-1].append(stripped[2:])
        elif stripped and rows:
            rows[-1][-1] += ' ' + stripped
    if not rows or any(len(row) < 3 for row in rows):
        raise ValueError('the integrator docstring\'s ".. pluginparameters::" list is not '
                         'name / type / description rows')
    return rows


def _split_default(description: str) -> tuple[str, str]:
    """'Text. (Default: x)' -> ('Text.', 'x')."""
    m = re.search(r'\s*\(Default:\s*(.*)\)\s*$', description)
    if not m:
        return description, ''
    return description[:m.start()].rstrip(), m.group(1).strip()


def parameter_table(rows: list[list[str]]) -> str:
    extra = max(len(row) for row in rows) - 3
    head = ['name', 'type', 'default', 'meaning'] + ['flags'] * min(extra, 1)
    out = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for name, kind, description, *rest in rows:
        text, default = _split_default(description)
        cells = [f'`{name}`', rst_to_markdown(kind), rst_to_markdown(default) or '–',
                 rst_to_markdown(text)]
        if extra:
            cells.append(rst_to_markdown(', '.join(rest)))
        out.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(out)


# ---------------------------------------------------------------------------------------------
# Modules: the first paragraph of each module's docstring
# ---------------------------------------------------------------------------------------------

def module_summaries(package: Path = ROOT / 'mi_nerfpp') -> list[tuple[str, str]]:
    """(dotted module name, first paragraph of its docstring) for every module of the package
    and its subpackages (folders with an ``__init__.py``), read with ``ast`` (nothing is
    imported); each package before its modules."""
    def order(path):
        parts = path.relative_to(package.parent).with_suffix('').parts
        return tuple((0, '') if part == '__init__' else (1, part) for part in parts)

    out = []
    for path in sorted(package.rglob('*.py'), key=order):
        if any(part.startswith(('_', '.')) and part != '__init__.py'
               for part in path.relative_to(package).parts):
            continue                                   # private modules, __main__
        if any(not (folder / '__init__.py').is_file()
               for folder in path.parents if folder.is_relative_to(package)):
            continue                                   # scripts in data folders (scenes/)
        doc = ast.get_docstring(ast.parse(path.read_text(encoding='utf-8'))) or ''
        first = ' '.join(doc.strip().split('\n\n')[0].split())
        parts = path.relative_to(package.parent).with_suffix('').parts
        name = '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)
        out.append((name, first))
    return out


def module_table(summaries) -> str:
    out = ['| module | what it is |', '|---|---|']
    out += [f'| `{name}` | {rst_to_markdown(text) or "–"} |' for name, text in summaries]
    return '\n'.join(out)


# ---------------------------------------------------------------------------------------------
# The page
# ---------------------------------------------------------------------------------------------

def render_page() -> str:
    helps = command_helps()
    cls = integrator_class()
    rows = plugin_parameters(cls.__doc__)
    titles = [f'`{PROG}{" " + name if name else ""}`' for name, _ in helps]
    out = [
        f'<!-- Generated by `{REGENERATE}` from the code; do not edit by hand. -->',
        '',
        '# Reference',
        '',
        'Generated from the code: the `--help` of every command (as argparse prints it at '
        f'{COLUMNS} columns) and the `<integrator type="nerfpp">` parameters (from the '
        f'integrator\'s docstring, `{cls.__module__}.{cls.__qualname__}`). After changing an '
        f'option or a parameter, run `{REGENERATE}`; `tests/test_docs.py` fails while this page '
        'is out of date. `python optimize.py [options]` is the same as '
        f'`{PROG} optimize [options]`.',
        '',
        '**Commands:** ' + ', '.join(f'[{t}](#{_anchor(t)})' for t in titles) + '. '
        '**Integrator:** [parameters](#integrator-parameters). '
        '**Package:** [modules](#modules).',
        '',
    ]
    for title, (_, text) in zip(titles, helps):
        out += [f'## {title}', '', '```text', text.rstrip('\n'), '```', '']
    out += ['## Integrator parameters', '',
            'Set as `<integer name="fg_samples" value="32"/>` (`<string>`, `<float>`, '
            '`<boolean>` after the type) inside `<integrator type="nerfpp">`. How they act '
            'together: [rendering](rendering.md).', '',
            parameter_table(rows), '',
            '## Modules', '',
            'The package `mi_nerfpp`, module by module: the first paragraph of each module\'s '
            'docstring (private modules left out). How they fit together: '
            '[design](design.md).', '',
            module_table(module_summaries()), '']
    return '\n'.join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--check', action='store_true',
                    help='only compare with the committed page; exit 1 if it differs')
    ap.add_argument('--out', type=Path, default=PAGE, help=f'default: {PAGE.relative_to(ROOT)}')
    args = ap.parse_args(argv)
    text = render_page()
    if args.check:
        current = args.out.read_text(encoding='utf-8') if args.out.exists() else None
        if current != text:
            print(f'error: {args.out} is out of date: run `{REGENERATE}`', file=sys.stderr)
            return 1
        return 0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text, encoding='utf-8')
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
