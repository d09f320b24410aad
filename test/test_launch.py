"""The launch file and the shipped params file: what can be checked without the `launch` packages (not on PyPI).

- launch/dpv_sensor.launch.py parses, is installed by setup.py, names the installed executable and an existing
  params file; its remappings (drivers, overrides, free-form pairs) and parameter arguments come out as the node
  expects them, and the argument list it builds, run as the node's command line, gives the node those parameters
  and topics;
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
    assert _setup_tools()[launch_module.EXECUTABLE] == 'dpv_sensor.ros.entry:console_main'
    params = REPO / launch_module.PARAMS_FILE
    assert params.is_file()
    assert '/**' in yaml.safe_load(params.read_text())
    from dpv_sensor.ros.node import NODE_NAME
    source = LAUNCH.read_text()
    assert 'name=PACKAGE' in source and NODE_NAME == launch_module.PACKAGE


def test_remappings_drivers_overrides_and_extra_pairs(launch_module):
    remappings = launch_module.remappings
    assert remappings() == []
    assert remappings('realsense') == [('image', '/camera/camera/color/image_raw'),
                                       ('camera_info', '/camera/camera/color/camera_info')]
    assert remappings('zed') == [('image', '/zed/zed_node/rgb/color/rect/image'),
                                 ('camera_info', '/zed/zed_node/rgb/color/rect/camera_info'),
                                 ('odom', '/zed/zed_node/odom')]
    assert remappings('realsense', odom='/odometry/filtered')[-1] == ('odom', '/odometry/filtered')
    # an image of its own without camera_info: the node takes the image's sibling, not the driver's camera_info
    assert remappings('zed', image='/zed/zed_node/rgb/color/raw/image') == \
        [('image', '/zed/zed_node/rgb/color/raw/image'), ('odom', '/zed/zed_node/odom')]
    assert remappings(remaps='depth/image:=/dpv/depth  depth/points:=/dpv/points') == \
        [('depth/image', '/dpv/depth'), ('depth/points', '/dpv/points')]
    for name, target in remappings('zed', remaps='pose:=/cam_pose'):
        assert name and target and ':=' not in name + target


def test_parameter_arguments_reach_the_node_parameters_typed_and_checked(launch_module):
    parameters = launch_module.parameters
    assert parameters() == {}
    # the network preset is a node parameter (the driver's topics are the driver argument)
    assert parameters(preset='paper', window_mode='causal') == {'preset': 'paper', 'window_mode': 'causal'}
    assert parameters('zed')['T_base_camera'] == launch_module.ZED_OPTICAL_IN_CAMERA_LINK
    assert parameters('zed', T_base_camera='[0.1,0,0.2,0,0,0,1]')['T_base_camera'] == [0.1, 0, 0.2, 0, 0, 0, 1]
    assert parameters(params='damping:=0.5 publish_tf:=true') == {'damping': 0.5, 'publish_tf': True}


@pytest.mark.parametrize('call,message', [
    (lambda m: m.remappings('kinect'), "driver 'kinect' is not one of"),
    (lambda m: m.remappings(remaps='image=/x'), "remap 'image=/x' is not of the form from:=to"),
    (lambda m: m.remappings(remaps='image:='), "remap 'image:=' is not of the form from:=to"),
    (lambda m: m.parameters(preset='huge'), "parameter 'preset' = 'huge' is not one of"),
    (lambda m: m.parameters(T_base_camera='[0,0,0,0,0,0,2]'), 'quaternion .* is not unit length'),
    (lambda m: m.parameters(params='damping:=3'), "parameter 'damping' = 3.0 is above its maximum 1.0"),
    (lambda m: m.parameters(params='dampening:=0.3'), "unknown parameter 'dampening'"),
])
def test_bad_launch_arguments_are_refused_with_the_reason(launch_module, call, message):
    from dpv_sensor.params import ParameterError
    with pytest.raises((ValueError, ParameterError), match=message):
        call(launch_module)


def test_launch_arguments_give_the_node_its_parameters_and_remaps(launch_module, observer):
    """The argument list the launch file builds, run as the node's command line: parameters read back over the
    parameter service, topics from the graph."""
    from rcl_interfaces.srv import GetParameters
    config = launch_module.node_configuration({
        'namespace': 'cam', 'params_file': str(REPO / launch_module.PARAMS_FILE), 'driver': 'zed',
        'preset': 'paper', 'window_mode': 'causal', 'measurement': 'classical', 'params': 'damping:=0.5',
        'remaps': 'depth/image:=/dpv/depth', 'log_level': 'warn'})
    assert config['ros_arguments'] == ['--log-level', 'warn']
    node, executor = observer
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    names = ['preset', 'window_mode', 'T_base_camera', 'measurement', 'damping', 'keyframe_max_interval']
    client = node.create_client(GetParameters, '/cam/dpv_sensor/get_parameters')
    proc = start_node(launch_module.ros_args(config))

    def topics(kind):
        try:
            get = node.get_subscriber_names_and_types_by_node if kind == 'sub' else \
                node.get_publisher_names_and_types_by_node
            return {name for name, _ in get('dpv_sensor', '/cam')}
        except Exception:   # not in the graph yet
            return set()
    subs_want = {'/zed/zed_node/rgb/color/rect/image', '/zed/zed_node/rgb/color/rect/camera_info', '/zed/zed_node/odom'}
    pubs_want = {'/dpv/depth', '/dpv/camera_info', '/cam/rgb/image', '/cam/depth/points'}
    try:
        assert wait_for(client.service_is_ready, timeout=60.0, spin=spin), 'no parameter service in /cam'
        future = client.call_async(GetParameters.Request(names=names))
        assert wait_for(future.done, timeout=20.0, spin=spin)
        got = future.result().values
        graph = wait_for(lambda: subs_want <= topics('sub') and pubs_want <= topics('pub'), timeout=30.0, spin=spin)
        subs, pubs = topics('sub'), topics('pub')
    finally:
        code, out = stop_process(proc)
    assert code == 0, out
    assert graph, (sorted(subs), sorted(pubs))
    assert [got[0].string_value, got[1].string_value, list(got[2].double_array_value), got[3].string_value,
            got[4].double_value, got[5].integer_value] == \
        ['paper', 'causal', launch_module.ZED_OPTICAL_IN_CAMERA_LINK, 'classical', 0.5, 5], out
    assert ' INFO' not in out and '[INFO]' not in out, out      # log_level warn


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
