"""The held-out decision of the adapt tool: an exact one-sided sign-flip test on the runs' relative differences,
checked on cases small enough to count by hand."""
import math

import numpy as np
import pytest

from dpv_sensor.training.heldout_decision import judge, sign_flip_p_value


def test_sign_flip_p_value_by_hand():
    # every run better: only the observed pattern (all negative) reaches its sum, 1 of 2^n
    assert sign_flip_p_value([-1.0] * 5) == pytest.approx(1 / 32)
    assert sign_flip_p_value([-0.2, -0.1, -0.3, -0.4]) == pytest.approx(1 / 16)
    # |d| = 3, 2, 1 observed as -3 -2 +1 = -4: of the 8 sums (+-3 +-2 +-1) only -6 and -4 are <= -4
    assert sign_flip_p_value([-3.0, -2.0, 1.0]) == pytest.approx(2 / 8)
    # no difference at all, an empty or broken comparison: no evidence
    assert sign_flip_p_value([0.0, 0.0, 0.0]) == 1.0
    assert sign_flip_p_value([]) == 1.0 and sign_flip_p_value([-1.0, math.nan]) == 1.0
    # a worse mean: at least half the patterns lie below it
    assert sign_flip_p_value([1.0, 2.0, -0.5]) > 0.5


def test_many_runs_are_sampled_with_a_fixed_seed():
    d = -np.linspace(0.01, 0.02, 20)                        # 20 runs, all better: p about 2^-16, not 0
    p = sign_flip_p_value(d)
    assert 0 < p < 1e-4 and p == sign_flip_p_value(d)
    noise = np.random.default_rng(1).normal(0.0, 1.0, 20)
    assert 0.05 < sign_flip_p_value(noise - noise.mean()) < 0.95


def test_judge_writes_only_a_gain_the_runs_can_show():
    base = [1.0, 2.0, 1.0, 2.0, 1.0]
    # 1 % better on each of five runs: p = 1/32 <= 0.05
    v = judge(base, [0.99 * b for b in base], 0.05)
    assert v.better and v.reason is None and v.runs == v.runs_better == 5
    assert v.p_value == pytest.approx(1 / 32) and v.mean_change == pytest.approx(-0.01)
    # four runs cannot show it at 0.05 (1/16), and the reason says so; at 1 any lower mean is written
    v = judge(base[:4], [0.99 * b for b in base[:4]], 0.05)
    assert not v.better and 'cannot tell from noise' in v.reason and 'p = 0.062' in v.reason
    assert judge(base[:4], [0.99 * b for b in base[:4]], 1.0).better
    # a worse mean is refused whatever the level
    v = judge(base, [1.01 * b for b in base], 1.0)
    assert not v.better and 'no better' in v.reason
    # a run the base weights could not score is left out; one only the adapted weights could not score refuses
    assert judge(base + [math.nan], [0.99 * b for b in base] + [0.5], 0.05).runs == 5
    v = judge(base, [0.99 * b for b in base[:4]] + [math.nan], 0.05)
    assert not v.better and 'not finite' in v.reason
    with pytest.raises(ValueError, match='pair run for run'):
        judge(base, base[:3], 0.05)
