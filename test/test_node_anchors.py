"""The metric anchors through the node process: a rendered room written as a rosbag2 and replayed in lockstep
through a node with `depth_anchors: dense` (classical model, small processing size): /diagnostics reports the
mode, the keyframes checked and aligned, the anchors per keyframe, the rejected candidates by reason and the last
keyframe's scale; the same replay shows where the worker's time goes and the mount check's estimate (no WARN:
the bag's odometry is the camera's own)."""
import re

import pytest

from dpv_sensor.client import replay as D
from dpv_sensor.data import rosbag_io as R
from dpv_sensor.data.synthetic import render_sequence
from ros_helpers import launch_replay_node

NODE = {'measurement': 'classical', 'processing_width': 96, 'processing_height': 72, 'num_planes': 32,
        'depth_anchors': 'dense'}


@pytest.fixture(scope='module')
def replay(tmp_path_factory):
    tmp = tmp_path_factory.mktemp('anchors')
    bag = tmp / 'input'
    R.write_sequence_bag(bag, render_sequence(50, 30, width=320, height=240), progress=False)
    node = dict(D.DEMO_NODE_PARAMS)
    node.update(NODE)
    (tmp / 'logs').mkdir()
    topics = {'image': R.IMAGE_TOPIC, 'camera_info': R.CAMERA_INFO_TOPIC, 'odom': R.ODOM_TOPIC}
    return D.run_node_replay(D.Steps(3), bag, tmp / 'output', topics=topics, params=node, log_dir=tmp / 'logs',
                             lockstep=True, rate=1.0, start_timeout=120.0, frame_timeout=120.0, max_images=0,
                             progress=False, launch=launch_replay_node)


def test_the_node_publishes_what_the_anchors_did(replay):
    assert replay.node_exit_code == 0
    diag = replay.diagnostics
    assert diag['depth_anchors'] == 'dense'
    m = re.fullmatch(r"(\d+) checked, (\d+) aligned, (\d+) overruled \((\d+) pixels\), (\d+) with the classical "
                     r"sweep blended in \((\d+) pixels mostly the sweep's\)", diag['anchors_keyframes'])
    assert m, diag['anchors_keyframes']
    checked, aligned = int(m.group(1)), int(m.group(2))
    # the measurement is the classical sweep itself: no second opinion to blend in
    assert m.group(5) == m.group(6) == '0'
    assert checked >= 3 and 1 <= aligned <= checked
    assert float(diag['anchors_per_keyframe']) >= 20
    assert 'reprojection' in diag['anchors_rejected'] and 'depth_edge' in diag['anchors_rejected']
    assert re.search(r'\d+ anchors, \d+ on the depth, (scale \d\.\d{3} \+- \d+\.\d %|no fit)', diag['anchors_last']), \
        diag['anchors_last']


def test_the_node_says_where_its_time_goes(replay):
    diag = replay.diagnostics
    stages = diag['keyframe_stages_ms']
    for stage in ('pose_refinement', 'measurement', 'filter', 'anchors', 'total'):
        assert re.search(rf'\b{stage} \d+', stages), stages
    share = diag['worker_busy_share']
    assert share == 'n/a' or 0.0 <= float(share) <= 1.0


def test_the_node_reports_its_mount_check_and_does_not_warn_on_the_exact_mount(replay):
    diag = replay.diagnostics
    for key in ('mount_estimate', 'time_offset_estimate'):
        assert re.match(r'(ok: |no estimate|not fitted)', diag[key]), (key, diag[key])
    assert 'mount check:' not in replay.node_log
