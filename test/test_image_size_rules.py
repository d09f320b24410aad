"""The image size rules without ROS: the one minimum the estimator and the node's receipt share
(stream.frame.image_too_small), a size change taken only when it persists (stream.continuity.StreamSize), the receipt
refusing tiny and stray images with their own counters and words (raw, and compressed judged from the header without
decoding), the header size reader (compressed_image.compressed_size), and the time rule for images stamped in the
future (continuity.future_stamp)."""
import collections
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from dpv_sensor.ros import compressed_image as CI
from dpv_sensor.ros.node_support import FaultLog
from dpv_sensor.ros.receipt import ImageReceipt
from dpv_sensor.stream.continuity import StreamSize, future_stamp
from dpv_sensor.stream.frame import MIN_IMAGE_SIDE, Frame, checked_image, image_too_small
from log_lines import Lines

NS = 1_000_000_000


def raw(w, h, stamp_ns=0):
    header = SimpleNamespace(frame_id='cam', stamp=None)
    return SimpleNamespace(header=header, encoding='rgb8', width=w, height=h, step=3 * w, data=bytes(3 * w * h),
                           is_bigendian=0)


def receipt(n=3):
    log, dropped = Lines(), collections.Counter()
    return ImageReceipt(FaultLog(log), lambda r: dropped.update([r]), size_change_images=n), log, dropped


# ------------------------------------------------------------------------------------------ the minimum
@pytest.mark.parametrize('w,h,small', [(1, 1, True), (1, 480, True), (640, 1, True), (2, 1, True),
                                       (2, 2, False), (3, 2, False), (2, 5, False)])
def test_the_estimator_and_the_receipt_refuse_exactly_the_same_sizes(w, h, small):
    assert MIN_IMAGE_SIDE == 2
    assert (image_too_small(w, h) is not None) == small
    frame = Frame(stamp=0.0, image=np.zeros((h, w, 3), np.uint8), K_33=np.eye(3))
    if small:
        with pytest.raises(ValueError, match=f'{w}x{h} is smaller than the smallest image the estimator takes '
                                             r'\(2x2 pixels\)'):
            checked_image(frame)
    else:
        checked_image(frame)
    rec, log, dropped = receipt()
    handed = rec.image(raw(w, h), 5 * NS, 0.0, 0)
    assert (handed is None) == small and dropped['image_too_small'] == int(small)
    if small:
        assert log.lines == [('warn', f'dropping image at 5.000 s: {w}x{h} is smaller than the smallest image the '
                                      'estimator takes (2x2 pixels)')]


# ------------------------------------------------------------------------------------------ persistence
def test_a_new_size_is_taken_at_the_nth_image_in_a_row_not_before():
    A, B = (640, 480), (320, 240)
    size = StreamSize(4)
    assert size.image(A).taken and size.size == A
    for k in range(3):                        # N - 1 in a row: strays, the stream stays at A
        verdict = size.image(B)
        assert not verdict.taken and not verdict.changed and size.size == A, k
        assert f"320x240 is not the stream's 640x480 ({k + 1} image(s) in a row" in verdict.stray
    assert size.image(A).taken and size.size == A          # an A ends the run ...
    for _ in range(3):
        assert not size.image(B).taken                     # ... so three more B are strays again
    verdict = size.image(B)                                # the 4th in a row: taken, the stream changes once
    assert verdict.taken and verdict.changed and verdict.previous == A and size.size == B
    assert size.image(B).taken and not size.image(B).changed
    assert not size.image(A).taken                         # the old size is a stray now


def test_a_third_size_starts_its_own_run_and_one_image_at_a_time_is_taken_at_once():
    A, B, C = (160, 128), (16, 12), (4000, 3000)
    size = StreamSize(3)
    size.image(A)
    # B, B, C, B, B: no size had 3 in a row
    assert [size.image(s).taken for s in (B, B, C, B, B)] == [False] * 5 and size.size == A
    assert size.image(B).changed and size.size == B        # now three B in a row
    immediate = StreamSize(1)
    immediate.image(A)
    assert immediate.image(B).changed and immediate.image(A).changed and immediate.size == A
    with pytest.raises(ValueError):
        StreamSize(0)


def test_the_receipt_drops_strays_and_tiny_images_balances_and_hands_a_persisting_size_on():
    rec, log, dropped = receipt(3)
    sizes = [(160, 128)] * 4 + [(1, 1), (160, 128), (16, 12), (160, 128), (80, 64), (80, 64), (160, 128),
                                (80, 64), (80, 64), (80, 64), (80, 64), (160, 128)]
    handed = []
    for i, (w, h) in enumerate(sizes):
        t = 100 * NS + i * NS // 30
        item = rec.image(raw(w, h), t, i / 30, t, seq=i + 1)
        handed.append(None if item is None else (item.msg.width, item.msg.height))
    taken = [s for s in handed if s is not None]
    # the 80x64 run of two ends at a 160x128: strays; the run of four changes the stream at its third image, and
    # the 160x128 after it is a stray of the new stream
    assert taken == [(160, 128)] * 7 + [(80, 64)] * 2, handed
    assert handed[-1] is None and handed[-4:-1] == [None, (80, 64), (80, 64)], handed
    assert dropped == {'image_too_small': 1, 'stray_image_size': 6}, dropped
    assert len(taken) + sum(dropped.values()) == len(sizes)
    assert rec.faults.counts['stray_image_size'] == 6 and rec.faults.counts['image_too_small'] == 1
    strays = [m for level, m in log.lines if level == 'warn' and 'stray' in m]
    assert strays[0].startswith("dropping image at 100.200 s: 16x12 is not the stream's 160x128 (1 image(s) in a "
                                'row of 16x12; a new size is taken once 3 in a row have it) (size_change_images)')
    assert rec.stream_loss.lost_total == 0                 # refused on receipt: dropped, never counted as lost


# ------------------------------------------------------------------------------------------ compressed
def jpeg(w, h, seed=0):
    rng = np.random.default_rng(seed)
    ok, buf = cv2.imencode('.jpg', rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
    assert ok
    return buf.tobytes()


def compressed(data, fmt='rgb8; jpeg compressed bgr8'):
    return SimpleNamespace(header=SimpleNamespace(frame_id='cam', stamp=None), format=fmt, data=data)


def test_a_compressed_image_of_a_refused_size_is_never_decoded():
    rec, log, dropped = receipt(3)
    decoded = []

    def decode(msg):
        decoded.append(msg)
        return CI.decode_message(msg)
    sent = [(160, 128), (4000, 3000), (160, 128), (1, 1), (160, 128)]
    handed = []
    for i, (w, h) in enumerate(sent):
        t = 100 * NS + i * NS // 30
        item = rec.image(compressed(jpeg(w, h, i)), t, i / 30, t, seq=i + 1, decode=decode)
        handed.append(item)
    assert [item is not None for item in handed] == [True, False, True, False, True]
    assert len(decoded) == 3                               # the 4000x3000 and the 1x1 were judged from the header
    assert all(isinstance(item.msg, CI.DecodedImage) and item.msg.width == 160 for item in handed if item)
    assert dropped == {'stray_image_size': 1, 'image_too_small': 1}, dropped
    words = [m for _, m in log.lines]
    assert "dropping compressed image (format 'rgb8; jpeg compressed bgr8') at 100.033 s: 4000x3000 is not the " \
        "stream's 160x128" in words[0], words
    assert '1x1 is smaller than the smallest image the estimator takes (2x2 pixels)' in words[1], words


def test_an_undecodable_payload_is_still_counted_as_undecodable():
    rec, _log, dropped = receipt(3)
    good = jpeg(160, 128)
    assert rec.image(compressed(good), 1, 0.0, 0, decode=CI.decode_message) is not None
    # a header that names the stream's size but a payload cut short: decoded, and refused as undecodable
    assert rec.image(compressed(good[:len(good) // 2]), 2, 0.0, 0, decode=CI.decode_message) is None
    assert rec.image(compressed(b'garbage bytes'), 3, 0.0, 0, decode=CI.decode_message) is None
    assert dropped == {'undecodable_image': 2}, dropped


@pytest.mark.parametrize('w,h', [(1, 1), (16, 12), (3, 2), (640, 480), (4000, 3000)])
def test_the_header_gives_the_size_the_decoder_gives(w, h):
    rng = np.random.default_rng(w)
    colour = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    alpha = np.concatenate([colour, rng.integers(0, 256, (h, w, 1), dtype=np.uint8)], 2)
    payloads = [cv2.imencode('.jpg', colour)[1], cv2.imencode('.jpg', colour, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1],
                cv2.imencode('.jpg', colour[:, :, 0])[1], cv2.imencode('.png', colour)[1],
                cv2.imencode('.png', alpha)[1], cv2.imencode('.png', colour[:, :, 0])[1]]
    for data in payloads:
        data = data.tobytes()
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        assert CI.compressed_size(data) == (w, h) == (decoded.shape[1], decoded.shape[0])


def test_a_header_that_does_not_say_gives_no_size():
    data = jpeg(64, 48)
    assert CI.compressed_size(data) == (64, 48)
    sof = data.index(b'\xff\xc0')
    for cut in (b'', b'\xff\xd8\xff', data[:sof], data[:sof + 6], b'not an image at all', b'\x89PNG\r\n\x1a\n'):
        assert CI.compressed_size(cut) is None, cut[:12]


# ------------------------------------------------------------------------------------------ the future
@pytest.mark.parametrize('ahead_s,future', [(0.9, False), (1.1, True)])
def test_a_stamp_ahead_of_both_the_clock_and_the_odometry_by_more_than_the_tolerance(ahead_s, future):
    clock = 1_800_000_000 * NS
    stamp = clock + int(ahead_s * NS)
    odom = clock - NS // 10                           # the odometry 0.1 s behind the clock
    assert (future_stamp(stamp, clock, odom - NS, 1.0) is not None) == future     # odometry far behind
    # ahead of the clock, but not of the odometry by more than the tolerance: not from the future
    assert future_stamp(stamp, clock, stamp - int(0.9 * NS), 1.0) is None
    # ahead of the odometry by 3 s but not of the clock by more than 1 s: a late odometry, not a future stamp
    assert future_stamp(clock + int(0.9 * NS), clock, clock - 2 * NS, 1.0) is None
    # no odometry yet: the clock alone
    assert (future_stamp(stamp, clock, None, 1.0) is not None) == future


def test_a_future_stamp_says_how_far_ahead_and_a_clock_at_zero_says_nothing():
    clock = 1_800_000_000 * NS
    why = future_stamp(clock + 3600 * NS, clock, clock - NS // 2, 2.5)
    assert why == "stamped 3600.000 s ahead of the node's clock, 3600.500 s ahead of the newest odometry"
    assert future_stamp(clock + 3600 * NS, clock, None, 2.5) == \
        "stamped 3600.000 s ahead of the node's clock, no odometry has arrived yet"
    assert future_stamp(3600 * NS, 0, None, 1.0) is None        # use_sim_time before the first /clock
    assert future_stamp(clock + NS, clock, None, 1.0) is None   # exactly the tolerance: not more than it
