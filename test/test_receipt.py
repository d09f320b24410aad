"""The image callback's checks without ROS (ImageReceipt, CameraFrame): a second camera on the image topic is dropped
and counted, a frame_id that changes for good is followed, and the publication sequence numbers reach stream_loss."""
import collections
from types import SimpleNamespace

from dpv_sensor.ros.node_support import FaultLog
from dpv_sensor.ros.receipt import CameraFrame, ImageReceipt
from log_lines import Lines

NS = 1_000_000_000


def image(frame_id, stamp_ns, w=4, h=2):
    header = SimpleNamespace(frame_id=frame_id, stamp=None)
    return SimpleNamespace(header=header, encoding='rgb8', width=w, height=h, step=3 * w, data=bytes(3 * w * h),
                           is_bigendian=0)


def receipt():
    log, dropped = Lines(), collections.Counter()
    return ImageReceipt(FaultLog(log), lambda r: dropped.update([r])), log, dropped


def test_a_second_frame_id_is_dropped_counted_and_named_and_never_reaches_the_stream():
    rec, log, dropped = receipt()
    handed = []
    for i in range(30):                       # camera 'left' at 30 Hz, camera 'right' at 10 Hz on the same topic
        t = 100 * NS + i * NS // 30           # (two writers: each numbers its own samples)
        handed.append(rec.image(image('left', t), t, i / 30, t, seq=i + 1))
        if i % 3 == 0:
            assert rec.image(image('right', t + 1000), t + 1000, i / 30, t, seq=i // 3 + 1) is None
    assert all(item is not None for item in handed)
    assert dropped['other_camera'] == 10 and rec.faults.counts['other_camera'] == 10
    warns = [m for level, m in log.lines if level == 'warn' and 'two cameras' in m]
    assert warns and "'right'" in warns[0] and "'left'" in warns[0] and 'Remap one of them' in warns[0]
    # the interleaved numbers go back: never trusted, and the stamps of 'left' alone show no loss
    assert rec.stream_loss.lost_total == 0 and rec.stream_loss.sequence.restarts > 0


def test_one_writer_sending_two_frame_ids_loses_nothing_and_its_numbers_still_count_losses():
    rec, _, dropped = receipt()
    seq = 0
    for i in range(30):
        t = 100 * NS + i * NS // 30
        seq += 1
        rec.image(image('left', t), t, i / 30, t, seq=seq)
        if i % 3 == 0:
            seq += 1 if i != 15 else 3        # at i = 15 two samples of the writer never arrived
            rec.image(image('right', t + 1000), t + 1000, i / 30, t, seq=seq)
    assert dropped['other_camera'] == 10
    assert rec.stream_loss.lost_total == 2 and rec.stream_loss.lost_sequence_gap_only == 2


def test_the_stream_follows_a_new_frame_id_once_the_old_one_stopped_for_good():
    log, dropped = Lines(), collections.Counter()
    cam = CameraFrame(FaultLog(log), lambda r: dropped.update([r]), switch_after_s=2.0)
    assert cam.accept('a', 0, 0.0) and cam.accept('', 1, 0.1)     # an empty frame_id belongs to the stream
    assert not cam.accept('b', 2, 1.0)                             # 'a' came 1 s ago: a second camera
    assert cam.accept('b', 3, 2.5) and cam.frame_id == 'b'         # no 'a' for 2.4 s: renamed for good
    assert not cam.accept('a', 4, 2.6)                             # now 'a' is the other one
    assert dropped['other_camera'] == 2 and cam.faults.counts['camera_frame_change'] == 1
    assert any("changed from 'a' to 'b'" in m for _, m in log.lines)


def test_sequence_numbers_that_go_back_are_logged_once_and_the_stamps_take_over():
    rec, log, _ = receipt()
    for i in range(12):
        t = 100 * NS + i * NS // 30
        rec.image(image('cam', t), t, i / 30, t, seq=50 + i if i < 10 else i - 9)
    assert rec.stream_loss.sequence.restarts == 1
    assert sum('sequence numbers went back (59 -> 1)' in m for _, m in log.lines) == 1


def test_sequence_numbers_that_keep_going_back_are_two_publishers_of_one_frame_id():
    rec, log, _ = receipt()
    for i in range(20):                      # two writers, both 'cam', numbering 1, 2, ... each
        t = 100 * NS + i * NS // 60
        rec.image(image('cam', t), t, i / 60, t, seq=i // 2 + 1)
    assert rec.faults.counts['image_two_publishers'] >= 1
    warn = [m for level, m in log.lines if level == 'warn' and 'two publishers' in m]
    assert warn and "frame_id 'cam'" in warn[0] and 'Remap one of them' in warn[0]
    assert rec.stream_loss.lost_sequence_gap_only == 0
