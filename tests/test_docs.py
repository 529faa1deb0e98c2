"""The user documentation: README.md is short and links every docs page, every relative link in
the docs resolves, and the generated pages (docs/reference.md, docs/benchmarks.md) match what
their scripts make from the code and from benchmarks/results/ now."""
from __future__ import annotations

import datetime
import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / 'README.md'
DOCS = ROOT / 'docs'


def _script(name):
    """A generator script in scripts/ as a module (scripts/ is not a package)."""
    spec = importlib.util.spec_from_file_location(f'_docs_{name}', ROOT / 'scripts' / f'{name}.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


reference = _script('reference')
benchmarks_page = _script('benchmarks_page')


# ---------------------------------------------------------------------------------------------
# Markdown links
# ---------------------------------------------------------------------------------------------

_FENCE = re.compile(r'^\s*(```|~~~)')
_LINK = re.compile(r'!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+"[^"]*")?\s*\)')
_HEADING = re.compile(r'^(#{1,6})\s+(.*?)\s*#*\s*$')


def _prose_lines(text):
    """The lines outside fenced code blocks, with inline code spans blanked out."""
    fenced = False
    for line in text.splitlines():
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            yield line


def _links(path):
    out = []
    for line in _prose_lines(path.read_text(encoding='utf-8')):
        out += _LINK.findall(re.sub(r'`[^`]*`', '``', line))
    return out


def _slug(heading):
    """GitHub's anchor of a heading: its text (links and code marks removed) in lower case,
    everything but letters, digits, '_', '-' and spaces dropped, spaces to hyphens."""
    text = re.sub(r'!?\[([^\]]*)\]\([^)]*\)', r'\1', heading)
    return re.sub(r'[^\w\- ]', '', text.strip().lower()).replace(' ', '-')


def _anchors(path):
    anchors, counts = set(), {}
    for line in _prose_lines(path.read_text(encoding='utf-8')):
        m = _HEADING.match(line)
        if m:
            slug = _slug(m.group(2))
            n = counts.get(slug, 0)
            counts[slug] = n + 1
            anchors.add(slug if n == 0 else f'{slug}-{n}')
    return anchors


def _user_pages():
    return [README, ROOT / 'CHANGELOG.md'] + sorted(DOCS.rglob('*.md'))


def test_readme_is_short_and_has_the_two_commands():
    lines = README.read_text(encoding='utf-8').splitlines()
    assert len(lines) <= 400, f'README.md has {len(lines)} lines (at most 400): move detail to docs/'
    text = '\n'.join(lines)
    assert 'bash scripts/run.sh' in text and 'bash scripts/test.sh' in text


def test_every_docs_page_is_linked_from_the_readme():
    targets = {(README.parent / t.split('#')[0]).resolve() for t in _links(README)
               if not re.match(r'^[a-z]+:', t) and not t.startswith('#')}
    pages = sorted(DOCS.glob('*.md'))
    assert pages, 'docs/ has no pages'
    unlinked = [p.relative_to(ROOT).as_posix() for p in pages if p.resolve() not in targets]
    assert not unlinked, f'docs pages not linked from README.md: {unlinked}'


@pytest.mark.parametrize('page', _user_pages(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(page):
    broken = []
    for target in _links(page):
        if re.match(r'^[a-z][a-z0-9+.-]*:', target):            # http:, https:, mailto:
            continue
        file_part, _, anchor = target.partition('#')
        dest = (page.parent / file_part).resolve() if file_part else page
        if not dest.exists():
            broken.append(f'{target} (no such file)')
        elif anchor and dest.suffix == '.md' and anchor not in _anchors(dest):
            broken.append(f'{target} (no heading with anchor #{anchor})')
    assert not broken, f'{page.relative_to(ROOT)}: broken links: {broken}'


def test_link_checker_sees_a_broken_link(tmp_path):
    """The checker above is not vacuous: it finds links, skips code, and computes anchors."""
    page = tmp_path / 'p.md'
    page.write_text('# A `b` title, with punctuation!\n## Dup\n## Dup\n'
                    'See [x](missing.md), ![img](pic.png) and `[code](not-a-link.md)`.\n'
                    '```\n[in a fence](also-not.md)\n```\n', encoding='utf-8')
    assert _links(page) == ['missing.md', 'pic.png']
    assert _anchors(page) == {'a-b-title-with-punctuation', 'dup', 'dup-1'}


# ---------------------------------------------------------------------------------------------
# The generated reference
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope='module')
def reference_page():
    return reference.render_page()


def test_the_generated_reference_matches_help(reference_page):
    committed = (DOCS / 'reference.md').read_text(encoding='utf-8')
    assert committed == reference_page, (
        'docs/reference.md does not match the --help of the commands and the integrator '
        'docstring: run `python scripts/reference.py` and commit docs/reference.md')


def test_the_reference_lists_every_command_and_option(reference_page):
    import argparse
    from mi_nerfpp.commands.cli import build_parser
    parser = build_parser()
    commands = list(reference._subcommands(parser))
    assert {name for name, _ in commands} >= {'render', 'optimize', 'synth', 'evaluate', 'video',
                                              'sweep', 'colmap'}
    for name, sub in commands:
        section = reference_page.split(f'## `python -m mi_nerfpp {name}`\n', 1)[1].split('\n## ')[0]
        for action in sub._actions:
            for option in action.option_strings:
                assert option in section, f'{name}: {option} missing from docs/reference.md'
            if not action.option_strings and not isinstance(action, argparse._SubParsersAction):
                assert action.dest in section


def test_the_reference_documents_exactly_the_integrators_parameters(reference_page):
    """Every parameter the plugin accepts is in the docstring's table, and nothing else: the
    plugin names what it takes when given an unknown one."""
    import mitsuba as mi
    with pytest.raises(Exception) as error:
        mi.load_dict({'type': 'nerfpp', 'zz_not_a_parameter': 1})
    m = re.search(r'integrator takes ([\w, ]+)', str(error.value))
    assert m, f'the unknown-parameter error no longer lists the parameters: {error.value}'
    accepted = {name.strip() for name in m.group(1).split(',')}
    documented = {row[0] for row in reference.plugin_parameters(reference.integrator_class().__doc__)}
    assert documented == accepted, (f'undocumented: {sorted(accepted - documented)}, '
                                    f'documented but not accepted: {sorted(documented - accepted)}')
    for name in accepted:
        assert f'| `{name}` |' in reference_page


# Options of other programs that the guides show (oiiotool, ray start, SLURM, scripts/setup.sh)
# and of benchmark scripts; every other --option named in README.md and the guide pages must be one that a
# command of the package accepts.
FOREIGN_OPTIONS = {
    'docs/compositing.md': {'--ch', '--over', '--add', '--tocolorspace', '--flatten',
                            '--deepmerge'},
    'docs/rendering.md': {'--tocolorspace', '--flatten', '--deepmerge',
                          '--cpu-only'},                          # benchmarks/gpu_check.sh
    'docs/testing.md': {'--test'},                                   # scripts/setup.sh --test
    'docs/videos-and-ray.md': {'--head', '--port', '--address', '--node-ip-address', '--num-cpus',
                               '--block', '--nodes', '--ntasks-per-node', '--cpus-per-task',
                               '--exclusive', '--run', '--test'},
}


def test_options_named_in_the_guides_exist():
    from mi_nerfpp.commands.cli import build_parser
    accepted = {option for _, sub in reference._subcommands(build_parser())
                for action in sub._actions for option in action.option_strings}
    generated = {DOCS / 'reference.md', DOCS / 'benchmarks.md'}
    # paper-section-3.md documents the experiment scripts' own options; experiments.md is a
    # record of what was measured, with the options of its day (some since removed) and the
    # benchmark scripts' own
    pages = [README] + [p for p in sorted(DOCS.glob('*.md'))
                        if p not in generated
                        and p.name not in ('paper-section-3.md', 'experiments.md')]
    unknown = {}
    for page in pages:
        name = page.relative_to(ROOT).as_posix()
        named = set(re.findall(r'(?<![\w-])--[a-z][a-z0-9-]*', page.read_text(encoding='utf-8')))
        stale = sorted(named - accepted - FOREIGN_OPTIONS.get(name, set()))
        if stale:
            unknown[name] = stale
    assert not unknown, (f'options no command accepts (renamed or removed?): {unknown}; the '
                         'current ones are in docs/reference.md (python scripts/reference.py)')


def test_plugin_parameter_parsing():
    doc = '''
    Intro.

    .. pluginparameters::

     * - spp
       - |int|
       - Samples per pixel, ``spp`` of the
         sensor. (Default: 4)
     * - name
       - |string|
       - See :meth:`~a.b.set_model` and :data:`LIMIT`; a | bar.
       - |exposed|

    After the list.
    '''
    rows = reference.plugin_parameters(doc)
    assert rows == [['spp', '|int|', 'Samples per pixel, ``spp`` of the sensor. (Default: 4)'],
                    ['name', '|string|', 'See :meth:`~a.b.set_model` and :data:`LIMIT`; a | bar.',
                     '|exposed|']]
    table = reference.parameter_table(rows).splitlines()
    assert table[0] == '| name | type | default | meaning | flags |'
    assert table[2] == '| `spp` | integer | 4 | Samples per pixel, `spp` of the sensor. |  |'
    assert table[3] == ('| `name` | string | – | See `set_model` and `LIMIT`; a \\| bar. '
                        '| exposed |')
    with pytest.raises(ValueError, match='pluginparameters'):
        reference.plugin_parameters('no table here')


def test_help_is_formatted_at_a_fixed_width(monkeypatch):
    monkeypatch.setenv('COLUMNS', '40')
    helps = dict(reference.command_helps())
    assert max(len(line) for text in helps.values() for line in text.splitlines()) <= \
        reference.COLUMNS
    assert any(len(line) > 40 for line in helps['optimize'].splitlines())


# ---------------------------------------------------------------------------------------------
# The generated benchmarks page
# ---------------------------------------------------------------------------------------------

def test_the_benchmarks_page_is_up_to_date():
    committed = (DOCS / 'benchmarks.md').read_text(encoding='utf-8')
    assert committed == benchmarks_page.render_page(), (
        'docs/benchmarks.md does not match benchmarks/results/*.json: run '
        '`python scripts/benchmarks_page.py` and commit docs/benchmarks.md')


MACHINE = {'cpu': 'AMD EPYC 7B13 (2 cores)', 'memory_gib': 24, 'os': 'Debian 12',
           'python': '3.11.7', 'mitsuba': '3.9.1', 'drjit': '1.5.0'}


def _result(benchmark, title, **extra):
    result = {'benchmark': benchmark, 'title': title,
              'command': f'python benchmarks/{benchmark}.py --steps 60',
              'date': '2026-11-25T14:03:00+00:00', 'machine': MACHINE, 'git': 'c93a164',
              'tables': [{'title': 'Median step', 'columns': ['setting', 'median step (ms)',
                                                              'rays/s'],
                          'rows': [['default', 54.2, 18087], ['--batch-rays 4096', 165.66, 24899]],
                          'note': 'Alternating, warm kernels.'}]}
    result.update(extra)
    return result


def _write(folder, name, result):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f'{name}.json').write_text(json.dumps(result), encoding='utf-8')


def test_benchmarks_page_from_result_files(tmp_path):
    import imageio.v3 as iio
    results, page = tmp_path / 'benchmarks' / 'results', tmp_path / 'docs' / 'benchmarks.md'
    _write(results, 'zeta', _result('zeta', 'Zeta check', date='2026-11-26T10:00:00+01:00'))
    _write(results, 'train', _result('train', 'Training throughput', notes='Alone on the machine.',
                                     figures=['train_curve.png'], raw={'secret': 123456789}))
    iio.imwrite(results / 'train_curve.png', np.zeros((4, 4, 3), np.uint8))
    _write(results, 'quality_default', _result('quality', 'Quality at time'))
    text = benchmarks_page.render_page(results, page)

    # Known benchmarks first in their fixed order, then the others alphabetically.
    sections = re.findall(r'^## (.+)$', text, flags=re.M)
    assert sections == ['Quality at time', 'Training throughput', 'Zeta check']
    train = text.split('## Training throughput\n')[1].split('\n## ')[0]
    assert '**Median step**' in train
    assert '| setting | median step (ms) | rays/s |' in train
    assert '| default | 54.2 | 18,087 |' in train
    assert '| --batch-rays 4096 | 165.7 | 24,899 |' in train
    assert 'Alternating, warm kernels.' in train and 'Alone on the machine.' in train
    assert ('`python benchmarks/train.py --steps 60` - 2026-11-25 14:03 UTC, AMD EPYC 7B13 '
            '(2 cores), 24 GiB, Debian 12, Python 3.11.7, Mitsuba 3.9.1, Dr.Jit 1.5.0, git '
            '`c93a164`') in train
    assert '123456789' not in text                       # raw data stays in the JSON
    figure = re.search(r'!\[train_curve.png\]\(([^)]+)\)', train).group(1)
    assert (page.parent / figure).resolve() == (results / 'train_curve.png').resolve()
    source = re.search(r'\[train.json\]\(([^)]+)\)', train).group(1)
    assert (page.parent / source).resolve() == (results / 'train.json').resolve()
    assert '2026-11-26 09:00 UTC' in text                # dates shown in UTC
    assert '[Quality at time](#quality-at-time)' in text

    # The command line writes the same page and then finds it up to date.
    assert benchmarks_page.main(['--results', str(results), '--out', str(page), '--check']) == 1
    assert benchmarks_page.main(['--results', str(results), '--out', str(page)]) == 0
    assert page.read_text(encoding='utf-8') == text
    assert benchmarks_page.main(['--results', str(results), '--out', str(page), '--check']) == 0


def test_the_benchmarks_page_shows_each_kind_once():
    """One section per kind of result in benchmarks/results (a benchmark and its variant): the
    latest file of the kind; every older file is named under "Older results", without tables."""
    results = benchmarks_page.load_results(benchmarks_page.RESULTS)
    assert results, 'benchmarks/results/ has no result files'
    text = (DOCS / 'benchmarks.md').read_text(encoding='utf-8')
    body, _, older = text.partition('\n## Older results\n')
    sections = re.findall(r'^## (.+)$', body, flags=re.M)
    kinds = {}
    for path, result in results:
        kinds.setdefault(benchmarks_page.kind(result), []).append(path)
    assert len(sections) == len(kinds), (sections, sorted(kinds))
    assert {name for name, _ in kinds} == {result['benchmark'] for _, result in results}

    def when(path):
        date = json.loads(path.read_text(encoding='utf-8'))['date'].replace('Z', '+00:00')
        return datetime.datetime.fromisoformat(date).astimezone(datetime.timezone.utc), path.name

    for paths in kinds.values():
        latest, *rest = sorted(paths, key=when, reverse=True)
        assert body.count(f'[{latest.name}](') == 1, f'{latest.name}: not shown once'
        for path in rest:
            assert f'[{path.name}](' not in body and f'[{path.name}](' in older, path.name


def test_benchmarks_page_shows_only_the_latest_result_of_a_kind(tmp_path):
    results, page = tmp_path / 'benchmarks' / 'results', tmp_path / 'docs' / 'benchmarks.md'
    old = _result('held_out', 'Held-out quality', date='2026-11-26T10:30:00+02:00')
    old['tables'][0]['rows'] = [['old run', 11.11, 1111]]
    new = _result('held_out', 'Held-out quality', date='2026-11-26T09:00:00+00:00')
    new['tables'][0]['rows'] = [['new run', 22.22, 2222]]
    # the older file's name sorts last, and its local time reads later: only the date in UTC
    # (08:30 against 09:00) says which is newer
    _write(results, 'held_out_a', new)
    _write(results, 'held_out_z', old)
    text = benchmarks_page.render_page(results, page)
    assert re.findall(r'^## (.+)$', text, flags=re.M) == ['Held-out quality', 'Older results']
    assert '| new run | 22.22 | 2,222 |' in text
    assert 'old run' not in text and '11.11' not in text and '1,111' not in text
    body, older = text.split('## Older results\n')
    assert '[held_out_a.json](' in body and '[held_out_z.json](' not in body
    line = next(l for l in older.splitlines() if '[held_out_z.json](' in l)
    assert '2026-11-26 08:30 UTC' in line and 'Held-out quality' in line
    assert '[Older results](#older-results)' in text
    link = re.search(r'\[held_out_z.json\]\(([^)]+)\)', line).group(1)
    assert (page.parent / link).resolve() == (results / 'held_out_z.json').resolve()


def test_benchmarks_page_keeps_a_section_per_variant(tmp_path):
    """Files of one benchmark that measure different things are different kinds: versus's
    mode, profile's option overrides, or a "variant" key in the file."""
    results = tmp_path / 'results'
    later = '2026-11-26T14:03:00+00:00'
    _write(results, 'versus_train', _result(
        'versus', 'Training throughput', command='python benchmarks/versus.py train --base c93a164'
        ' --rounds 8'))
    _write(results, 'versus_render', _result(
        'versus', 'Render time', date=later, command='python benchmarks/versus.py render --base '
        'c93a164 --base-run A --run B --rounds 7 --name versus_render'))
    _write(results, 'profile', _result('profile', 'Where the time goes',
                                       command='python benchmarks/profile.py --steps 30'))
    _write(results, 'profile_small', _result(
        'profile', 'Where the time goes (small grids)', date=later,
        command="python benchmarks/profile.py --steps 30 --name profile_small "
                "'grid_levels=[32,64]' --at=0.6 'bg_grid_levels=[32,64]'"))
    _write(results, 'held_out_plaza', _result('held_out', 'Held-out quality', variant='plaza512'))
    _write(results, 'held_out_default', _result('held_out', 'Held-out quality', date=later))
    found = {path.stem: benchmarks_page.kind(result)
             for path, result in benchmarks_page.load_results(results)}
    assert found == {'versus_train': ('versus', 'train'), 'versus_render': ('versus', 'render'),
                     'profile': ('profile', ''),
                     'profile_small': ('profile', 'grid_levels=[32,64] bg_grid_levels=[32,64]'),
                     'held_out_plaza': ('held_out', 'plaza512'),
                     'held_out_default': ('held_out', '')}
    text = benchmarks_page.render_page(results, tmp_path / 'benchmarks.md')
    assert re.findall(r'^## (.+)$', text, flags=re.M) == [
        'Render time', 'Training throughput', 'Held-out quality', 'Held-out quality (plaza512)',
        'Where the time goes', 'Where the time goes (small grids)']
    assert 'Older results' not in text


def test_benchmarks_page_without_results(tmp_path):
    text = benchmarks_page.render_page(tmp_path / 'results', tmp_path / 'benchmarks.md')
    assert '## No results yet' in text and 'python scripts/benchmarks_page.py' in text
    assert not re.search(r'\d+\.\d+ (dB|ms|s)\b', text)


@pytest.mark.parametrize('change, message', [
    (lambda r: r.pop('command'), "missing 'command'"),
    (lambda r: r.update(date='yesterday'), 'not ISO 8601'),
    (lambda r: r.update(figures=['absent.png']), "figure 'absent.png' is not in"),
    (lambda r: r['tables'][0]['rows'].append([1, 2]), 'row 2 has 2 cells for 3 columns'),
    (lambda r: r.update(tables=[]), 'non-empty list of tables'),
    (lambda r: r.update(variant=' '), '"variant", when present, must be a non-empty string'),
])
def test_benchmarks_page_refuses_bad_result_files(tmp_path, change, message):
    result = _result('train', 'Training throughput')
    change(result)
    _write(tmp_path, 'train', result)
    with pytest.raises(benchmarks_page.ResultError, match=re.escape(message)) as error:
        benchmarks_page.render_page(tmp_path, tmp_path / 'page.md')
    assert 'train.json' in str(error.value)


def test_number_formatting():
    f = benchmarks_page.format_number
    assert [f(v) for v in (18087, 54.2, 26.987, 0.7723, 0.0123, 0.00012, 1234.5, 0.0, None,
                           True, 'n/a', float('inf'))] == \
        ['18,087', '54.2', '26.99', '0.7723', '0.0123', '0.00012', '1,234', '0', '–', 'yes',
         'n/a', '∞']
