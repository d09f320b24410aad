"""The subpackages are the layers (dpv_sensor/__init__.py): imports point down only, no ROS below the adapter, no
import cycle between modules, benchmarks do not import tools or studies, studies and tools do not import each other,
tools do not import each other (shared pieces live in the client package below them), and the entry point imports
only the standard library before it has installed its signal handlers."""
import ast
import pathlib
import sys

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / 'dpv_sensor'
ROS_PACKAGES = {'rclpy', 'rcl_interfaces', 'sensor_msgs', 'nav_msgs', 'geometry_msgs', 'diagnostic_msgs',
                'std_msgs', 'builtin_interfaces', 'tf2_msgs'}
# The layers from the ground up; a package imports only from a lower rank or from itself. The studies (the one-off
# measurements behind the docs' figures) sit on the benchmarks, whose pieces they use (the stream table's pose
# sources, the held-out loader), beside the tools: neither of those two imports the other.
GROUND = ('params', 'cli', 'common')
RANK = {'core': 1, 'stream': 2, 'ros': 3, 'data': 4, 'evaluation': 5, 'client': 6, 'training': 6,
        'benchmarks': 7, 'studies': 8, 'tools': 8}
# Packages that never import ROS, and the ROS adapter's modules that must stay importable without it.
NO_ROS_PACKAGES = ('core', 'stream', 'data', 'evaluation', 'training')
NO_ROS_ADAPTER = ('entry.py', 'startup.py', 'msgs.py', 'cloud_msgs.py', 'compressed_depth.py', 'compressed_image.py',
                  'fault_kinds.py', 'node_support.py', 'process_memory.py', 'receipt.py', 'sequence_numbers.py',
                  'stream_loss.py',
                  'topic_names.py', 'transport.py', 'worker.py')
SHARED_TOOL_MODULES = {'dpv_sensor.tools'}


def _imports(path: pathlib.Path, top_level_only: bool = False):
    """Absolute module names a file imports (relative imports resolved)."""
    tree = ast.parse(path.read_text())
    rel = path.relative_to(PACKAGE.parent).with_suffix('')
    package = list(rel.parts[:-1])
    nodes = tree.body if top_level_only else ast.walk(tree)
    for node in nodes:
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                module = '.'.join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ''
            yield module
            for a in node.names:
                yield f'{module}.{a.name}'


def _module_of(name: str) -> str:
    """The module an imported name lives in: ``dpv_sensor.tools.bag.BagPlayer`` -> ``dpv_sensor.tools.bag``."""
    parts = name.split('.')
    for n in range(len(parts), 0, -1):
        path = PACKAGE.parent.joinpath(*parts[:n])
        if path.with_suffix('.py').is_file() or (path / '__init__.py').is_file():
            return '.'.join(parts[:n])
    return name


def _layer(module: str) -> str:
    """``dpv_sensor.stream.estimator`` -> ``stream``; a ground-floor module -> ``ground``; the package -> ``''``."""
    parts = module.split('.')
    if len(parts) < 2:
        return ''
    return 'ground' if parts[1] in GROUND else parts[1]


def _sources():
    for path in sorted(PACKAGE.rglob('*.py')):
        yield path, '.'.join(path.relative_to(PACKAGE.parent).with_suffix('').parts).removesuffix('.__init__')


def test_every_package_is_a_layer():
    folders = {p.parent.name for p in PACKAGE.glob('*/__init__.py')}
    assert folders == set(RANK)
    flat = {p.stem for p in PACKAGE.glob('*.py')} - {'__init__'}
    assert flat == set(GROUND)


def test_imports_point_down():
    offenders = []
    for path, module in _sources():
        own = _layer(module)
        for name in _imports(path):
            if not name.startswith('dpv_sensor.'):
                continue
            other = _layer(_module_of(name))
            if other in ('', own):
                continue
            if own == 'ground' or (other != 'ground' and RANK[other] >= RANK.get(own, 0)):
                offenders.append(f'{module} -> {name}')
    assert not offenders


def test_no_ros_below_the_adapter():
    paths = [p for pkg in NO_ROS_PACKAGES for p in (PACKAGE / pkg).rglob('*.py')]
    paths += [PACKAGE / 'ros' / name for name in NO_ROS_ADAPTER] + [PACKAGE / f'{g}.py' for g in GROUND]
    offenders = [f'{p.relative_to(PACKAGE)}: {m}' for p in paths for m in _imports(p)
                 if m.split('.')[0] in ROS_PACKAGES]
    assert not offenders


def test_no_import_cycle():
    """Between modules, lazy (function-level) imports included; a package's ``__init__`` re-exporting its own
    modules is not an edge."""
    graph = {}
    for path, module in _sources():
        edges = {_module_of(n) for n in _imports(path) if n.startswith('dpv_sensor.')}
        graph[module] = {e for e in edges if e != module and not module.startswith(e + '.')
                         and not (path.name == '__init__.py' and e.startswith(module + '.'))}
    state, cycles = {}, []

    def visit(node, stack):
        state[node] = 'open'
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 'open':
                cycles.append(' -> '.join(stack[stack.index(nxt):] + [node, nxt]) if nxt in stack
                              else f'{node} -> {nxt}')
            elif nxt not in state:
                visit(nxt, stack + [node])
        state[node] = 'done'

    for node in sorted(graph):
        if node not in state:
            visit(node, [])
    assert cycles == []


def test_benchmarks_do_not_import_tools():
    offenders = [f'{p.parent.name}/{p.name}: {m}' for pkg in ('benchmarks', 'studies')
                 for p in (PACKAGE / pkg).glob('*.py') for m in _imports(p) if m.startswith('dpv_sensor.tools')]
    assert not offenders


def test_benchmarks_do_not_import_studies():
    """A benchmark a user runs stands without the one-off studies; a study may use a benchmark's pieces."""
    offenders = [f'{p.name}: {m}' for p in (PACKAGE / 'benchmarks').glob('*.py') for m in _imports(p)
                 if m.startswith('dpv_sensor.studies')]
    assert not offenders


def test_tools_do_not_import_each_other():
    offenders = []
    for p in (PACKAGE / 'tools').glob('*.py'):
        own = f'dpv_sensor.tools.{p.stem}'
        for m in _imports(p):
            module = _module_of(m)
            if module.startswith('dpv_sensor.tools.') and module not in SHARED_TOOL_MODULES and module != own:
                offenders.append(f'{p.name}: {module}')
    # the demo runs evaluate and fuse through their main(): the one sanctioned tool-to-tool call
    sanctioned = ('demo.py: dpv_sensor.tools.evaluate', 'demo.py: dpv_sensor.tools.fuse')
    offenders = [o for o in offenders if o not in sanctioned]
    assert not offenders


def test_entry_point_imports_only_the_standard_library_first():
    stdlib = set(sys.stdlib_module_names)
    # the console script imports only the start-up steps, and they only the standard library
    startup = {'dpv_sensor.ros', 'dpv_sensor.ros.startup'}
    heavy = [m for m in _imports(PACKAGE / 'ros' / 'entry.py', top_level_only=True)
             if m.split('.')[0] not in stdlib and m not in startup]
    heavy += [m for m in _imports(PACKAGE / 'ros' / 'startup.py', top_level_only=True) if m.split('.')[0] not in stdlib]
    assert heavy == []
    for init in (PACKAGE / '__init__.py', PACKAGE / 'ros' / '__init__.py'):     # imported on the way
        assert list(_imports(init, top_level_only=True)) == []
    # and node.py, run as __main__, runs the start-up steps before any other import
    tree = ast.parse((PACKAGE / 'ros' / 'node.py').read_text())
    first_import = next(n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom, ast.If))
                        and not (isinstance(n, ast.ImportFrom) and n.module == '__future__'))
    assert isinstance(first_import, ast.If) and "__name__ == '__main__'" in ast.unparse(first_import.test)
    assert 'dpv_sensor.ros.startup' in ast.unparse(first_import)
