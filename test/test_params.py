"""The parameter table, the documented YAML and validation agree."""
import pathlib

import pytest
import yaml

from dpv_sensor import params as P

CONFIG = pathlib.Path(__file__).resolve().parents[1] / 'config' / 'dpv_sensor.yaml'


def test_yaml_documents_every_parameter_with_its_default():
    doc = yaml.safe_load(CONFIG.read_text())
    assert list(doc) == ['/**']          # any node name, any namespace
    values = doc['/**']['ros__parameters']
    assert set(values) == {s.name for s in P.SPECS}
    for spec in P.SPECS:
        assert values[spec.name] == spec.default, spec.name
        assert type(values[spec.name]) is type(spec.default), spec.name
    P.validate(values)


@pytest.mark.parametrize('name,value,message', [
    ('damping', 1.5, "'damping' = 1.5 is above its maximum"),
    ('filter_mode', 'kalman', "'filter_mode' = 'kalman' is not one of"),
    ('keyframe_max_interval', 0, "'keyframe_max_interval' = 0 is below its minimum"),
    ('T_base_camera', [0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 'must be a list of 7 numbers'),
    ('T_base_camera', [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0], 'is not unit length'),
    ('processing_width', 'wide', "'processing_width' must be int"),
    ('d_min', 9.0, 'must be below d_max'),
])
def test_validation_names_the_parameter_and_the_problem(name, value, message):
    values = P.defaults()
    values[name] = value
    with pytest.raises(P.ParameterError, match=message.replace('(', r'\(').replace('[', r'\[')):
        P.validate(values)


def test_yaml_is_generated_from_the_table():
    assert CONFIG.read_text() == P.yaml_text(), 'regenerate: python -m dpv_sensor.params > config/dpv_sensor.yaml'


def test_ints_are_accepted_for_floats():
    values = P.defaults()
    values['damping'] = 1
    assert P.validate(values)['damping'] == 1.0


def test_pose_refiner_sigmas_come_from_the_parameters():
    from dpv_sensor.stream.window_graph import odometry_between_sigmas
    from dpv_sensor.stream.window_refiner import PoseRefinerConfig
    import numpy as np
    defaults = P.defaults()
    assert PoseRefinerConfig.from_params(defaults) == PoseRefinerConfig()   # one set of defaults
    values = dict(defaults, odom_sigma_rot_deg=2.0, odom_sigma_trans_m=0.01, odom_sigma_trans_rel=0.1)
    cfg = PoseRefinerConfig.from_params(P.validate(values))
    step = np.eye(4)
    step[:3, 3] = [0.3, 0.4, 0.0]                                            # 0.5 m
    sig = odometry_between_sigmas(step, cfg)
    np.testing.assert_allclose(sig[:3], np.radians(2.0))
    np.testing.assert_allclose(sig[3:], 0.01 + 0.1 * 0.5)


def test_flow_width_comes_from_the_parameters():
    """refine_flow_max_width reaches the flow's config and no other flow field moves; a 640x480 camera is then matched
    at 320x240 with its intrinsics halved (fx 500 -> 250, cx 320 -> 160, cy 240 -> 120)."""
    import dataclasses
    import numpy as np
    from dpv_sensor.core.flow_rotation import FlowConfig, match_image
    from dpv_sensor.stream.window_refiner import PoseRefinerConfig
    assert PoseRefinerConfig.from_params(P.defaults()).flow == FlowConfig()          # 640 wide by default
    cfg = PoseRefinerConfig.from_params(P.validate(dict(P.defaults(), refine_flow_max_width=320)))
    assert cfg.flow == dataclasses.replace(FlowConfig(), max_width=320)
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    grey, K_small = match_image(np.zeros((480, 640, 3), np.uint8), K, cfg.flow)
    assert grey.shape == (240, 320)
    np.testing.assert_allclose(K_small, [[250.0, 0.0, 160.0], [0.0, 250.0, 120.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match='refine_flow_max_width'):
        P.validate(dict(P.defaults(), refine_flow_max_width=32))


def test_pose_error_model_comes_from_the_parameters():
    from dpv_sensor.stream.window_refiner import PoseRefinerConfig
    values = dict(P.defaults(), refine_odom_covariance='odometry', refine_keypoints=True, refine_marginals=True,
                  refine_gate_chi2=16.27, refine_gate_min_inliers=30, odom_drift_trans=0.05,
                  odom_drift_rot_deg_per_m=2.0, odom_drift_rot=0.01)
    cfg = PoseRefinerConfig.from_params(P.validate(values))
    assert (cfg.odom_covariance, cfg.keypoint_factors, cfg.marginals) == ('odometry', True, True)
    assert (cfg.gate_chi2, cfg.gate_min_inliers) == (16.27, 30)
    assert (cfg.drift.trans_per_m, cfg.drift.rot_deg_per_m, cfg.drift.rot_per_deg) == (0.05, 2.0, 0.01)
    assert cfg.drift.sync_s == 0.0          # the window's steps carry no time-offset term
    with pytest.raises(ValueError, match='refine_odom_covariance'):
        P.validate(dict(P.defaults(), refine_odom_covariance='exact'))


# ------------------------------------------------------------------------------------------------------
# a value of the wrong type: one message naming the setting, its type and the value, wherever it comes in
# ------------------------------------------------------------------------------------------------------

WRONG_TYPES = [   # (setting, a Python value of the wrong type, command-line text of the wrong type, expected type)
    ('keyframe_max_interval', 0.5, '0.5', 'int'),
    ('damping', 'high', 'high', 'float'),
    ('publish_between_keyframes', 1, 'maybe', 'bool (true or false)'),
    ('T_base_camera', 'x', '0,0,0,0,0,x,1', 'a list of 7 numbers'),
]


@pytest.mark.parametrize('name,value,text,expected', WRONG_TYPES)
def test_wrong_type_names_setting_type_and_value(name, value, text, expected):
    message = f"parameter '{name}' must be {expected}, got {value!r}"
    values = dict(P.defaults(P.SPECS + P.LIBRARY_SPECS), **{name: value})
    with pytest.raises(P.ParameterError) as exc:
        P.validate(values, P.SPECS + P.LIBRARY_SPECS)        # the node's parameters and evaluate's configuration
    assert str(exc.value) == message
    with pytest.raises(P.ParameterError) as exc:
        P.check_value(P.spec(name), value)                  # the node's start-up and runtime checks
    assert str(exc.value) == message
    with pytest.raises(P.ParameterError) as exc:
        P.parse_assignments([f'{name}={text}'])             # key=value on a command line
    assert str(exc.value) == f"parameter '{name}' must be {expected}, got {text!r}"


def test_wrong_type_of_a_choice_and_in_the_estimator_config():
    from dpv_sensor.stream.estimator import EstimatorConfig
    with pytest.raises(P.ParameterError, match=r"^parameter 'filter_mode' must be str, got 3$"):
        P.check_value(P.spec('filter_mode'), 3)
    with pytest.raises(P.ParameterError, match=r"^parameter 'filter_mode' = 'kalman' is not one of \['none'"):
        P.check_value(P.spec('filter_mode'), 'kalman')
    with pytest.raises(P.ParameterError, match=r"^parameter 'keyframe_max_interval' must be int, got 0\.5$"):
        EstimatorConfig(keyframe_max_interval=0.5).validate()
    with pytest.raises(P.ParameterError, match=r"^parameter 'T_base_camera' must be a list of 7 numbers, got \[1"):
        P.check_value(P.spec('T_base_camera'), [1.0, 'a', 0.0, 0.0, 0.0, 0.0, 1.0])


@pytest.mark.parametrize('assignment,message', [
    ('keyframe_max_interval=0.5', "parameter 'keyframe_max_interval' must be int, got '0.5'"),
    ('damping=high', "parameter 'damping' must be float, got 'high'"),
    ('publish_between_keyframes=maybe', "parameter 'publish_between_keyframes' must be bool (true or false), "
                                        "got 'maybe'"),
    ('filter_mode=kalman', "parameter 'filter_mode' = 'kalman' is not one of ['none', 'bayes', 'global', 'knet']"),
    ('T_base_camera=0,0,0,0,0,x,1', "parameter 'T_base_camera' must be a list of 7 numbers, got '0,0,0,0,0,x,1'"),
    ('T_base_camera=0,0,0,1', "parameter 'T_base_camera' must be a list of 7 numbers, got [0.0, 0.0, 0.0, 1.0]"),
])
def test_evaluate_refuses_a_wrong_type_naming_the_setting(assignment, message, tmp_path, capsys):
    from dpv_sensor.tools.evaluate import main
    rc = main(['sequence', 'synthetic:0:3', '--out', str(tmp_path / 'out'), '--quiet', '--config', assignment])
    assert rc == 2
    assert capsys.readouterr().err.strip() == f'evaluate: {message}'
    assert not (tmp_path / 'out').exists()


def test_off_read_as_a_boolean_means_the_choice_off():
    """YAML 1.1 and `--ros-args -p pose_refinement:=off` deliver False for the word off."""
    spec = {s.name: s for s in P.SPECS}
    assert P.check_value(spec['pose_refinement'], False) == 'off'
    assert P.check_value(spec['pose_uncertainty'], False) == 'off'
    with pytest.raises(P.ParameterError, match="'pose_refinement' must be str, got True"):
        P.check_value(spec['pose_refinement'], True)          # no choice 'on'
    with pytest.raises(P.ParameterError, match="'frame_id' must be str"):
        P.check_value(spec['frame_id'], False)                # a free string takes no boolean
