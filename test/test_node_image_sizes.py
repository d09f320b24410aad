"""Tiny and stray image sizes through the node process: among 160x128 images every 5th 1x1, every 5th 16x12 (raw),
every 5th a 4000x3000 JPEG and every 5th a 1x1 JPEG (image_transport compressed). None reaches the estimator: no
exception, no traceback, no filter restart, depth keeps coming (at least 80 % of a clean phase's outputs), and each is
counted by its cause (dropped.image_too_small, dropped.stray_image_size) with a WARN naming the size. A size that
persists is taken at the size_change_images-th image in a row (3), not at the 2nd: the filter restarts once for it.

The client sends one image at a time and waits until the node has accounted for it (frames_processed +
dropped_total), so every image reaches the receipt and the counts are exact; processed + dropped = received = sent."""
import re

import cv2
import numpy as np

from stream_driver import FAST_PARAMS, ONE_AT_A_TIME, StreamDriver, params_args
from dpv_sensor.ros import compressed_image as CI

PARAMS = {**FAST_PARAMS, **ONE_AT_A_TIME, 'pose_refinement': 'off'}      # sizes are under test, not the window
REMAPS = {'image': '/cam/image', 'camera_info': '/cam/camera_info', 'odom': '/odom'}
CLEAN, PHASE, TAIL = 20, 25, 4      # a clean phase, phases with every 5th image stray, clean images at the end


class Phases:
    """Sends images one at a time and remembers which stamps belong to which phase. The rendered sequence is played
    forth and back (its end does not jump back to its start: that would be an odometry teleport)."""

    def __init__(self, drv: StreamDriver):
        self.drv, self.i, self.stamps, self.resets = drv, 0, {}, {}

    @property
    def frame(self) -> int:
        n = len(self.drv.seq)
        k = self.i % (2 * n - 2)
        return k if k < n else 2 * n - 2 - k

    def image(self, size) -> np.ndarray:
        """The current frame at `size` (w, h)."""
        rgb = self.drv.seq.image(self.frame)
        return cv2.resize(rgb, size, interpolation=cv2.INTER_LINEAR if size[0] > rgb.shape[1] else cv2.INTER_AREA)

    def send(self, phase: str, image=None, image_msg=None) -> None:
        drv = self.drv
        t = drv.stamp_ns(self.i)
        if image_msg is not None:
            image_msg = image_msg(self.frame, t)
        drv.send(self.frame, t, image=image, image_msg=image_msg)
        self.stamps.setdefault(phase, []).append(t)
        self.i += 1
        assert drv.wait_accounted(self.i), (phase, drv.outputs.diagnostics)

    def end(self, phase: str) -> None:
        """The filter restarts counted once the phase's images are accounted for."""
        self.resets[phase] = int(self.drv.wait_diagnostics()['filter_resets'])

    def outputs(self, phase: str) -> int:
        return len(set(self.stamps[phase]) & set(self.drv.outputs.by_stamp))


def _check(drv: StreamDriver, ph: Phases, diag: dict, log: str, phases: list[str]) -> None:
    assert drv.code == 0, log
    assert 'Traceback' not in log and 'faults.estimator_exception' not in diag, log
    assert int(diag['frames_received']) == ph.i == int(diag['frames_processed']) + int(diag['dropped_total']), diag
    clean = ph.outputs('clean')
    print('outputs by phase:', {phase: ph.outputs(phase) for phase in ph.stamps}, 'resets:', ph.resets)
    assert clean >= CLEAN - 3, (clean, diag)
    for phase in phases:
        # the stray images never restarted the filter, and depth kept coming for the images around them
        assert ph.resets[phase] == ph.resets['clean'], (phase, ph.resets)
        assert ph.outputs(phase) >= 0.8 * clean, (phase, ph.outputs(phase), clean)


def test_raw_tiny_and_stray_images_are_dropped_by_cause_and_a_size_that_persists_restarts_once():
    drv = StreamDriver(params_args(PARAMS, REMAPS), topics=REMAPS, frames=40, name='raw_sizes')
    ph = Phases(drv)
    tiny = np.full((1, 1, 3), 128, np.uint8)
    try:
        drv.wait_ready()
        for _ in range(CLEAN):
            ph.send('clean')
        ph.end('clean')
        for k in range(PHASE):
            ph.send('1x1', image=tiny if k % 5 == 4 else None)
        ph.end('1x1')
        for k in range(PHASE):
            ph.send('16x12', image=ph.image((16, 12)) if k % 5 == 4 else None)
        ph.end('16x12')
        after_strays = drv.wait_diagnostics()
        # size_change_images 3: two 80x64 in a row are strays (no restart) ...
        for _ in range(2):
            ph.send('80x64 twice', image=ph.image((80, 64)))
        for _ in range(3):
            ph.send('80x64 twice')
        ph.end('80x64 twice')
        # ... three are a size change: taken at the third (one restart), and the same back to 160x128
        for _ in range(3):
            ph.send('80x64 three times', image=ph.image((80, 64)))
        for _ in range(3 + TAIL):
            ph.send('back')
        ph.end('back')
        diag = drv.wait_diagnostics()
    finally:
        log = drv.stop()
    _check(drv, ph, diag, log, ['1x1', '16x12'])
    assert ph.resets['80x64 twice'] == ph.resets['clean'], ph.resets
    # depth for the first image after the two strays (the next two wait for keyframes after them, which the size
    # change that follows restarts)
    assert ph.stamps['80x64 twice'][2] in drv.outputs.by_stamp, sorted(drv.outputs.by_stamp)
    assert int(after_strays['dropped.image_too_small']) == 5 and int(after_strays['faults.image_too_small']) == 5
    assert int(after_strays['dropped.stray_image_size']) == 5, after_strays
    assert 'faults.image_size_change' not in after_strays, after_strays
    # 80x64: 2 (twice) + 2 (the first two of three); back: the first two 160x128 of the new 80x64 stream
    assert int(diag['dropped.stray_image_size']) == 5 + 2 + 2 + 2, diag
    assert int(diag['faults.image_size_change']) == 2, diag
    assert ph.resets['back'] == ph.resets['clean'] + 2, ph.resets
    assert int(diag['dropped_total']) == 5 + 11, diag
    assert re.search(r'WARN.*dropping image at \d+\.\d+ s: 1x1 is smaller than the smallest image the estimator '
                     r'takes \(2x2 pixels\)', log), log
    assert re.search(r"WARN.*dropping image at \d+\.\d+ s: 16x12 is not the stream's 160x128 \(1 image\(s\) in a "
                     r'row of 16x12; a new size is taken once 3 in a row have it\) \(size_change_images\)', log), log
    assert log.count('image size changed from 160x128 to 80x64; resetting the estimator') == 1, log
    assert log.count('image size changed from 80x64 to 160x128; resetting the estimator') == 1, log


def test_compressed_huge_and_tiny_images_are_dropped_by_cause_without_decoding_and_depth_keeps_coming():
    from sensor_msgs.msg import CompressedImage
    topic = '/cam/color/image_raw'
    drv = StreamDriver(params_args({**PARAMS, 'image_transport': 'compressed'},
                                   {'image': topic, 'camera_info': '/cam/color/camera_info'}),
                       topics={'image': f'{topic}/compressed', 'camera_info': '/cam/color/camera_info',
                               'odom': '/odom'}, frames=40, name='compressed_sizes', image_type=CompressedImage)
    ph = Phases(drv)

    def jpeg(size=None):
        def make(frame, t):
            rgb = drv.seq.image(frame) if size is None else ph.image(size)
            return CI.rgb_to_compressed(rgb, t, 'cam', codec='jpeg', jpeg_quality=90)
        return make
    try:
        drv.wait_ready()
        for _ in range(CLEAN):
            ph.send('clean', image_msg=jpeg())
        ph.end('clean')
        for k in range(PHASE):
            ph.send('4000x3000', image_msg=jpeg((4000, 3000) if k % 5 == 4 else None))
        ph.end('4000x3000')
        for k in range(PHASE):
            ph.send('1x1', image_msg=jpeg((1, 1) if k % 5 == 4 else None))
        for _ in range(TAIL):
            ph.send('tail', image_msg=jpeg())
        ph.end('1x1')
        diag = drv.wait_diagnostics()
    finally:
        log = drv.stop()
    _check(drv, ph, diag, log, ['4000x3000', '1x1'])
    assert int(diag['dropped.stray_image_size']) == 5 and int(diag['dropped.image_too_small']) == 5, diag
    assert int(diag['dropped_total']) == 10 and 'faults.image_size_change' not in diag, diag
    assert int(diag['lost.transport']) == 0, diag
    assert re.search(r"WARN.*dropping compressed image \(format 'rgb8; jpeg compressed bgr8'\) at \d+\.\d+ s: "
                     r"4000x3000 is not the stream's 160x128", log), log
    assert re.search(r"WARN.*dropping compressed image \(format 'rgb8; jpeg compressed bgr8'\) at \d+\.\d+ s: "
                     r'1x1 is smaller than the smallest image the estimator takes \(2x2 pixels\)', log), log
