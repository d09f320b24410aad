"""The node runs as its own process, shows up in the ROS graph and stops cleanly on SIGINT and SIGTERM."""
import os
import signal

import pytest

from ros_helpers import forked_node_starts, start_node, stop_process, wait_for
from dpv_sensor.ros.node import NODE_NAME




def _visible(node, name: str = NODE_NAME) -> bool:
    return any(n == name for n, _ns in node.get_node_names_and_namespaces())


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_node_joins_graph_and_stops_cleanly(observer, sig):
    """The node under a name of its own (remapped), so that only its own leaving is waited for: another test's
    node of the default name in this worker's domain cannot stand in for it."""
    node, executor = observer
    name = f'{NODE_NAME}_{sig.name.lower()}_{os.getpid()}'
    proc = start_node(['--ros-args', '-r', f'__node:={name}'])
    try:
        seen = wait_for(lambda: _visible(node, name), timeout=20.0,
                        spin=lambda t: executor.spin_once(timeout_sec=t))
        assert proc.poll() is None, 'node exited early:\n' + stop_process(proc)[1]
        assert seen, 'node never appeared in the ROS graph'
    finally:
        code, out = stop_process(proc, sig)
    assert code == 0, out
    assert 'starting (building the estimator)' in out
    assert 'Traceback' not in out, out
    # A clean exit announces the participant's end; where that message is lost (seen twice under a loaded suite),
    # the peer drops it when its lease runs out. Fast DDS's default lease is 20 s, counted from the last
    # announcement it heard and noticed some time after it runs out: 30 s was once too short.
    gone = wait_for(lambda: not _visible(node, name), timeout=45.0,
                    spin=lambda t: executor.spin_once(timeout_sec=t))
    assert gone, f'node still listed in the graph after it stopped: {node.get_node_names_and_namespaces()}'


def test_off_on_the_command_line_turns_a_setting_off(observer):
    """`-p pose_refinement:=off` reaches rclpy as the boolean False (YAML); the node takes it as the choice 'off'."""
    from rcl_interfaces.srv import GetParameters
    node, executor = observer
    proc = start_node(['--ros-args', '-p', 'pose_refinement:=off'])
    try:
        spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
        client = node.create_client(GetParameters, f'/{NODE_NAME}/get_parameters')
        assert wait_for(client.service_is_ready, timeout=20.0, spin=spin), \
            'no parameter service:\n' + stop_process(proc)[1]
        future = client.call_async(GetParameters.Request(names=['pose_refinement']))
        assert wait_for(future.done, timeout=10.0, spin=spin)
        assert future.result().values[0].string_value == 'off'
        node.destroy_client(client)
    finally:
        code, out = stop_process(proc)
    assert code == 0, out
    assert 'invalid parameter' not in out and 'Traceback' not in out, out


REFUSED = [
    ('damping:=3.0', "parameter 'damping' = 3.0 is above its maximum 1.0"),
    ('filter_mode:=kalman', "parameter 'filter_mode' = 'kalman' is not one of"),
    ('d_min:=9.0', 'd_min (9.0) must be below d_max (8.0)'),
]


@pytest.fixture(scope='module')
def refusals():
    """{override: (exit code, output)} of one start per invalid override, forked from one parent."""
    starts = [('module', ['--ros-args', '-p', override]) for override, _ in REFUSED]
    return dict(zip((o for o, _ in REFUSED), forked_node_starts(starts)))


@pytest.mark.parametrize('override,message', REFUSED)
def test_invalid_parameter_is_refused_with_a_reason(override, message, refusals):
    code, out = refusals[override]
    assert code == 2, out
    assert message in out
    assert 'Traceback' not in out


def test_tool_client_node_ignores_the_tools_own_argv(monkeypatch):
    """`soak --param cpu_precision:=bfloat16` puts `name:=value` in the tool's argv; rclpy must not read it as a
    remap rule of the tool's own client node (here `__node:=` would rename it)."""
    import sys
    from dpv_sensor.client.node_process import ClientNode
    monkeypatch.setattr(sys, 'argv', ['soak', '--param', '__node:=hijacked', 'cpu_precision:=bfloat16'])
    client = ClientNode('dpv_probe')
    try:
        assert client.node.get_name() == 'dpv_probe'
        assert client.context.ok()
    finally:
        client.close()
        client.close()   # idempotent
    assert not client.context.ok()
