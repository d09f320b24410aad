"""Runtime parameters through the node process: a change of a parameter in params.RUNTIME is accepted and applied to
the next outputs (depth_encoding, min_confidence); an out-of-range value is refused with the table's message, and a
parameter that needs a restart is refused as read-only. The YAML states which can change."""
import pathlib

from stream_driver import FAST_PARAMS, StreamDriver, params_args
from ros_helpers import wait_for
from dpv_sensor import params as P

REPO = pathlib.Path(__file__).resolve().parents[1]
REMAPS = {'image': '/cam/image', 'camera_info': '/cam/camera_info', 'odom': '/odom'}


def _set(drv, client, **values):
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    def value(v):
        if isinstance(v, float):
            return ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=v)
        if isinstance(v, int):
            return ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=v)
        return ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=v)
    req = SetParameters.Request(parameters=[Parameter(name=k, value=value(v)) for k, v in values.items()])
    future = client.call_async(req)
    assert wait_for(future.done, timeout=20.0, spin=drv.spin)
    return future.result().results


def test_runtime_parameters_are_applied_and_bad_changes_refused_with_the_tables_message():
    from rcl_interfaces.srv import SetParameters
    drv = StreamDriver(params_args(FAST_PARAMS, REMAPS), topics=REMAPS, frames=12, name='runtime_params')
    client = drv.node.create_client(SetParameters, '/dpv_sensor/set_parameters')
    try:
        drv.wait_ready()
        assert wait_for(client.service_is_ready, timeout=30.0, spin=drv.spin)
        for i in range(4):
            drv.send(i, drv.stamp_ns(i))
            assert drv.wait_accounted(i + 1)
        assert wait_for(lambda: drv.outputs.depth_count > 0, timeout=30.0, spin=drv.spin)
        before = {r.depth.encoding for r in drv.outputs.by_stamp.values() if r.depth is not None}
        accepted = _set(drv, client, depth_encoding='16UC1', min_confidence=0.5)
        refused = _set(drv, client, damping=3.0)
        read_only = _set(drv, client, preset='paper')
        first_after = max(drv.outputs.by_stamp)
        for i in range(4, 12):
            drv.send(i, drv.stamp_ns(i))
            assert drv.wait_accounted(i + 1)
        assert wait_for(lambda: max(drv.outputs.by_stamp) > first_after and
                        drv.outputs.by_stamp[max(drv.outputs.by_stamp)].depth is not None, timeout=30.0, spin=drv.spin)
        after = {r.depth.encoding for s, r in drv.outputs.by_stamp.items() if s > first_after and r.depth is not None}
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    assert [r.successful for r in accepted] == [True, True], accepted
    assert before == {'32FC1'} and after == {'16UC1'}, (before, after)
    assert not refused[0].successful and "parameter 'damping' = 3.0 is above its maximum 1.0" in refused[0].reason
    assert not read_only[0].successful and 'read-only' in read_only[0].reason, read_only
    assert "parameters changed: depth_encoding='16UC1'" in log and 'parameters changed: min_confidence=0.5' in log, log
    assert "parameter change refused: parameter 'damping' = 3.0 is above its maximum 1.0" in log, log


def test_the_yaml_states_which_parameters_can_change_at_run_time():
    head = (REPO / 'config' / 'dpv_sensor.yaml').read_text().split('/**:')[0]
    assert 'Every other parameter needs a restart' in head
    for name in P.RUNTIME:
        assert name in head
    assert P.check_changes(P.defaults(), {'min_confidence': 0.3})['min_confidence'] == 0.3


def test_the_pipeline_takes_runtime_settings_on_its_running_estimator():
    from dpv_sensor.stream.estimator import EstimatorConfig
    from dpv_sensor.stream.pipeline import Pipeline
    pipe = Pipeline(EstimatorConfig.from_params({'measurement': 'classical', 'filter_mode': 'global'}))
    pipe.apply_settings({'damping': 0.3, 'min_confidence': 0.4, 'edge_filter_radius': 0})
    cfg = pipe.estimator.config
    assert (cfg.damping, cfg.min_confidence, cfg.edge_filter_radius) == (0.3, 0.4, 0)
    assert pipe.estimator.filter.damping == 0.3
