"""The odometry's pose covariance through the node process: nav_msgs/Odometry -> pose buffer's covariance track ->
Frame -> estimator, reported in /diagnostics (`pose_uncertainty`).

One rendered sequence (classical model, 96x72, causal window) is written twice as a rosbag2: once with odometry
whose covariance is left unfilled (all zeros) and once with a filled covariance (0.01 m / 0.5 deg per axis, the
same value in every message). Each bag is replayed in lockstep through its own node process at the default
`pose_uncertainty: covariance`. Checked: without covariance the node says so and treats the poses as exact; a pose
covariance that does not grow between two views says nothing about the relative motion (diff_drive_controller's
constant pose_covariance_diagonal), so without a twist covariance the node says that too. Then the source of the
window's odometry factors (`pose_refinement_odometry`) and of the widening for each convention: a growing pose
covariance, a constant one with the motion noise in the twist covariance, none.
"""
import numpy as np
import pytest

from dpv_sensor.client import replay as D
from dpv_sensor.data import rosbag_io as R
from dpv_sensor.data.synthetic import render_sequence
from ros_helpers import launch_replay_node

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
                             frame_timeout=120.0, max_images=0, progress=False,
                             launch=launch_replay_node)


@pytest.fixture(scope='module')
def sequence():
    return render_sequence(50, 12, width=96, height=72)


@pytest.mark.parametrize('odom_noise,expected', [((0.0, 0.0), 'none (no odometry covariance)'),
                                                  ((0.01, 0.5), 'none (the pose covariance does not grow and there '
                                                   'is no twist covariance)')])
def test_odometry_covariance_reaches_the_estimator(tmp_path, sequence, odom_noise, expected):
    bag = tmp_path / 'input'
    # odom_noise sets the sigmas of the published covariance (and perturbs the poses by as much: white noise)
    R.write_sequence_bag(bag, sequence, odom_rate=60.0, odom_noise=odom_noise, progress=False)
    res = _replay(tmp_path, bag)
    assert res.node_exit_code == 0
    assert int(res.diagnostics['estimator_keyframes']) >= 3
    assert res.diagnostics['pose_uncertainty'].startswith(expected), res.diagnostics['pose_uncertainty']


@pytest.mark.parametrize('convention', ['none', 'growing pose', 'constant pose + twist'])
def test_a_published_covariance_reaches_the_window_refiner_and_the_widening(tmp_path, sequence, convention):
    """The same odometry without covariance, with its accumulated pose covariance (the stream table's honest
    odometry), and with a constant pose covariance and the motion noise in its twist covariance (a diff-drive
    controller), replayed through a node refining its poses with ``refine_odom_covariance: odometry``: the refiner's
    odometry factors and the measurement's widening come from the pose covariance's growth, from the twist covariance,
    or from the drift figures and nothing (poses exact), as the diagnostics say."""
    from dpv_sensor.data.trajectory import corruption_twist_variance, corruption_variance
    bag = tmp_path / 'input'
    gt = [sequence.pose(i) for i in range(len(sequence))]
    pose = twist = None
    if convention == 'growing pose':
        pose = corruption_variance(gt, trans_noise_rel=0.02, rot_noise_deg=0.1)
    elif convention == 'constant pose + twist':
        pose = np.full((len(gt), 2), 1e-3)
        twist = corruption_twist_variance(gt, [sequence.stamp(i) for i in range(len(gt))], trans_noise_rel=0.02,
                                          rot_noise_deg=0.1)
    R.write_sequence_bag(bag, sequence, pose_variance=pose, twist_variance=twist, progress=False)
    res = _replay(tmp_path, bag, pose_refinement='window', refine_odom_covariance='odometry')
    assert res.node_exit_code == 0
    diag = res.diagnostics
    assert int(diag['estimator_keyframes']) >= 3
    odometry = diag.get('pose_refinement_odometry', '')
    if convention == 'growing pose':
        assert odometry.endswith('(pose covariance growth)'), odometry
        assert diag['pose_uncertainty'].startswith('covariance'), diag['pose_uncertainty']
        assert not diag['pose_uncertainty'].startswith('covariance: rotation 0.000 deg'), diag['pose_uncertainty']
    elif convention == 'constant pose + twist':
        assert odometry.endswith('(twist covariance)'), odometry
        # the factors' figures: 0.1 deg per frame of noise over a keyframe step of several frames, far above the
        # 0.001 deg floor a constant pose covariance gave before
        assert float(odometry.split(' deg')[0]) > 0.05, odometry
        assert diag['pose_uncertainty'].startswith('twist covariance: rotation'), diag['pose_uncertainty']
    else:
        assert odometry.endswith('(drift figures)'), odometry
        assert diag['pose_uncertainty'].startswith('none'), diag['pose_uncertainty']


def test_the_photometric_gate_decisions_reach_the_diagnostics(tmp_path, sequence):
    """refine_photometric_gate_chi2 through the node: with a threshold no real correction meets, every alignment that
    converged is dropped as inconsistent and /diagnostics pose_refinement_factors counts it; none is used."""
    from dpv_sensor.data.trajectory import corruption_variance
    bag = tmp_path / 'input'
    gt = [sequence.pose(i) for i in range(len(sequence))]
    R.write_sequence_bag(bag, sequence, pose_variance=corruption_variance(gt, trans_noise_rel=0.02, rot_noise_deg=0.1),
                         progress=False)
    res = _replay(tmp_path, bag, pose_refinement='window', refine_photometric_sources=1,
                  refine_photometric_gate_chi2=1e-9)
    assert res.node_exit_code == 0
    factors = res.diagnostics.get('pose_refinement_factors', '')
    counts = {k: int(v) for k, v in (item.rsplit(' ', 1) for item in factors.split(', ') if item)}
    assert counts.get('photometric_inconsistent', 0) >= 1, factors
    assert 'photometric_used' not in counts, factors
