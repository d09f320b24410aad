"""The worker's load for /diagnostics (ros.worker_load): the busy share of a window and the stages' medians, by hand."""
import pytest

from dpv_sensor.ros.worker_load import WorkerLoad


def test_busy_share_of_a_slowed_worker_by_hand():
    load = WorkerLoad()
    # images every 0.1 s, each taking 0.09 s: a worker busy 90 % of the time
    for i in range(200):
        load.busy(i * 0.1, i * 0.1 + 0.09)
    assert load.busy_share(20.0, 10.0) == pytest.approx(0.9, abs=1e-9)
    # a span that straddles the window's start counts only its part inside: the window 9.99-19.99 holds 0.05 s of
    # 9.95-10.04, and nothing of 0.00-0.01
    load = WorkerLoad()
    load.busy(0.0, 0.01)
    load.busy(9.95, 10.04)
    assert load.busy_share(19.99, 10.0) == pytest.approx(0.005, abs=1e-9)


def test_busy_share_needs_a_whole_window():
    load = WorkerLoad()
    assert load.busy_share(5.0, 10.0) is None
    load.busy(1.0, 1.5)
    assert load.busy_share(10.99, 10.0) is None        # 9.99 s since the first image
    assert load.busy_share(11.0, 10.0) == pytest.approx(0.05, abs=1e-9)     # 0.5 s busy in the 10 s from 1.0


def test_stage_medians_of_the_last_keyframes():
    load = WorkerLoad(keyframes=3)
    for ms in (10.0, 200.0, 30.0, 40.0):                 # the first falls out of the last three
        load.keyframe({'measurement': ms, 'measurement.features': 1.0, 'anchors': 2.0, 'total': ms + 2.0})
    assert load.stage_medians() == {'measurement': 40.0, 'anchors': 2.0, 'total': 42.0}
    assert load.text() == 'measurement 40, anchors 2, total 42'
    assert WorkerLoad().text() == 'n/a'
