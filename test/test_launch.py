"""The launch file and the shipped params file: what can be checked without the `launch` packages (not on PyPI).

- launch/dpv_sensor.launch.py parses, is installed by setup.py, names the installed executable and an existing
  params file, and its remappings (presets, overrides, free-form pairs) come out as the node expects them;
- config/dpv_sensor.yaml is keyed `/**`: a node started in a namespace with the file (one value changed) has
  that value, read back over its parameter service.
"""
import ast
import importlib.util
import pathlib

import pytest
import yaml

from ros_helpers import start_node, stop_process, wait_for

REPO = pathlib.Path(__file__).resolve().parents[1]
LAUNCH = REPO / 'launch' / 'dpv_sensor.launch.py'


@pytest.fixture(scope='module')
def launch_module():
    spec = importlib.util.spec_from_file_location('dpv_sensor_launch', LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)        # imports no `launch` package at module level
    return module


def _setup_tools() -> dict:
    """TOOLS of setup.py (the console_scripts entry points), read without running setup()."""
    tree = ast.parse((REPO / 'setup.py').read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, 'id', '') == 'TOOLS' for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError('setup.py has no TOOLS table')


def test_launch_file_parses_and_is_installed():
    ast.parse(LAUNCH.read_text())
    setup = (REPO / 'setup.py').read_text()
    assert "('share/' + PACKAGE + '/launch', glob('launch/*.launch.py'))" in setup


def test_launch_file_names_the_installed_executable_and_an_existing_params_file(launch_module):
    assert launch_module.PACKAGE == 'dpv_sensor'
    assert _setup_tools()[launch_module.EXECUTABLE] == 'dpv_sensor.entry:console_main'
    params = REPO / launch_module.PARAMS_FILE
    assert params.is_file()
    assert '/**' in yaml.safe_load(params.read_text())
    from dpv_sensor.node import NODE_NAME
    source = LAUNCH.read_text()
    assert 'name=PACKAGE' in source and NODE_NAME == launch_module.PACKAGE


def test_remappings_presets_overrides_and_extra_pairs(launch_module):
    remappings = launch_module.remappings
    assert remappings() == []
    assert remappings('realsense') == [('image', '/camera/camera/color/image_raw'),
                                       ('camera_info', '/camera/camera/color/camera_info')]
    assert remappings('zed') == [('image', '/zed/zed_node/rgb/color/rect/image'),
                                 ('camera_info', '/zed/zed_node/rgb/color/rect/camera_info'),
                                 ('odom', '/zed/zed_node/odom')]
    assert remappings('realsense', odom='/odometry/filtered')[-1] == ('odom', '/odometry/filtered')
    assert remappings('zed', image='/zed/zed_node/rgb/color/raw/image')[0] == \
        ('image', '/zed/zed_node/rgb/color/raw/image')
    assert remappings(remaps='depth/image:=/dpv/depth  depth/points:=/dpv/points') == \
        [('depth/image', '/dpv/depth'), ('depth/points', '/dpv/points')]
    for name, target in remappings('zed', remaps='pose:=/cam_pose'):
        assert name and target and ':=' not in name + target


@pytest.mark.parametrize('kwargs,message', [
    ({'preset': 'kinect'}, "preset 'kinect' is not one of"),
    ({'remaps': 'image=/x'}, "remap 'image=/x' is not of the form from:=to"),
    ({'remaps': 'image:='}, "remap 'image:=' is not of the form from:=to"),
])
def test_remappings_reject_bad_arguments_with_the_reason(launch_module, kwargs, message):
    with pytest.raises(ValueError, match=message):
        launch_module.remappings(**kwargs)


def test_params_file_applies_in_a_namespace(tmp_path, observer):
    from rcl_interfaces.srv import GetParameters
    doc = yaml.safe_load((REPO / 'config' / 'dpv_sensor.yaml').read_text())
    values = doc['/**']['ros__parameters']
    assert values['keyframe_max_interval'] == 5
    values.update(keyframe_max_interval=7, measurement='classical')   # classical: no weights to load
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump(doc))
    node, executor = observer
    client = node.create_client(GetParameters, '/cam/dpv_sensor/get_parameters')
    proc = start_node(['--ros-args', '-r', '__ns:=/cam', '--params-file', str(params)])
    try:
        assert wait_for(client.service_is_ready, timeout=60.0, spin=lambda t: executor.spin_once(timeout_sec=t)), \
            'the node in /cam never offered its parameter service'
        future = client.call_async(GetParameters.Request(names=['keyframe_max_interval', 'measurement']))
        assert wait_for(future.done, timeout=20.0, spin=lambda t: executor.spin_once(timeout_sec=t))
        got = future.result().values
    finally:
        code, out = stop_process(proc)
    assert code == 0, out
    assert [got[0].integer_value, got[1].string_value] == [7, 'classical'], out
