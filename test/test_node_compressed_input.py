"""image_transport compressed colour input through the node process: with ``image_transport: compressed`` and
``image`` remapped to a camera's raw topic, the node subscribes the camera's ``.../image_raw/compressed``
(sensor_msgs/CompressedImage), decodes JPEG and PNG, and publishes depth with the input's stamp and frame_id; a
truncated JPEG and a garbage payload are dropped, counted (faults/dropped.undecodable_image) and logged with their
stamp and reason, no image is counted lost, and the images after them still produce depth.

The client sends one image at a time and waits until the node has accounted for it (frames_processed +
dropped_total), so every image reaches the node. One replay serves the tests of this module."""
import re

import cv2
import pytest

from stream_driver import FAST_PARAMS, StreamDriver, params_args
from dpv_sensor.ros import compressed_image as CI
from dpv_sensor.stream.pose_buffer import NS

FRAMES = 16
TRUNCATED = 6          # frame sent as the first half of its JPEG
GARBAGE = 7            # frame sent as bytes that are no image
PNG_FRAMES = (3, 12)   # frames sent as PNG (the rest JPEG at quality 90)
TOPIC = '/cam/color/image_raw'


@pytest.fixture(scope='module')
def replay():
    """Run the node and send the sequence; returns (driver, diagnostics, node log, {stamp: output frame_id})."""
    from sensor_msgs.msg import CompressedImage
    args = params_args({**FAST_PARAMS, 'image_transport': 'compressed'},
                       {'image': TOPIC, 'camera_info': '/cam/color/camera_info'})
    drv = StreamDriver(args, topics={'image': f'{TOPIC}/compressed', 'camera_info': '/cam/color/camera_info',
                                     'odom': '/odom'}, frames=FRAMES, name='compressed_client',
                       image_type=CompressedImage)
    try:
        drv.wait_ready()
        for i in range(FRAMES):
            t = drv.stamp_ns(i)
            msg = CI.rgb_to_compressed(drv.seq.image(i), t, 'cam', codec='png' if i in PNG_FRAMES else 'jpeg',
                                       jpeg_quality=90)
            if i == TRUNCATED:
                msg.data = bytes(msg.data)[:len(msg.data) // 2]
            elif i == GARBAGE:
                msg.data = b'\x00\x01 not an image \xff' * 8
            drv.send(i, t, image_msg=msg)
            assert drv.wait_accounted(i + 1), f'image {i} was not accounted for: {drv.outputs.diagnostics}'
        diag = drv.wait_diagnostics()
        frames_out = {r.stamp_ns: r.frame_id for r in drv.outputs.complete()}
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    return drv, diag, log, frames_out


def test_the_node_subscribes_the_compressed_child_of_the_remapped_image_topic(replay):
    _drv, diag, log, _out = replay
    assert diag['image_transport'] == 'compressed' and diag['image_topic'] == f'{TOPIC}/compressed', diag
    assert f"image='{TOPIC}/compressed'" in log and 'image_transport=compressed' in log, log
    assert float(diag['image_decode_ms_median']) > 0, diag


def test_compressed_images_produce_depth_with_the_input_stamp_and_frame_id(replay):
    drv, _diag, _log, frames_out = replay
    sent = {drv.stamp_ns(i) for i in range(FRAMES)}
    assert len(frames_out) >= 5, frames_out
    assert set(frames_out) <= sent - {drv.stamp_ns(TRUNCATED), drv.stamp_ns(GARBAGE)}, sorted(frames_out)
    assert set(frames_out.values()) == {'cam'}, frames_out
    assert drv.stamp_ns(PNG_FRAMES[1]) in frames_out or drv.stamp_ns(PNG_FRAMES[0]) in frames_out, sorted(frames_out)


def test_undecodable_payloads_are_counted_logged_and_the_next_image_still_produces_depth(replay):
    drv, diag, log, frames_out = replay
    assert int(diag['faults.undecodable_image']) == 2 and int(diag['dropped.undecodable_image']) == 2, diag
    assert int(diag['dropped_total']) == 2 and int(diag['frames_received']) == FRAMES, diag
    assert int(diag['lost.transport']) == 0, diag            # arrived, so not lost
    lines = re.findall(r"dropping compressed image \(format '([^']*)'\) at (\d+\.\d+) s: (.*)", log)
    assert [(round(float(t), 3), f) for f, t, _why in lines] == \
        [(round(drv.stamp_ns(i) / NS, 3), 'rgb8; jpeg compressed bgr8') for i in (TRUNCATED, GARBAGE)], log
    assert 'truncated JPEG' in lines[0][2] and 'neither JPEG nor PNG' in lines[1][2], lines
    assert any(s > drv.stamp_ns(GARBAGE) for s in frames_out), sorted(frames_out)


def test_the_decoder_reads_what_the_client_sent():
    """The truncated frame of the replay really is undecodable (the test above would pass vacuously otherwise)."""
    from dpv_sensor.data.synthetic import render_sequence
    rgb = render_sequence(4, 1, width=160, height=128).image(0)
    ok, buf = cv2.imencode('.jpg', rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok and CI.decode_compressed('jpeg', buf.tobytes())[0].shape == (128, 160, 3)
    with pytest.raises(CI.UndecodableImage):
        CI.decode_compressed('jpeg', buf.tobytes()[:buf.size // 2])
