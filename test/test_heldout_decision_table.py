"""The held-out decision (training.heldout_decision) just either side of each of its lines, every p-value counted by
hand over the 2^n sign patterns:

- the adapted weights are written when their mean is strictly lower *and* p <= significance (p equal to the level
  is written; a level just under it is not);
- an equal mean is refused whatever the level;
- sums that tie with the observed one count towards p (within rounding of the relative differences);
- up to 16 runs every sign pattern is counted (p can be 2^-16); above, 2^16 seeded random patterns plus the observed
  one (p is at least 1 / 65537, never 2^-17).
"""
import math

import pytest

from dpv_sensor.training.heldout_decision import judge, sign_flip_p_value

BASE5 = [1.0, 2.0, 1.0, 2.0, 1.0]


@pytest.mark.parametrize('base, adapted, significance, better, p, runs_better, why', [
    # five runs each 1 % better: only the all-negative pattern of 32 reaches the sum
    (BASE5, [0.99 * b for b in BASE5], 0.05, True, 1 / 32, 5, None),
    (BASE5, [0.99 * b for b in BASE5], 1 / 32, True, 1 / 32, 5, None),          # p equal to the level: written
    (BASE5, [0.99 * b for b in BASE5], 0.031, False, 1 / 32, 5, 'p = 0.031 > 0.031'),
    # four runs: 1 of 16
    (BASE5[:4], [0.99 * b for b in BASE5[:4]], 0.05, False, 1 / 16, 4, 'the smallest p 4 runs can give is 0.062'),
    (BASE5[:4], [0.99 * b for b in BASE5[:4]], 0.0625, True, 1 / 16, 4, None),
    # six runs, five 1 % better and one 1 % worse: sums of six +-1 % at most -4 %: 5 or 6 negative, 6 + 1 of 64
    ([1.0] * 6, [0.99] * 5 + [1.01], 0.1, False, 7 / 64, 5, 'p = 0.109 > 0.1'),
    ([1.0] * 6, [0.99] * 5 + [1.01], 0.11, True, 7 / 64, 5, None),
    # an equal mean (two runs 10 % better, two 10 % worse, one equal): refused even at level 1; by hand the sums of
    # +-10 % four times (the equal run doubles every pattern) at most 0: 2, 3 or 4 negative, 6 + 4 + 1 of 16
    ([1.0] * 5, [0.9, 0.9, 1.1, 1.1, 1.0], 1.0, False, 22 / 32, 2, 'no better'),
    # a mean lower by a hair, one run better: half the patterns, written only at a level of 0.5 or more
    ([1.0] * 5, [1.0] * 4 + [0.999999], 0.5, True, 1 / 2, 1, None),
    ([1.0] * 5, [1.0] * 4 + [0.999999], 0.49, False, 1 / 2, 1, 'p = 0.500 > 0.49'),
    # worse: refused
    (BASE5, [1.01 * b for b in BASE5], 1.0, False, 1.0, 0, 'no better'),
])
def test_the_decision_either_side_of_its_lines(base, adapted, significance, better, p, runs_better, why):
    v = judge(base, adapted, significance)
    assert v.better is better, v
    assert v.p_value == pytest.approx(p, abs=1e-12)
    assert v.runs == len(base) and v.runs_better == runs_better
    if why is None:
        assert v.reason is None
    else:
        assert why in v.reason, v.reason


@pytest.mark.parametrize('diff, p', [
    ([-0.1, -0.2, 0.1], 3 / 8),     # observed -0.2: -0.4, and -0.2 twice (-0.1 - 0.2 + 0.1 ties after rounding)
    ([-2.0, -1.0, 1.0], 3 / 8),     # the same in whole numbers
    ([-3.0, -2.0, 1.0], 2 / 8),     # -6 and -4 of +-3 +-2 +-1
    ([1.0, 2.0, -0.5], 7 / 8),      # observed 2.5: all but +3.5
    ([-1.0] * 16, 2.0 ** -16),      # 16 runs: every pattern counted, only one reaches the sum
    ([0.0, 0.0, 0.0], 1.0),
    ([], 1.0),
    ([-1.0, math.inf], 1.0),
])
def test_sign_flip_p_values_by_hand(diff, p):
    assert sign_flip_p_value(diff) == pytest.approx(p, abs=1e-15)


def test_above_16_runs_the_patterns_are_sampled():
    """17 runs all better: counted exactly p would be 2^-17; 2^16 sampled patterns plus the observed one give at
    least 1 / 65537 (and the same value every time: the sampling is seeded)."""
    p = sign_flip_p_value([-1.0] * 17)
    assert p >= 1 / 65537 > 2.0 ** -17
    assert p < 1e-4 and p == sign_flip_p_value([-1.0] * 17)
