"""The odometry's pose covariance through the node process: nav_msgs/Odometry -> pose buffer's covariance track ->
Frame -> estimator, reported in /diagnostics (`pose_uncertainty`).

One rendered sequence (classical model, 96x72, causal window) is written twice as a rosbag2: once with odometry
whose covariance is left unfilled (all zeros) and once with a filled covariance (0.01 m / 0.5 deg per axis, the
same value in every message). Each bag is replayed in lockstep through its own node process at the default
`pose_uncertainty: covariance`. Checked: without covariance the node says so and treats the poses as exact; with
it, the uncertainty comes from the covariance, and a covariance that does not grow between two views means no
relative pose error (0 deg, 0 mm), as integrated odometry's covariance is read.
"""
import pytest

from dpv_sensor.client import replay as D
from dpv_sensor.data import rosbag_io as R
from dpv_sensor.data.synthetic import render_sequence

NODE = {'measurement': 'classical', 'processing_width': 96, 'processing_height': 72, 'num_planes': 32,
        'window_mode': 'causal'}


def _replay(tmp_path, bag, **params):
    """Replay ``bag`` in lockstep through a node with the demo's parameters, NODE and ``params``."""
    node = dict(D.DEMO_NODE_PARAMS)
    node.update(NODE, **params)
    topics = {'image': R.IMAGE_TOPIC, 'camera_info': R.CAMERA_INFO_TOPIC, 'odom': R.ODOM_TOPIC}
    (tmp_path / 'logs').mkdir()
    return D.run_node_replay(D.Steps(3), bag, tmp_path / 'output', topics=topics, params=node,
                             log_dir=tmp_path / 'logs', lockstep=True, rate=1.0, start_timeout=120.0,
                             frame_timeout=120.0, max_images=0, progress=False)


@pytest.fixture(scope='module')
def sequence():
    return render_sequence(50, 12, width=96, height=72)


@pytest.mark.parametrize('odom_noise,expected', [((0.0, 0.0), 'none (no odometry covariance)'),
                                                  ((0.01, 0.5), 'covariance: rotation 0.000 deg, translation 0.00 mm')])
def test_odometry_covariance_reaches_the_estimator(tmp_path, sequence, odom_noise, expected):
    bag = tmp_path / 'input'
    # odom_noise sets the sigmas of the published covariance (and perturbs the poses by as much: white noise)
    R.write_sequence_bag(bag, sequence, odom_rate=60.0, odom_noise=odom_noise, progress=False)
    res = _replay(tmp_path, bag)
    assert res.node_exit_code == 0
    assert int(res.diagnostics['estimator_keyframes']) >= 3
    assert res.diagnostics['pose_uncertainty'].startswith(expected), res.diagnostics['pose_uncertainty']


@pytest.mark.parametrize('with_covariance', [False, True])
def test_a_published_covariance_reaches_the_window_refiner_and_the_widening(tmp_path, sequence, with_covariance):
    """The same odometry with and without its accumulated covariance (the stream table's honest odometry), replayed
    through a node refining its poses with ``refine_odom_covariance: odometry``: the refiner's odometry factors and
    the measurement's widening both come from the published covariance where it is filled, else from the drift
    figures and nothing (poses exact), as the diagnostics say."""
    from dpv_sensor.data.trajectory import corruption_variance
    bag = tmp_path / 'input'
    gt = [sequence.pose(i) for i in range(len(sequence))]
    variance = corruption_variance(gt, trans_noise_rel=0.02, rot_noise_deg=0.1) if with_covariance else None
    R.write_sequence_bag(bag, sequence, pose_variance=variance, progress=False)
    res = _replay(tmp_path, bag, pose_refinement='window', refine_odom_covariance='odometry')
    assert res.node_exit_code == 0
    diag = res.diagnostics
    assert int(diag['estimator_keyframes']) >= 3
    odometry = diag.get('pose_refinement_odometry', '')
    if with_covariance:
        assert odometry.endswith('(published covariance)'), odometry
        assert diag['pose_uncertainty'].startswith('covariance'), diag['pose_uncertainty']
        assert not diag['pose_uncertainty'].startswith('covariance: rotation 0.000 deg'), diag['pose_uncertainty']
    else:
        assert odometry.endswith('(drift figures)'), odometry
        assert diag['pose_uncertainty'].startswith('none'), diag['pose_uncertainty']
