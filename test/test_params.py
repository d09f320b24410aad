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
    from dpv_sensor.stream.poses import PoseRefinerConfig, odometry_between_sigmas
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
