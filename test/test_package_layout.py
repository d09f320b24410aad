"""`colcon build` produces the layout `ros2 run dpv_sensor node` relies on."""
import os
import pathlib
import shutil
import subprocess
import sys

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
VENV_BIN = pathlib.Path(sys.executable).parent


@pytest.fixture(scope='module')
def install_prefix(tmp_path_factory):
    colcon = shutil.which('colcon', path=str(VENV_BIN)) or shutil.which('colcon')
    if colcon is None:
        pytest.fail('colcon is not installed in the test environment (requirements.txt pins it)')
    work = tmp_path_factory.mktemp('colcon')
    # Build from a copy of the sources so colcon leaves nothing behind in the checkout.
    src = work / 'src' / 'dpv_sensor'
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(
        '.venv', '.git', 'build', 'install', 'log', 'out', '__pycache__', '*.egg-info', '.pytest_cache', '.ruff'))
    env = dict(os.environ, PATH=f'{VENV_BIN}{os.pathsep}{os.environ["PATH"]}')
    result = subprocess.run(
        [colcon, '--log-base', str(work / 'log'), 'build', '--base-paths', str(work / 'src'),
         '--build-base', str(work / 'build'), '--install-base', str(work / 'install')],
        cwd=work, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    return work / 'install'


def _sourced(install: pathlib.Path, command: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ('PYTHONPATH', 'AMENT_PREFIX_PATH')}
    env['PATH'] = f'{VENV_BIN}{os.pathsep}{os.environ["PATH"]}'
    return subprocess.run(['bash', '-c', f'. "{install}/setup.sh" && {command}'], env=env, cwd='/',
                          capture_output=True, text=True, timeout=120)


def test_ament_index_finds_the_package_and_its_executable(install_prefix):
    script = ("from ament_index_python.packages import get_package_prefix, get_package_share_directory;"
              "print(get_package_prefix('dpv_sensor')); print(get_package_share_directory('dpv_sensor'))")
    result = _sourced(install_prefix, f'"{VENV_BIN}/python" -c "{script}"')
    assert result.returncode == 0, result.stderr
    prefix, share = result.stdout.split()
    prefix, share = pathlib.Path(prefix), pathlib.Path(share)
    assert prefix == install_prefix / 'dpv_sensor'
    node = prefix / 'lib' / 'dpv_sensor' / 'node'
    assert node.is_file() and os.access(node, os.X_OK)
    assert (share / 'package.xml').is_file()
    assert (share / 'config' / 'dpv_sensor.yaml').is_file()
    assert (share / 'launch' / 'dpv_sensor.launch.py').is_file()
    marker = prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'dpv_sensor'
    assert marker.is_file()


def test_installed_node_runs_its_self_check(install_prefix):
    # This is what `ros2 run dpv_sensor node --check` executes: lib/<package>/<executable> in the prefix.
    result = _sourced(install_prefix, f'"{install_prefix}/dpv_sensor/lib/dpv_sensor/node" --check')
    assert result.returncode == 0, result.stdout + result.stderr
    assert 'self-check ok' in result.stdout
    for module in ('rclpy', 'torch', 'cv2', 'gtsam', 'tf2_msgs.msg'):
        assert module in result.stdout


def test_installed_node_imports_the_installed_package(install_prefix):
    result = _sourced(install_prefix, f'"{VENV_BIN}/python" -c "import dpv_sensor; print(dpv_sensor.__file__)"')
    assert result.returncode == 0, result.stderr
    assert str(install_prefix) in result.stdout
