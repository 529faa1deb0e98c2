"""The package's modules import each other without a cycle and never from a higher layer: data
flows one way, and the folders show the layers (``LAYERS``). Imports sit at module level, except
the few that say why they wait (``# deferred: <reason>``).

The graph is read from the source with ``ast`` (nothing is imported): every ``import`` and
``from ... import`` of a module of the package, at module level or inside a function (an
import deferred into a function is still a dependency, only a later one), is an edge to the
module it names - ``from .data import load_dataset`` to ``mi_nerfpp.data``, ``from . import
optim`` to ``mi_nerfpp.training.optim``. An import of one of the module's own ancestor packages (``from
. import __version__`` in ``mi_nerfpp/files/exr.py``, ``from . import positive_int`` in a command)
is not an edge: Python has set up the ancestor packages before the module runs, so such an
import starts no import of its own.
"""
import ast
import os
import re

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def modules(root, package):
    """``{module name: path}`` of every ``.py`` file of ``package`` under ``root``."""
    out = {}
    for folder, _, files in os.walk(os.path.join(root, package)):
        for name in files:
            if name.endswith('.py'):
                path = os.path.join(folder, name)
                parts = os.path.relpath(path, root)[:-3].split(os.sep)
                if parts[-1] == '__init__':
                    parts = parts[:-1]
                out['.'.join(parts)] = path
    return out


def import_graph(root, package):
    """``{module: set of the package's modules it imports}`` (see the module docstring)."""
    found = modules(root, package)
    graph = {}
    for module, path in found.items():
        with open(path, encoding='utf-8') as f:
            tree = ast.parse(f.read(), path)
        is_package = path.endswith('__init__.py')
        here = module if is_package else module.rpartition('.')[0]
        named = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                named.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = here.split('.')
                    base = base[:len(base) - node.level + 1]
                    target = '.'.join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ''
                for alias in node.names:        # a submodule, or a name of the module
                    sub = f'{target}.{alias.name}'
                    named.add(sub if sub in found else target)
        ancestors = {module.rsplit('.', n)[0] for n in range(1, module.count('.') + 1)}
        graph[module] = {m for m in named if m in found and m != module and m not in ancestors}
    return graph


def find_cycle(graph):
    """A cycle of the graph as a list of modules (first = last), or None."""
    state, stack = {}, []

    def visit(node):
        state[node] = 'open'
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 'open':
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                cycle = visit(nxt)
                if cycle:
                    return cycle
        state[node] = 'done'
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return None


# The package's folders, lowest first: a module imports from its own layer or lower ones. The
# root's ``_llvm``, ``_start``, ``errors``, ``variant`` and ``version`` lie below every folder;
# ``mi_nerfpp`` itself (the package's facade, which registers the integrator) and ``__main__``
# above them.
LAYERS = ('core', 'files', 'integrator', 'data', 'output', 'training', 'jobs', 'commands')
DEFERRED = re.compile(r'#.*\bdeferred: \S')


def layer(module):
    """The layer index of a module of the package (see :data:`LAYERS`)."""
    parts = module.split('.')
    if len(parts) == 1 or parts[1] == '__main__':
        return len(LAYERS)
    if parts[1] in LAYERS:
        return LAYERS.index(parts[1])
    return -1                                  # _llvm, _start, errors, variant, version


def upward_imports(graph):
    """``[(module, imported module)]`` of every import from a higher layer."""
    return sorted((m, t) for m, targets in graph.items() for t in targets if layer(t) > layer(m))


def test_the_package_has_no_import_cycle():
    graph = import_graph(ROOT, 'mi_nerfpp')
    assert len(graph) > 40 and 'mi_nerfpp.jobs.run' in graph['mi_nerfpp.commands.optimize']
    assert 'mi_nerfpp.files.checkpoint' in graph['mi_nerfpp.training.train']
    cycle = find_cycle(graph)
    assert cycle is None, ' -> '.join(cycle)


def _write(root, files):
    for name, text in files.items():
        path = os.path.join(root, name)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, 'w') as f:
            f.write(text)


def test_a_cycle_through_a_function_level_import_is_found(tmp_path):
    _write(tmp_path, {
        'pkg/__init__.py': 'from . import a\n__version__ = "1"\n',
        'pkg/a.py': 'from . import __version__\nfrom .sub import b\n',      # the ancestor: no edge
        'pkg/sub/__init__.py': '',
        'pkg/sub/b.py': 'def later():\n    from ..c import thing\n    return thing\n',
        'pkg/c.py': 'import os\nimport pkg.sub\nthing = 1\n',
    })
    graph = import_graph(str(tmp_path), 'pkg')
    assert graph['pkg.a'] == {'pkg.sub.b'} and graph['pkg.sub.b'] == {'pkg.c'}
    assert find_cycle(graph) is None            # c imports the package sub, not b
    _write(tmp_path, {'pkg/c.py': 'import pkg.a\nthing = 1\n'})
    cycle = find_cycle(import_graph(str(tmp_path), 'pkg'))
    assert cycle == ['pkg.a', 'pkg.sub.b', 'pkg.c', 'pkg.a']


def test_no_module_imports_from_a_higher_layer():
    graph = import_graph(ROOT, 'mi_nerfpp')
    placed = {m: layer(m) for m in graph}
    misplaced = [m for m, i in placed.items() if i == -1
                 and m not in ('mi_nerfpp._llvm', 'mi_nerfpp._start', 'mi_nerfpp.errors',
                               'mi_nerfpp.variant', 'mi_nerfpp.version')]
    assert not misplaced, f'modules outside the layer folders {LAYERS}: {misplaced}'
    assert upward_imports(graph) == []


def test_an_upward_import_is_found():
    graph = {'mi_nerfpp.core.model': {'mi_nerfpp.training.config'},
             'mi_nerfpp.training.config': {'mi_nerfpp.core.model'}}
    assert upward_imports(graph) == [('mi_nerfpp.core.model', 'mi_nerfpp.training.config')]


def deferred_imports(path):
    """``[(line, text, has a reason)]`` of the imports inside functions of one file."""
    with open(path, encoding='utf-8') as f:
        text = f.read()
    lines = text.split('\n')
    found = []
    for node in ast.walk(ast.parse(text, path)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for sub in ast.walk(node):
                if isinstance(sub, (ast.Import, ast.ImportFrom)):
                    line = lines[sub.end_lineno - 1]
                    found.append((sub.lineno, lines[sub.lineno - 1].strip(),
                                  bool(DEFERRED.search(line))))
    return found


def test_imports_sit_at_module_level_unless_they_say_why():
    missing = [f'{os.path.relpath(path, ROOT)}:{line}: {text}'
               for path in modules(ROOT, 'mi_nerfpp').values()
               for line, text, reason in deferred_imports(path) if not reason]
    assert not missing, ('imports inside functions without a "# deferred: <reason>" comment '
                         '(move them to the top of the module):\n' + '\n'.join(missing))


def test_a_deferred_import_without_a_reason_is_found(tmp_path):
    path = tmp_path / 'm.py'
    path.write_text('import os\n\ndef f():\n    import ray  # deferred: an optional extra\n'
                    '    import json\n    return json\n')
    assert deferred_imports(str(path)) == [(4, 'import ray  # deferred: an optional extra', True),
                                           (5, 'import json', False)]


def test_every_module_says_its_job_in_its_first_docstring_line():
    missing = []
    for module, path in modules(ROOT, 'mi_nerfpp').items():
        with open(path, encoding='utf-8') as f:
            doc = ast.get_docstring(ast.parse(f.read(), path))
        if not doc or not doc.strip().splitlines()[0].strip():
            missing.append(module)
    assert not missing, f'modules without a one-line docstring of their job: {missing}'
