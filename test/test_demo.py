"""The demo end to end at a tiny size: render -> bag -> node process -> replay + record -> SIGINT -> evaluate -> fuse.

One demo run (96x72, 20 frames, classical model, ~30 s on a busy 2-core CPU) is shared by the checks:
- exit code 0, and every promised file exists (GT sequence, both bags, eval report with a real montage PNG, meshes);
- the node was stopped with SIGINT and exited 0, every replayed image was processed (none dropped: lockstep pacing)
  and every depth output it published is in the recorded bag;
- the headline metrics the demo prints are exactly what the `evaluate bag` tool prints for the recorded bag when
  run by hand (same table row, same summary.json numbers).
Then the same input bag, its topics renamed, goes through `--bag` mode without ground truth and without topic names
(only the first 12 images): the topics are found by message type, outputs are recorded and an image | depth |
confidence montage is written; with a second image topic the demo stops and lists both.
"""
import contextlib
import io
import json
import os
import re
import subprocess
import sys
import time

import cv2
import pytest

from ros_helpers import REPO
from dpv_sensor.client.node_process import node_command
from dpv_sensor.tools import demo as D

NODE = ['measurement=classical', 'processing_width=96', 'processing_height=72', 'num_planes=32']


def _run_demo(args, timeout=240):
    cmd = [sys.executable, '-m', 'dpv_sensor.tools.demo', '--quiet'] + args
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope='module')
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp('demo') / 'out'
    t0 = time.monotonic()
    proc = _run_demo(['--out', str(out), '--frames', '20', '--width', '96', '--height', '72', '--params'] + NODE)
    proc.wall_s = time.monotonic() - t0
    return out, proc


def _png_shape(path):
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, f'{path} is not a readable image'
    return img.shape


def test_demo_runs_every_step_and_writes_its_files(demo_run):
    out, proc = demo_run
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for name in ('sequence/poses.txt', 'sequence/K.txt', 'input_bag/metadata.yaml', 'output_bag/metadata.yaml',
                 'eval/summary.json', 'eval/frames.csv', 'eval/montage.png', 'eval/sparsification.png',
                 'fusion/mesh_pred.ply', 'fusion/mesh_pred_masked.ply', 'fusion/mesh_gt.ply', 'fusion/fusion.json',
                 'logs/node.log', 'summary.json'):
        assert (out / name).is_file(), f'{name} missing; output:\n{proc.stdout}'
    assert len(list((out / 'sequence' / 'images').iterdir())) == 20
    h, w, _ = _png_shape(out / 'eval' / 'montage.png')
    assert h > 200 and w > 400
    assert (out / 'fusion' / 'mesh_pred.ply').stat().st_size > 1000
    s = json.loads((out / 'summary.json').read_text())
    assert s['ok'] and s['failure'] is None
    assert [r['step'] for r in s['steps']] == ['render', 'bag', 'node', 'replay', 'stop', 'eval', 'fuse']
    assert all(r['ok'] for r in s['steps'])
    # every step did some work, and the steps' times add up to no more than the wall time of the whole process
    assert all(r['seconds'] > 0 for r in s['steps']), s['steps']
    assert sum(r['seconds'] for r in s['steps']) <= proc.wall_s, (s['steps'], proc.wall_s)
    fu = s['fusion']['unmasked']
    assert fu['num_vertices'] > 0 and 0.0 <= fu['fscore'] <= 1.0
    for line in ('=== dpv_sensor demo finished', 'what ran', 'metrics', 'fusion', 'pictures'):
        assert line in proc.stdout, proc.stdout


def test_node_stopped_cleanly_and_nothing_was_lost(demo_run):
    out, proc = demo_run
    s = json.loads((out / 'summary.json').read_text())
    nd = s['node']
    assert nd['exit_code'] == 0
    assert 'SIGINT -> exit code 0' in proc.stdout
    assert nd['measurement_model'] == 'classical' and nd['filter_mode'] == 'global'
    # the demo's odometry fills no covariance: with the default pose_uncertainty (covariance) the poses count as exact
    assert nd['pose_uncertainty'] == 'none (no odometry covariance)', nd['pose_uncertainty']
    assert nd['images_sent'] == 20 and int(nd['frames_received']) == 20 and int(nd['frames_processed']) == 20
    assert int(nd['dropped_total']) == 0, nd['dropped']
    n_out = int(nd['outputs_published'])
    assert n_out >= 3
    assert nd['recorded']['/depth/image'] == nd['recorded']['/confidence/image'] == \
        nd['recorded']['/depth/camera_info'] == n_out
    # centered window (the default): keyframe k is published when keyframe k + 2 arrives, so the last two keyframes
    # of the stream (and of each segment before a restart) give none; every output was scored
    kf, resets = int(nd['keyframes']), int(nd['filter_resets'])
    assert kf - 2 * (1 + resets) <= n_out <= kf - 2
    assert s['evaluation']['num_keyframes'] == n_out
    assert 'Traceback' not in (out / 'logs' / 'node.log').read_text()
    # a private DDS domain and the ROS logs under OUT
    assert s['ros_env']['ROS_LOG_DIR'].startswith(str(out))
    assert s['ros_env']['ROS_DOMAIN_ID'] == os.environ['ROS_DOMAIN_ID']    # honoured when set (conftest sets it)


def test_printed_metrics_equal_evaluate_by_hand(demo_run, tmp_path):
    out, proc = demo_run
    from dpv_sensor.tools import evaluate
    by_hand = tmp_path / 'by_hand'
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = evaluate.main(['bag', str(out / 'output_bag'), '--gt', str(out / 'sequence'), '--out', str(by_hand),
                              '--quiet'])
    assert code == 0
    rows = [ln for ln in buf.getvalue().splitlines() if ln.startswith('| output_bag ')]
    assert len(rows) == 1
    demo_rows = [ln.strip() for ln in proc.stdout.splitlines() if ln.strip().startswith('| output_bag ')]
    assert demo_rows == rows
    hand = json.loads((by_hand / 'summary.json').read_text())
    demo = json.loads((out / 'eval' / 'summary.json').read_text())
    for key in ('metric', 'median_scaled', 'coverage'):
        assert demo[key]['frame_mean'] == hand[key]['frame_mean']
    m = re.search(r'abs_rel (\d+\.\d+), rmse', proc.stdout)
    assert m and m.group(1) == f"{hand['metric']['frame_mean']['abs_rel']:.4f}"
    # the command the demo tells the user to run is this one
    assert 'python -m dpv_sensor.tools.evaluate bag ' in proc.stdout and '--gt ' in proc.stdout


def _renamed_bag(src, dst, names, extra_image=None):
    """A copy of the bag ``src`` with its topics renamed (``names``: old -> new), optionally with one more image
    topic (a copy of the images under ``extra_image``)."""
    from dpv_sensor.data import rosbag_io as R
    with R.BagWriter(dst) as bag:
        for topic, msgtype, log_ns, msg in R.read_messages(src):
            bag.write(names.get(topic, topic), msgtype, msg, log_ns)
            if extra_image and msgtype == R.IMAGE:
                bag.write(extra_image, msgtype, msg, log_ns)
    return dst


USER_NAMES = {'/image': '/rover/cam0/rgb', '/camera_info': '/rover/cam0/intrinsics',
              '/odom': '/rover/wheel_odometry'}


def test_make_demo_passes_no_topic_names_unless_given():
    dry = subprocess.run(['make', '-n', 'demo', 'BAG=run.mcap'], cwd=REPO, capture_output=True, text=True)
    assert dry.returncode == 0, dry.stderr
    line = [ln for ln in dry.stdout.splitlines() if 'dpv_sensor.tools.demo' in ln]
    assert len(line) == 1 and '--bag run.mcap' in line[0] and '-topic' not in line[0]
    dry = subprocess.run(['make', '-n', 'demo', 'BAG=run.mcap', 'IMAGE_TOPIC=/a'], cwd=REPO, capture_output=True,
                         text=True)
    assert '--image-topic /a' in dry.stdout


def test_bag_mode_finds_the_topics_by_type_without_ground_truth(demo_run, tmp_path):
    out, _ = demo_run
    bag = _renamed_bag(out / 'input_bag', tmp_path / 'user_bag', USER_NAMES)
    mine = tmp_path / 'mine'
    proc = _run_demo(['--out', str(mine), '--bag', str(bag), '--frames', '12', '--params'] + NODE)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert ('demo: input topics: image /rover/cam0/rgb (the only sensor_msgs/msg/Image topic), camera_info '
            '/rover/cam0/intrinsics (the only sensor_msgs/msg/CameraInfo topic), odom /rover/wheel_odometry (the only '
            'nav_msgs/msg/Odometry topic)') in proc.stdout
    s = json.loads((mine / 'summary.json').read_text())
    assert s['input']['topics'] == {'image': '/rover/cam0/rgb', 'camera_info': '/rover/cam0/intrinsics',
                                    'odom': '/rover/wheel_odometry'}
    assert s['node']['images_sent'] == 12 and s['node']['exit_code'] == 0
    assert s['outputs']['outputs'] == s['node']['recorded']['/depth/image'] >= 1
    assert 0.0 < s['outputs']['coverage_mean'] <= 1.0
    assert _png_shape(mine / 'montage.png')[0] > 100
    assert not (mine / 'eval').exists() and not (mine / 'fusion').exists()
    assert [r['step'] for r in s['steps'] if not r.get('skipped')] == ['node', 'replay', 'stop', 'montage']


def test_bag_mode_with_two_image_topics_lists_them(tmp_path, demo_run):
    out, _ = demo_run
    bag = _renamed_bag(out / 'input_bag', tmp_path / 'two', USER_NAMES, extra_image='/rover/cam1/rgb')
    proc = _run_demo(['--out', str(tmp_path / 'x'), '--bag', str(bag)])
    assert proc.returncode == 1
    assert ('2 sensor_msgs/msg/Image topics could be the image: /rover/cam0/rgb [sensor_msgs/msg/Image, 20 '
            'messages], /rover/cam1/rgb [sensor_msgs/msg/Image, 20 messages]; choose with --image-topic '
            '(IMAGE_TOPIC= with make)') in proc.stdout
    assert 'what ran' not in proc.stdout        # stopped before starting the node


def test_bag_mode_names_missing_topics(tmp_path, demo_run):
    out, _ = demo_run
    proc = _run_demo(['--out', str(tmp_path / 'x'), '--bag', str(out / 'input_bag'), '--image-topic', '/nope'])
    assert proc.returncode == 1
    assert "no topic '/nope' for image" in proc.stdout
    assert '/image [sensor_msgs/msg/Image, 20 messages]' in proc.stdout


def test_parse_params_types_and_rejects_unknown_names():
    p = D.parse_params(['preset=paper', 'fx:=525', 'publish_between_keyframes=true', 'input_depth=7',
                        'T_base_camera=[0,0,0.1,0,0,0,1]'])
    assert p == {'preset': 'paper', 'fx': 525.0, 'publish_between_keyframes': True, 'input_depth': 7,
                 'T_base_camera': [0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0]}
    with pytest.raises(ValueError, match='unknown node parameter'):
        D.parse_params(['no_such_thing=1'])
    with pytest.raises(ValueError, match='KEY=VALUE'):
        D.parse_params(['preset'])
    cmd = node_command({'weights': '', 'damping': 0.5, 'T_base_camera': [0, 0, 0, 0, 0, 0, 1]}, {'image': '/cam'})
    assert cmd[:4] == [sys.executable, '-m', 'dpv_sensor.ros.node', '--ros-args']
    assert cmd[4:] == ['-p', "weights:=''", '-p', 'damping:=0.5', '-p', 'T_base_camera:=[0.0,0.0,0.0,0.0,0.0,0.0,1.0]',
                       '-r', 'image:=/cam']


def test_own_bag_with_epoch_stamps_and_gt_without_stamps_scores_without_stamp_offset(demo_run, tmp_path):
    """A GT folder without stamps.txt (its frame 0 is the bag's first image) and a bag recorded at real epoch
    stamps: the demo scores it with no --stamp-offset."""
    import shutil
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.evaluation.offline import load_sequence
    out, _ = demo_run
    gt = tmp_path / 'gt'
    shutil.copytree(out / 'sequence', gt)
    (gt / 'stamps.txt').unlink(missing_ok=True)
    bag = tmp_path / 'epoch_bag'
    R.write_sequence_bag(bag, load_sequence(gt), odom_rate=60.0, start_ns=1_700_000_000 * 10**9, progress=False)
    mine = tmp_path / 'mine'
    proc = _run_demo(['--out', str(mine), '--bag', str(bag), '--gt', str(gt), '--no-fusion', '--params'] + NODE)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    s = json.loads((mine / 'summary.json').read_text())
    assert abs(s['stamp_offset_s'] - 1_700_000_000) < 1.0, s.get('stamp_offset_s')
    assert s['evaluation']['num_keyframes'] == s['node']['recorded']['/depth/image'] >= 1, s['evaluation']
    assert not any('matched no ground-truth frame' in w for w in s['warnings']), s['warnings']


def test_a_run_refused_on_its_arguments_keeps_the_previous_results(demo_run, tmp_path):
    out, _ = demo_run
    kept = tmp_path / 'kept'
    (kept / 'eval').mkdir(parents=True)
    (kept / 'summary.json').write_text('{"ok": true}')
    for args in (['--bag', str(tmp_path / 'no_such.mcap')], ['--bag', str(out / 'input_bag'), '--image-topic', '/x'],
                 ['--gt', str(tmp_path / 'no_such_gt')]):
        proc = _run_demo(['--out', str(kept)] + args)
        assert proc.returncode == 1, proc.stdout + proc.stderr
        assert (kept / 'summary.json').read_text() == '{"ok": true}' and (kept / 'eval').is_dir(), args
