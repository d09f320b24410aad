"""Fault injection: a bag full of bad input replays through the node process without a crash; each fault is logged
with its own message, counted in /diagnostics, and the node keeps publishing valid depth afterwards.

Faults in the bag (160x128 rendered frames at 30 Hz, replayed at 0.25x): no camera_info for the first frames, a
camera_info with K all zeros, a 16UC1 image on the colour topic, an image whose data is shorter than step*height, a
1x1 image (below the estimator's smallest size: refused on receipt, never reaching the estimator), a stretch of three
80x64 images (the size persists for size_change_images 3 images: the first two are strays, the third changes the
stream, and so back),
a NaN odometry message at an image stamp, an odometry gap wider than max_odom_gap, every stamp jumping back by
5 s (a bag restarting), and an odometry teleport (every pose 0.5 m off from one message on: a relocalisation).
The node also starts with a corrupt weights file and must fall back to the classical model.
"""
import math
import re
import threading

import cv2
import numpy as np
import pytest

from ros_helpers import start_node, stop_process, wait_for
from dpv_sensor.ros import msgs as M
from dpv_sensor.ros import pose_msgs as PM
from dpv_sensor.data import rosbag_io as R
from dpv_sensor.stream.pose_buffer import NS
from dpv_sensor.client.ros_io import BagPlayer, OutputCollector

W, H = 160, 128
FRAMES = 44
BASE_NS = 1_750_000_000 * NS
JUMP_NS = 5 * NS
NO_INFO = range(0, 6)          # no camera_info for these frames
ZERO_K = 7                      # camera_info with K all zeros
WRONG_ENCODING = 10             # 16UC1 on the colour topic
TRUNCATED = 11                  # data shorter than step * height
TINY = 13                       # a 1x1 image: refused on receipt (image_too_small)
SMALL = range(16, 19)           # 80x64 images (+ matching camera_info): taken at the third
NAN_ODOM = 22                   # odometry at this frame's stamp is NaN
GAP = (25, 28)                  # no odometry strictly between these frames
JUMP = 32                       # from this frame on, every stamp is 5 s earlier
TELEPORT = 36                   # from this frame on, every odometry pose is 0.5 m off (the images are not)
PAUSE_BEFORE = {WRONG_ENCODING, TRUNCATED, TINY, SMALL[0], NAN_ODOM, GAP[0] + 1, JUMP, TELEPORT}


def frame_time_ns(i: float) -> int:
    return int(round(i * NS / 30))


def header_ns(i: float) -> int:
    return BASE_NS + frame_time_ns(i) - (JUMP_NS if i >= JUMP else 0)


def log_ns(i: float) -> int:
    """Record time: 30 Hz plus a 0.1 s pause before each faulty frame, so the node is idle when it arrives."""
    pauses = sum(1 for p in PAUSE_BEFORE if i >= p)
    return BASE_NS + frame_time_ns(i) + pauses * NS // 10


def write_fault_bag(path, seq):
    K = seq.K
    K_small = M.scale_K(K, (W, H), (W // 2, H // 2))
    T = R.ROSBAGS
    with R.BagWriter(path) as bag:
        for k in range(2 * (FRAMES - 1) + 1):          # odometry at 60 Hz
            i = k / 2
            if GAP[0] < i < GAP[1]:
                continue
            j = int(math.floor(i))
            pose = seq.pose(j) if i == j else R.interpolate_pose(seq.pose(j), seq.pose(j + 1), 0.5)
            if i >= TELEPORT:
                pose = pose.copy()
                pose[0, 3] += 0.5
            msg = PM.matrix_to_odometry(pose, header_ns(i), 'base_link', 'odom', types=T)
            if i == NAN_ODOM:
                msg.pose.pose.position.x = float('nan')
            bag.write(R.ODOM_TOPIC, R.ODOMETRY, msg, log_ns(i))
        for i in range(FRAMES):
            t, lg = header_ns(i), log_ns(i)
            rgb = seq.image(i)
            if i in SMALL:
                rgb = cv2.resize(rgb, (W // 2, H // 2), interpolation=cv2.INTER_AREA)
            if i not in NO_INFO:
                if i == ZERO_K:
                    info = M.K_to_camera_info(np.zeros((3, 3)), W, H, t, 'cam', types=T)
                else:
                    info = M.K_to_camera_info(K_small if i in SMALL else K, rgb.shape[1], rgb.shape[0], t, 'cam',
                                              types=T)
                bag.write(R.CAMERA_INFO_TOPIC, R.CAMERA_INFO, info, lg)
            img = M.rgb_to_image(rgb, t, 'cam', types=T)
            if i == WRONG_ENCODING:
                img = T('sensor_msgs/msg/Image', header=img.header, height=H, width=W, encoding='16UC1',
                        is_bigendian=0, step=2 * W, data=np.zeros(2 * W * H, np.uint8))
            elif i == TRUNCATED:
                img.data = img.data[:-7]
            elif i == TINY:
                img = M.rgb_to_image(rgb[:1, :1], t, 'cam', types=T)
            bag.write(R.IMAGE_TOPIC, R.IMAGE, img, lg)


@pytest.fixture(scope='module')
def fault_bag(tmp_path_factory):
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(4, FRAMES, width=W, height=H)
    path = tmp_path_factory.mktemp('faults') / 'fault_bag'
    write_fault_bag(path, seq)
    corrupt = path.parent / 'corrupt.safetensors'
    corrupt.write_bytes(b'this is not a safetensors file' * 10)
    return seq, path, corrupt




EXPECTED_LOGS = {
    'no_camera_info': 'no camera_info received yet on /camera_info; waiting',
    'bad_camera_info': 'ignoring camera_info on /camera_info: camera_info K is all zeros',
    'unsupported_encoding': "unsupported image encoding '16UC1' (a 16-bit depth/mono image)",
    'bad_image': 'data length 61433 does not match step*height = 480*128 = 61440',
    'image_size_change': 'image size changed from 160x128 to 80x64; resetting the estimator',
    'image_too_small': '1x1 is smaller than the smallest image the estimator takes (2x2 pixels)',
    'stray_image_size': "80x64 is not the stream's 160x128 (1 image(s) in a row",
    'nan_odometry': 'odometry has NaN/inf',
    'odometry_invalid_bracket': 'invalid odometry around the image',
    'odometry_gap': 'exceeds max_odom_gap 0.050 s',
    'time_backwards': 'time went backwards',
    'odometry_jump': 'odometry jumped 0.5',
}


def test_fault_bag_replays_without_crash_and_every_fault_is_reported(fault_bag, observer):
    seq, bag, corrupt = fault_bag
    node, executor = observer
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    outputs = OutputCollector(node)
    params = {'measurement': 'auto', 'weights': str(corrupt), 'processing_width': W, 'processing_height': H,
              'num_planes': 32, 'max_odom_gap': 0.05, 'odom_wait_timeout': 0.5, 'input_reliability': 'reliable',
              'input_depth': 50, 'diagnostics_period': 0.5, 'extrinsic_source': 'parameter'}
    args = ['--ros-args'] + [a for k, v in params.items() for a in ('-p', f'{k}:={v}')] + [
        '-r', 'image:=/image', '-r', 'camera_info:=/camera_info', '-r', 'odom:=/odom']
    proc = start_node(args, env={'OMP_NUM_THREADS': '1'})
    player = BagPlayer(node, bag, rate=0.25)
    played = {}
    try:
        # the node built its estimator and sees the player's publishers; the collector sees the node's outputs
        ready = wait_for(lambda: outputs.diagnostics.get('measurement_model') == 'classical'
                         and all(outputs.diag_int(f'publishers.{k}') == 1 for k in ('image', 'camera_info', 'odom'))
                         and outputs.subs[0].get_publisher_count() == 1, timeout=60.0, spin=spin)
        assert proc.poll() is None, 'node exited early:\n' + stop_process(proc)[1]
        assert ready, f'the node never got ready: {outputs.diagnostics}'
        assert not player.wait_for_subscribers(timeout=10.0, spin=spin)
        thread = threading.Thread(target=lambda: played.update(stats=player.play()), daemon=True)
        thread.start()
        finished = wait_for(lambda: not thread.is_alive() and outputs.diag_int('frames_received') == FRAMES
                            and outputs.diag_int('outputs_published', -1) == len(outputs.complete())
                            and outputs.diag_int('frames_processed') + outputs.diag_int('dropped_total') >= FRAMES - 1,
                            timeout=90.0, spin=spin)
        alive = proc.poll() is None
        diag = dict(outputs.diagnostics)
    finally:
        player.stop()
        code, out = stop_process(proc)
    assert alive, 'the node died during the replay:\n' + out
    assert finished, f'replay did not complete: {diag}\n{out}'
    assert played['stats'].published == sum(player.counts.values())
    assert code == 0, out

    # every fault has its own log message and counter
    for kind, text in EXPECTED_LOGS.items():
        assert text in out, f'no log for {kind}: expected {text!r} in\n{out}'
        assert int(diag.get(f'faults.{kind}', 0)) >= 1, f'faults.{kind} not counted: {diag}'
    assert 'image size changed from 80x64 to 160x128' in out
    assert re.search(r'time went backwards: image stamp 17499999\d\d\.\d+ s after 17500000\d\d\.\d+ s; resetting the '
                     r'estimator and the pose buffer', out)
    assert 'estimator reset: odometry jumped' in out               # no window spans the teleport
    # outputs after those resets are counted (the stream's first output, whose filter starts, is not)
    assert int(diag['output_resets']) >= 1 and 'follows a filter restart: ' in out, diag
    assert 'first frame' not in diag['last_output_reset'] and diag['last_output_reset'], diag
    # 160 -> 80x64 at the third 80x64 image and back at the third 160x128 one; the 1x1 never reached the estimator
    assert int(diag['faults.image_size_change']) == 2, diag
    assert int(diag['dropped.image_too_small']) == 1 and int(diag['dropped.stray_image_size']) == 4, diag
    assert "160x128 is not the stream's 80x64 (2 image(s) in a row" in out, out
    assert 'faults.estimator_exception' not in diag and 'Traceback' not in out, out
    # corrupt weights: the estimator fell back to the classical model, visible in the log and in /diagnostics
    assert 'falling back to the classical' in out
    assert diag['measurement_model'] == 'classical' and diag['measurement_reason'].startswith('fallback')
    assert int(diag['dropped_total']) >= 7

    # valid output before the faults, between them and after the time jump
    stamps = {header_ns(i): i for i in range(FRAMES)}
    done = outputs.complete()
    assert all(r.stamp_ns in stamps and r.frame_id == 'cam' for r in done)
    frames_out = sorted(stamps[r.stamp_ns] for r in done)
    assert any(i > SMALL[-1] and i < JUMP for i in frames_out), frames_out
    after = [r for r in done if stamps[r.stamp_ns] > JUMP]
    assert after, f'no output after the time jump: {frames_out}'
    for rec in after:
        depth = M.image_to_float(rec.depth)
        assert depth.shape == (H, W)
        finite = np.isfinite(depth)
        assert finite.mean() > 0.5 and np.all(depth[finite] > 0)
        gt = seq.depth(stamps[rec.stamp_ns])
        valid = finite & (gt > 0.3) & (gt < 8.0)
        assert np.mean(np.abs(depth[valid] - gt[valid]) / gt[valid]) < 0.6


def test_mailbox_drops_keep_the_longest_stream_gap():
    """Newest-wins drops must not hide a stalled camera: the image that replaces a dropped one inherits its gap,
    so the frame the worker pushes carries the longest interval between received images (Frame.sensor_gap_s)."""
    from dpv_sensor.ros.node_support import Incoming as _Incoming, Mailbox
    from dpv_sensor.ros.node_support import max_gap as _max_gap, merge_incoming as _merge_incoming
    box = Mailbox(merge=_merge_incoming)
    assert not box.put(_Incoming('a', 0.0, 0, gap_ns=None))      # first image: gap unknown
    assert box.take(0.0).msg == 'a'
    assert not box.put(_Incoming('b', 0.0, 0, gap_ns=33))
    assert box.put(_Incoming('c', 0.0, 0, gap_ns=2 * NS))          # b dropped; c came after a 2 s stall
    assert box.put(_Incoming('d', 0.0, 0, gap_ns=33))              # c dropped too
    item = box.take(0.0)
    assert item.msg == 'd' and item.gap_ns == 2 * NS and box.replaced == 2
    assert box.take(0.0) is None
    # without a merge the mailbox hands over the newest item untouched
    plain = Mailbox()
    plain.put(_Incoming('x', 0.0, 0, gap_ns=5))
    plain.put(_Incoming('y', 0.0, 0, gap_ns=1))
    assert plain.take(0.0).gap_ns == 1
    assert _max_gap(None, None) is None and _max_gap(None, 3) == 3 and _max_gap(4, None) == 4 and _max_gap(4, 9) == 9
