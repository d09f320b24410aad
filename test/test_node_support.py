"""Plumbing of the node without ROS: the stamp age /diagnostics reports (a latency on the node's clock, or nothing)
and what images replaced in the mailbox are counted as while the worker waits for odometry."""
from dpv_sensor.ros.node_support import OdometryWait, plausible_age_ms

S = 1_000_000_000


def test_an_age_on_the_same_clock_is_reported_in_milliseconds():
    assert plausible_age_ms(1000 * S + 40_000_000, 1000 * S) == 40.0
    assert plausible_age_ms(1000 * S, 1000 * S + 200_000_000) == -200.0      # a little ahead: clock skew


def test_no_age_before_sim_time_starts_far_off_the_clock_or_ahead_of_it():
    assert plausible_age_ms(0, 100 * S) is None                 # use_sim_time, no /clock yet: the clock reads 0
    assert plausible_age_ms(1_760_000_000 * S, 3 * S) is None   # a bag written from stamp 0, on the system clock
    assert plausible_age_ms(100 * S, 200 * S) is None           # /clock 100 s behind the stamps (not -100000 ms)


def test_images_replaced_during_an_odometry_wait_are_held_until_it_ends():
    wait = OdometryWait()
    assert wait.replaced()                    # the worker computes: busy at once
    wait.start()
    assert not wait.replaced() and not wait.replaced()      # held: the wait's end says why
    assert wait.waiting and wait.end() == 2
    assert not wait.waiting and wait.end() == 0 and wait.replaced()
