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

from dpv_sensor.training.heldout_decision import judge, runs_needed, sign_flip_p_value, veto

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


def test_the_runs_differences_are_relative_to_their_base():
    """Five runs of score 1 each 10 % better and one of score 10 that is 3 % worse: relative differences -0.1 x 5 and
    +0.03, sum -0.47; only two of 64 sign patterns reach it (the five -0.1 negative, the +0.03 either way): p = 1/32,
    written at 0.05. As absolute differences the worse run's +0.3 would outweigh the others' -0.5 (p 0.42)."""
    v = judge([1.0] * 5 + [10.0], [0.9] * 5 + [10.3], 0.05)
    assert v.better and v.p_value == pytest.approx(2 / 64) and v.runs_better == 5


@pytest.mark.parametrize('significance, runs', [
    (0.05, 5),               # 2^-4 = 0.0625 > 0.05 >= 2^-5
    (1 / 32, 5),             # exactly 2^-5: five runs reach it
    (0.01, 7),               # 2^-6 = 0.0156 > 0.01 >= 2^-7
    (0.5, 1),
    (1.0, 1),
])
def test_runs_needed_by_hand(significance, runs):
    assert runs_needed(significance) == runs


def test_the_veto_is_the_test_the_other_way_round():
    """A second score on which the adapted weights are 10 % worse on five runs of five (p = 1/32 the other way)
    vetoes them; one on which they are 10 % better does not."""
    why = veto([1.0] * 5, [1.1] * 5, 0.05, 'photometric')
    assert why is not None and 'photometric score is worse by 10.00 %' in why and '5 of 5 runs worse' in why, why
    assert veto([1.0] * 5, [0.9] * 5, 0.05, 'photometric') is None
    assert veto([1.0] * 4, [1.1] * 4, 0.05, 'photometric') is None      # four runs cannot show it at 0.05


def test_above_16_runs_the_p_value_counts_2_to_the_16_seeded_patterns_and_the_observed_one():
    """17 runs each better: the sampled p is a count over 2^16 + 1 sign patterns (the observed one among them),
    so p * 65537 is a whole number; the fixed seed makes it the same on every call."""
    p = sign_flip_p_value([-1.0] * 17)
    hits = p * 65537
    assert abs(hits - round(hits)) < 1e-6 and round(hits) >= 1, p
    assert sign_flip_p_value([-1.0] * 17) == p


def test_a_run_whose_base_scores_zero_counts_as_no_difference():
    """A run the base weights score 0 on (and the adapted too): its difference is taken over 1, not 0, so it is 0
    and ties in every sign pattern; the five 10 % gains alone decide: p = 2 / 64 (the zero either way)."""
    v = judge([0.0] + [1.0] * 5, [0.0] + [0.9] * 5, 0.05)
    assert v.better and v.p_value == pytest.approx(2 / 64) and v.runs == 6


def test_a_single_held_out_run_is_judged():
    """One run, 50 % better: p = 1/2 (one of two sign patterns); written at significance 1, refused at 0.05 with
    the reason that one run cannot show it."""
    v = judge([1.0], [0.5], 1.0)
    assert v.better and v.p_value == pytest.approx(0.5) and v.runs == 1
    v = judge([1.0], [0.5], 0.05)
    assert not v.better and 'the smallest p 1 runs can give is 0.500' in v.reason, v.reason
