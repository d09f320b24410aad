"""`make demo BAG= GT=` on a bag as a robot records it: the camera as image_transport's compressed JPEG, odometry of
`base_link` and the camera mount (base_link -> camera_link -> optical frame) only on /tf_static. The demo finds the
sensor_msgs/CompressedImage topic by type and says so, replays it to the node's image/compressed with
image_transport=compressed and /tf_static with its latched QoS; the node takes the mount from TF with no parameter
typed, and its depth matches the raw-image bag of the same frames with T_base_camera typed to within JPEG noise
(96x72, 20 frames, classical model: two runs of about ten seconds, side by side on two DDS domains)."""
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

from ros_helpers import REPO, spare_domain

NODE = ['measurement=classical', 'processing_width=96', 'processing_height=72', 'num_planes=32']
MOUNT = [0.05, -0.02, 0.3, -0.5, 0.5, -0.5, 0.5]     # x y z qx qy qz qw: a camera 30 cm up, optical axis forward
CAMERA = 'camera_color_optical_frame'


def _demo(tmp_path, bag, name, params=(), domain=None):
    out = tmp_path / name
    cmd = [sys.executable, '-m', 'dpv_sensor.tools.demo', '--quiet', '--out', str(out), '--bag', str(bag), '--gt',
           str(tmp_path / 'gt'), '--no-fusion', '--params'] + NODE + list(params)
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    if domain is not None:
        env['ROS_DOMAIN_ID'] = str(domain)
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout, json.loads((out / 'summary.json').read_text())


def test_a_robots_compressed_bag_with_the_mount_on_tf_static_gives_the_raw_bags_depth(tmp_path):
    from dpv_sensor.client.replay import ODOM_RATE_HZ, render_scene
    from dpv_sensor.data import rosbag_io as R
    seq = render_scene(tmp_path / 'gt', 42, 20, 96, 72, progress=False)
    robot, raw = tmp_path / 'robot_bag', tmp_path / 'raw_bag'
    R.write_sequence_bag(robot, seq, odom_rate=ODOM_RATE_HZ, compressed='jpeg', image_topic='/cam/image_raw/compressed',
                         camera_info_topic='/cam/camera_info', camera_frame=CAMERA, T_base_camera=MOUNT, tf_static=True,
                         camera_link='camera_link', progress=False)
    R.write_sequence_bag(raw, seq, odom_rate=ODOM_RATE_HZ, camera_frame=CAMERA, T_base_camera=MOUNT, progress=False)

    mount = 'T_base_camera=[' + ','.join(str(v) for v in MOUNT) + ']'
    with ThreadPoolExecutor(2) as pool:       # the two replays are independent: each its own demo, node and domain
        robot_run = pool.submit(_demo, tmp_path, robot, 'robot')
        raw_run = pool.submit(_demo, tmp_path, raw, 'raw', [mount], spare_domain())
        (stdout, s), (_, r) = robot_run.result(), raw_run.result()
    assert ("demo: image topic: /cam/image_raw/compressed (sensor_msgs/CompressedImage, JPEG 'rgb8; jpeg compressed "
            "bgr8') -> node image_transport=compressed") in stdout, stdout
    assert s['input']['image_transport'] == 'compressed' and s['node']['image_transport'] == 'compressed'
    assert '-p image_transport:=compressed' in s['node']['command']
    assert '-r image/compressed:=/cam/image_raw/compressed' in s['node']['command']
    assert 'T_base_camera' not in s['node']['command'] and 'extrinsic_source' not in s['node']['command']
    assert s['node']['camera_mount']['source'] == 'tf (auto)', s['node']['camera_mount']
    assert f"'base_link' -> '{CAMERA}' xyz [0.050, -0.020, 0.300]" in s['node']['camera_mount']['mount']
    assert s['node']['images_sent'] == 20 and s['node']['frames_received'] == '20', s['node']
    assert s['node']['dropped_total'] == '0' and not s['node']['faults'], s['node']
    assert float(s['node']['image_decode_ms_median']) > 0, s['node']
    assert s['evaluation']['num_keyframes'] == s['node']['recorded']['/depth/image'] >= 1, s['evaluation']

    assert r['node']['image_transport'] == 'raw' and r['node']['camera_mount']['source'].startswith('parameter')
    assert r['evaluation']['num_keyframes'] == s['evaluation']['num_keyframes'], (r['evaluation'], s['evaluation'])
    robot_abs_rel, raw_abs_rel = s['evaluation']['metric']['abs_rel'], r['evaluation']['metric']['abs_rel']
    assert 0.0 < raw_abs_rel < 0.5, r['evaluation']
    assert abs(robot_abs_rel - raw_abs_rel) <= 0.005, (robot_abs_rel, raw_abs_rel)
