#!/usr/bin/env python3
"""Write docs/benchmarks.md from the benchmarks' result files, benchmarks/results/*.json.

    python scripts/benchmarks_page.py            # (re)write docs/benchmarks.md
    python scripts/benchmarks_page.py --check    # exit 1 if docs/benchmarks.md is not up to date
    python scripts/benchmarks_page.py --results DIR --out FILE

Each script in ``benchmarks/`` that measures something writes one JSON file per measurement,
``benchmarks/results/<name>.json``, with these keys (in this order)::

    benchmark  the script's name without .py, e.g. "train"
    variant    optional: what this file measures when one benchmark measures different things,
               e.g. "train" or "render" for versus (see "Kinds" below)
    title      a heading for the page
    command    exactly what reproduces it, from the repository root
    date       ISO 8601, UTC, when it finished
    machine    {"cpu", "memory_gib", "os", "python", "mitsuba", "drjit"}
    git        short revision of the code measured (+ "-dirty" if modified)
    tables     [{"title", "columns": [...], "rows": [[...], ...], "note" (optional)}, ...]
    figures    optional: PNG files next to the JSON
    notes      optional paragraph: what was compared, caveats
    raw        optional: anything else the script keeps (not shown on the page)

Numbers in rows are plain JSON numbers; this script formats them.

Kinds. The page shows the current figure of each kind of result once: a kind is a benchmark
and its variant, and of the files of one kind the page shows the latest (by "date"; the file
name breaks a tie). A file's variant is its "variant" key; without one it is "" except for
the benchmarks in ``COMMAND_VARIANTS``, whose positional arguments say what was measured and
are the variant: ``versus`` (its mode, train or render, and any name=value options of the new
version) and ``profile`` (name=value options: a configuration other than the defaults). So a
held_out file replaces the held_out section whatever runs it compares, while a versus train
result and a versus render result each keep a section. Older files of a kind stay in
``benchmarks/results/`` and are listed at the end of the page ("Older results": file, date,
title), without their tables.

Each shown file is one section of the page, in a fixed order (the benchmarks in ``ORDER``
first, then the others alphabetically; the variants of one benchmark alphabetically, "" first):
its title, its tables (numbers formatted here), its figures (PNG files next to the JSON), its
notes, and the line that says how it was measured: the command, the date, the machine and the
git revision of the code measured. There are no hand-written numbers on the page; with no
result files it says how to produce them.

``tests/test_docs.py`` regenerates the page and fails when the committed file differs.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import re
import shlex
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / 'benchmarks' / 'results'
PAGE = ROOT / 'docs' / 'benchmarks.md'
REGENERATE = 'python scripts/benchmarks_page.py'

# Known benchmarks first, in this order (quality and speed of the default job, then the rest).
ORDER = ('versus', 'held_out', 'resolution', 'profile', 'quality', 'train', 'render',
         'compare', 'cluster', 'objects', 'appearance', 'poses', 'coverage', 'converged',
         'noise_ceiling', 'render_samples', 'ablation', 'photo_set_memory')
REQUIRED = ('benchmark', 'title', 'command', 'date', 'machine', 'git', 'tables')
# Benchmarks whose positional arguments say what a file measures (its variant, when the file
# has no "variant" key): versus's mode (train / render) and name=value options, profile's
# name=value options. Every --option of these scripts takes one value.
COMMAND_VARIANTS = ('versus', 'profile')
MACHINE_KEYS = ('cpu', 'memory_gib', 'os', 'python', 'mitsuba', 'drjit')


class ResultError(ValueError):
    """A result file that does not follow the schema (the message names the file and key)."""


# ---------------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------------

def _where(path: Path) -> str:
    try:
        return str(path.relative_to(ROOT))
    except ValueError:
        return str(path)


def load_result(path: Path) -> dict:
    """One result file, checked against the schema."""
    try:
        result = json.loads(path.read_text(encoding='utf-8'))
    except json.JSONDecodeError as e:
        raise ResultError(f'{_where(path)}: not valid JSON ({e})') from None
    if not isinstance(result, dict):
        raise ResultError(f'{_where(path)}: expected a JSON object, got {type(result).__name__}')
    missing = [key for key in REQUIRED if key not in result]
    if missing:
        raise ResultError(f'{_where(path)}: missing {", ".join(map(repr, missing))} '
                          f'(every result file has {", ".join(REQUIRED)})')
    for key in ('benchmark', 'title', 'command', 'date', 'git'):
        if not isinstance(result[key], str) or not result[key].strip():
            raise ResultError(f'{_where(path)}: {key!r} must be a non-empty string')
    _parse_date(result['date'], path)
    if 'variant' in result and (not isinstance(result['variant'], str)
                                or not result['variant'].strip()):
        raise ResultError(f'{_where(path)}: "variant", when present, must be a non-empty string')
    if not isinstance(result['machine'], dict):
        raise ResultError(f'{_where(path)}: "machine" must be an object with '
                          f'{", ".join(MACHINE_KEYS)}')
    tables = result['tables']
    if not isinstance(tables, list) or not tables:
        raise ResultError(f'{_where(path)}: "tables" must be a non-empty list of tables')
    for i, table in enumerate(tables):
        if not isinstance(table, dict) or not isinstance(table.get('columns'), list) \
                or not isinstance(table.get('rows'), list):
            raise ResultError(f'{_where(path)}: table {i} needs "columns" and "rows" lists')
        for j, row in enumerate(table['rows']):
            if not isinstance(row, list) or len(row) != len(table['columns']):
                raise ResultError(f'{_where(path)}: table {i}, row {j} has '
                                  f'{len(row) if isinstance(row, list) else "no"} cells for '
                                  f'{len(table["columns"])} columns')
    figures = result.get('figures') or []
    if not isinstance(figures, list) or not all(isinstance(f, str) for f in figures):
        raise ResultError(f'{_where(path)}: "figures" must be a list of PNG file names')
    for figure in figures:
        if not (path.parent / figure).is_file():
            raise ResultError(f'{_where(path)}: figure {figure!r} is not in '
                              f'{_where(path.parent)}/')
    return result


def variant(result: dict) -> str:
    """What a result measures within its benchmark: its "variant" key, else for the benchmarks
    in COMMAND_VARIANTS the positional arguments of its command, else ""."""
    if result.get('variant'):
        return result['variant'].strip()
    if result['benchmark'] not in COMMAND_VARIANTS:
        return ''
    try:
        words = shlex.split(result['command'])
    except ValueError:
        return ''
    script = next((i for i, w in enumerate(words) if w.endswith('.py')), None)
    if script is None:
        return ''
    positional, rest = [], iter(words[script + 1:])
    for word in rest:
        if word.startswith('--'):
            if '=' not in word:
                next(rest, None)                     # its value
        else:
            positional.append(word)
    return ' '.join(positional)


def kind(result: dict) -> tuple[str, str]:
    """The kind of a result: its benchmark and variant. The page shows each kind once."""
    return result['benchmark'], variant(result)


def _kind_key(item):
    name, var = kind(item[1])
    return (ORDER.index(name) if name in ORDER else len(ORDER)), name, var


def load_results(results_dir: Path) -> list[tuple[Path, dict]]:
    """Every results_dir/*.json, in the page's order (kinds in order; within a kind by name)."""
    found = [(path, load_result(path)) for path in sorted(Path(results_dir).glob('*.json'))]
    return sorted(found, key=lambda item: (_kind_key(item), item[0].name))


def _when(item) -> tuple:
    path, result = item
    return _parse_date(result['date'], path).timestamp(), path.name


def current_and_older(results) -> list[tuple[tuple[Path, dict], list[tuple[Path, dict]]]]:
    """For each kind, in the page's order: its latest result and its older ones, newest first."""
    kinds: dict[tuple, list] = {}
    for item in results:
        kinds.setdefault(_kind_key(item), []).append(item)
    out = []
    for key in sorted(kinds):
        items = sorted(kinds[key], key=_when, reverse=True)
        out.append((items[0], items[1:]))
    return out


# ---------------------------------------------------------------------------------------------
# Formatting
# ---------------------------------------------------------------------------------------------

def _parse_date(text: str, path: Path) -> datetime.datetime:
    try:
        date = datetime.datetime.fromisoformat(text.replace('Z', '+00:00'))
    except ValueError:
        raise ResultError(f'{_where(path)}: "date" {text!r} is not ISO 8601 '
                          f'(e.g. 2026-11-25T14:03:00+00:00)') from None
    if date.tzinfo is not None:
        date = date.astimezone(datetime.timezone.utc)
    return date


def format_number(value) -> str:
    """A cell: integers with thousands separators, other numbers to 4 significant digits
    (no exponent for ordinary magnitudes), strings as they are."""
    if value is None:
        return '–'
    if isinstance(value, bool):
        return 'yes' if value else 'no'
    if isinstance(value, int):
        return f'{value:,}'
    if isinstance(value, float):
        if math.isnan(value):
            return 'nan'
        if math.isinf(value):
            return '∞' if value > 0 else '−∞'
        if value == 0:
            return '0'
        if abs(value) >= 1000:
            return f'{value:,.0f}'
        if abs(value) < 1e-3:
            return f'{value:.3g}'
        return f'{value:.4g}'
    if isinstance(value, str):
        return value
    return json.dumps(value, ensure_ascii=False)


def _cell(value) -> str:
    return format_number(value).replace('|', '\\|').replace('\n', ' ')


def format_machine(machine: dict) -> str:
    parts = []
    if machine.get('cpu'):
        parts.append(str(machine['cpu']))
    if machine.get('memory_gib') is not None:
        parts.append(f'{format_number(machine["memory_gib"])} GiB')
    if machine.get('os'):
        parts.append(str(machine['os']))
    for key, name in (('python', 'Python'), ('mitsuba', 'Mitsuba'), ('drjit', 'Dr.Jit')):
        if machine.get(key):
            parts.append(f'{name} {machine[key]}')
    known = set(MACHINE_KEYS)
    parts += [f'{key} {value}' for key, value in machine.items() if key not in known]
    return ', '.join(parts) or 'machine not recorded'


def _anchor(title: str) -> str:
    return re.sub(r'[^\w\- ]', '', title.strip().lower()).replace(' ', '-')


def render_table(table: dict) -> list[str]:
    out = []
    if table.get('title'):
        out += [f'**{table["title"]}**', '']
    out.append('| ' + ' | '.join(_cell(c) for c in table['columns']) + ' |')
    out.append('|' + '---|' * len(table['columns']))
    out += ['| ' + ' | '.join(_cell(v) for v in row) + ' |' for row in table['rows']]
    out.append('')
    if table.get('note'):
        out += [str(table['note']), '']
    return out


def render_section(path: Path, result: dict, page_dir: Path, title: str) -> list[str]:
    out = [f'## {title}', '']
    for table in result['tables']:
        out += render_table(table)
    for figure in result.get('figures') or []:
        link = Path(os.path.relpath(path.parent / figure, page_dir)).as_posix()
        out += [f'![{figure}]({link})', '']
    if result.get('notes'):
        out += [str(result['notes']), '']
    date = _parse_date(result['date'], path).strftime('%Y-%m-%d %H:%M UTC')
    source = Path(os.path.relpath(path, page_dir)).as_posix()
    out += [f'`{result["command"]}` - {date}, {format_machine(result["machine"])}, '
            f'git `{result["git"]}` ([{path.name}]({source}))', '']
    return out


def render_page(results_dir: Path = RESULTS, page: Path = PAGE) -> str:
    results_dir, page = Path(results_dir), Path(page)
    results = load_results(results_dir)
    page_dir = page.parent
    where = Path(os.path.relpath(results_dir, page_dir)).as_posix()
    out = [f'<!-- Generated by `{REGENERATE}` from {_where(results_dir)}/*.json; '
           'do not edit by hand. -->', '',
           '# Benchmarks', '',
           'Speed and quality as measured by the scripts in `benchmarks/`: the current figure '
           'of each kind of measurement, that is the latest result file of each benchmark (and '
           f'variant) in [{_where(results_dir)}]({where}/), with the command that reproduces '
           'it (run from the repository root), when it finished, the machine and the git '
           'revision of the code measured. Numbers from different machines, or from a machine '
           'that was doing other work, do not compare. Earlier result files are listed at the '
           'end; what changed when, with the figure that justified it, is in the '
           '[changelog](../CHANGELOG.md), and what was tried and not kept in '
           '[experiments](experiments.md).', '']
    if not results:
        out += ['## No results yet', '',
                f'`{_where(results_dir)}/` holds no result files. Every script in `benchmarks/` '
                'that measures something prints its numbers and writes '
                f'`{_where(results_dir)}/<name>.json` (a later run of the same benchmark '
                'replaces its file). Run the benchmarks alone on an otherwise idle machine, '
                'with warm kernels (a first run compiles them), then regenerate this page:',
                '', '```', 'python benchmarks/<script>.py ...      # see each script\'s --help',
                REGENERATE, '```', '']
        return '\n'.join(out)
    shown = current_and_older(results)
    titles, seen = [], {}
    for (_, result), _ in shown:
        title = result['title'].strip()
        seen[title] = seen.get(title, 0) + 1
        if seen[title] > 1:
            title = f'{title} ({variant(result) or seen[title]})'
        titles.append(title)
    older = [(title, items) for title, (_, items) in zip(titles, shown) if items]
    contents = [f'[{t}](#{_anchor(t)})' for t in titles]
    if older:
        contents.append('[Older results](#older-results)')
    out += ['**Contents:** ' + ', '.join(contents) + '.', '']
    for ((path, result), _), title in zip(shown, titles):
        out += render_section(path, result, page_dir, title)
    if older:
        out += ['## Older results', '',
                'Earlier results of the benchmarks above, newest first: their files stay in '
                f'[{_where(results_dir)}]({where}/), and this page shows only the latest of each '
                'kind.', '']
        for title, items in older:
            out.append(f'- [{title}](#{_anchor(title)}):')
            for path, result in items:
                date = _parse_date(result['date'], path).strftime('%Y-%m-%d %H:%M UTC')
                source = Path(os.path.relpath(path, page_dir)).as_posix()
                out.append(f'  - [{path.name}]({source}) - {date}, '
                           f'{_cell(result["title"].strip())}')
        out.append('')
    return '\n'.join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--results', type=Path, default=RESULTS,
                    help=f'folder of result files (default: {_where(RESULTS)})')
    ap.add_argument('--out', type=Path, default=PAGE, help=f'the page (default: {_where(PAGE)})')
    ap.add_argument('--check', action='store_true',
                    help='only compare with the existing page; exit 1 if it differs')
    args = ap.parse_args(argv)
    try:
        text = render_page(args.results, args.out)
    except ResultError as e:
        print(f'error: {e}', file=sys.stderr)
        return 1
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
