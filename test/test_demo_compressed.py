"""`make demo BAG= GT=` with a bag that records the camera as image_transport's compressed JPEG (what robots record):
the demo finds the sensor_msgs/CompressedImage topic by type, says so in one line, replays it to the node's
image/compressed with image_transport=compressed, and scores the depth against the ground truth (96x72, 20 frames,
classical model: one run of about half a minute)."""
import json
import os
import subprocess
import sys

from ros_helpers import REPO

NODE = ['measurement=classical', 'processing_width=96', 'processing_height=72', 'num_planes=32']


def test_demo_replays_a_compressed_bag_with_image_transport_compressed(tmp_path):
    from dpv_sensor.client.replay import ODOM_RATE_HZ, render_scene
    from dpv_sensor.data import rosbag_io as R
    seq = render_scene(tmp_path / 'gt', 42, 20, 96, 72, progress=False)
    bag = tmp_path / 'jpeg_bag'
    R.write_sequence_bag(bag, seq, odom_rate=ODOM_RATE_HZ, compressed='jpeg', image_topic='/cam/image_raw/compressed',
                         camera_info_topic='/cam/camera_info', progress=False)
    out = tmp_path / 'out'
    cmd = [sys.executable, '-m', 'dpv_sensor.tools.demo', '--quiet', '--out', str(out), '--bag', str(bag), '--gt',
           str(tmp_path / 'gt'), '--no-fusion', '--params'] + NODE
    proc = subprocess.run(cmd, cwd=REPO, env=dict(os.environ, PYTHONUNBUFFERED='1'), capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert ("demo: image topic: /cam/image_raw/compressed (sensor_msgs/CompressedImage, JPEG 'rgb8; jpeg compressed "
            "bgr8') -> node image_transport=compressed") in proc.stdout, proc.stdout
    s = json.loads((out / 'summary.json').read_text())
    assert s['input']['image_transport'] == 'compressed' and s['node']['image_transport'] == 'compressed'
    assert '-p image_transport:=compressed' in s['node']['command']
    assert '-r image/compressed:=/cam/image_raw/compressed' in s['node']['command']
    assert s['node']['images_sent'] == 20 and s['node']['frames_received'] == '20', s['node']
    assert s['node']['dropped_total'] == '0' and not s['node']['faults'], s['node']
    assert float(s['node']['image_decode_ms_median']) > 0, s['node']
    assert s['evaluation']['num_keyframes'] == s['node']['recorded']['/depth/image'] >= 1, s['evaluation']
    assert 0.0 < s['evaluation']['metric']['abs_rel'] < 0.5, s['evaluation']
