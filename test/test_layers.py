"""Import arrows point down: no ROS below the node, benchmarks do not import tools, tools do not import each
other (shared pieces live in the client package below them: client/node_process.py, client/ros_io.py,
client/replay.py), the client package imports neither, and the entry point imports only the standard library before
it has installed its signal handlers."""
import ast
import pathlib
import sys

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / 'dpv_sensor'
ROS_PACKAGES = {'rclpy', 'rcl_interfaces', 'sensor_msgs', 'nav_msgs', 'geometry_msgs', 'diagnostic_msgs',
                'std_msgs', 'builtin_interfaces'}
# layers 1-6 and the ROS-free pieces of the node (DESIGN.md)
NO_ROS = ['geometry.py', 'dpv.py', 'params.py', 'cli.py', 'common.py', 'continuity.py', 'filter.py', 'keyframes.py',
          'poses.py', 'photometric.py', 'classical.py', 'estimator.py', 'pipeline.py', 'frame.py', 'node_support.py',
          'entry.py', 'process_memory.py', 'pose_buffer.py', 'metrics.py', 'evaluation.py']
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


def test_no_ros_below_the_node():
    offenders = [f'{name}: {m}' for name in NO_ROS for m in _imports(PACKAGE / name)
                 if m.split('.')[0] in ROS_PACKAGES]
    nets = [f'{p.name}: {m}' for p in (PACKAGE / 'nets').glob('*.py') for m in _imports(p)
            if m.split('.')[0] in ROS_PACKAGES]
    assert not offenders + nets


def test_benchmarks_do_not_import_tools():
    offenders = [f'{p.name}: {m}' for p in (PACKAGE / 'benchmarks').glob('*.py') for m in _imports(p)
                 if m.startswith('dpv_sensor.tools')]
    assert not offenders


def test_client_imports_neither_tools_nor_benchmarks():
    offenders = [f'{p.name}: {m}' for p in (PACKAGE / 'client').glob('*.py') for m in _imports(p)
                 if m.startswith(('dpv_sensor.tools', 'dpv_sensor.benchmarks'))]
    assert not offenders


def _module_of(name: str) -> str:
    """The module an imported name lives in: ``dpv_sensor.tools.bag.BagPlayer`` -> ``dpv_sensor.tools.bag``."""
    parts = name.split('.')
    for n in range(len(parts), 0, -1):
        path = PACKAGE.parent.joinpath(*parts[:n])
        if path.with_suffix('.py').is_file() or (path / '__init__.py').is_file():
            return '.'.join(parts[:n])
    return name


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
    heavy = [m for m in _imports(PACKAGE / 'entry.py', top_level_only=True) if m.split('.')[0] not in stdlib]
    assert heavy == []
    # and node.py, run as __main__, calls the entry point before any other import
    tree = ast.parse((PACKAGE / 'node.py').read_text())
    first_import = next(n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom, ast.If))
                        and not (isinstance(n, ast.ImportFrom) and n.module == '__future__'))
    assert isinstance(first_import, ast.If) and "__name__ == '__main__'" in ast.unparse(first_import.test)
