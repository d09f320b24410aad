"""Whether adapted weights are better than the base weights on the held-out runs of a recording.

Both weights are scored on the same held-out runs (:meth:`dpv_sensor.training.adapt_loop.Adapter.score`: one score
per run, lower is better). A lower mean alone is not enough: a gain of a few tenths of a percent is what fitting the
recording's noise and its poses' errors gives too, and such gains made the depth worse on rendered controls. The
adapted weights are taken only when their per-run gains could not come from noise: a one-sided exact sign-flip
(paired permutation) test on the runs' relative differences ``d_k = (adapted_k - base_k) / base_k``. Under the null
hypothesis (no difference) each ``d_k`` is as likely to be ``-d_k``; the p-value is the share of the ``2^n`` sign
patterns whose sum is at most the observed one. It needs no distribution; the smallest p-value ``n`` runs can give
is ``2^-n``, so at a level of 0.05 five runs are the fewest that can show a gain. Overlapping runs share keyframes
and are not independent, so the p-value is, if anything, too small: the test errs towards writing.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Optional, Sequence

import numpy as np

__all__ = ['sign_flip_p_value', 'HeldOutVerdict', 'judge', 'runs_needed', 'veto']

EXACT_MAX_RUNS = 16          # up to this many runs every sign pattern is counted; above, 2^16 random ones (seeded)


def sign_flip_p_value(diff_n: Sequence[float]) -> float:
    """One-sided p-value that the mean of ``diff_n`` is below 0 by chance (exact sign flips; see the module)."""
    d = np.asarray(diff_n, np.float64)
    if d.size == 0 or not np.all(np.isfinite(d)):
        return 1.0
    observed = float(d.sum())
    a = np.abs(d)
    n = d.size
    if n <= EXACT_MAX_RUNS:
        bits = (np.arange(2 ** n)[:, None] >> np.arange(n)[None, :]) & 1       # (2^n, n): 1 = that run negative
        sums = ((1 - 2 * bits) * a[None, :]).sum(1)
    else:
        signs = np.random.default_rng(0).choice([-1.0, 1.0], size=(2 ** 16, n))
        sums = np.concatenate([[observed], (signs * a[None, :]).sum(1)])
    tol = 1e-12 * max(1.0, float(a.sum()))
    return float(np.mean(sums <= observed + tol))


@dataclasses.dataclass
class HeldOutVerdict:
    """The decision on the held-out runs' scores: ``better`` when the adapted mean is lower with ``p_value`` at most
    ``significance``; ``reason`` says why not (None when better)."""
    better: bool
    runs: int
    runs_better: int
    mean_change: float                  # relative change of the mean score, adapted against base (< 0: better)
    p_value: float
    significance: float
    reason: Optional[str]

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def judge(base_n: Sequence[float], adapted_n: Sequence[float], significance: float, kind: str = 'photometric'
          ) -> HeldOutVerdict:
    """The verdict on per-run held-out scores (lower is better) of the base and the adapted weights, paired by run."""
    b = np.asarray(base_n, np.float64)
    a = np.asarray(adapted_n, np.float64)
    if b.shape != a.shape or b.ndim != 1:
        raise ValueError(f'the base and adapted scores must pair run for run, got {b.shape} and {a.shape}')
    scored = np.isfinite(b)                       # a run the base weights could not score says nothing
    b, a = b[scored], a[scored]
    n = int(b.size)
    finite = n > 0 and bool(np.all(np.isfinite(a)))
    mean_b, mean_a = (float(b.mean()), float(a.mean())) if finite else (math.nan, math.nan)
    change = mean_a / mean_b - 1.0 if finite and mean_b != 0 else math.nan
    if finite:
        diff = (a - b) / np.where(np.abs(b) > 0, np.abs(b), 1.0)
        p, better_runs = sign_flip_p_value(diff), int(np.sum(a < b))
    else:
        p, better_runs = 1.0, 0
    scores = f'{kind} {mean_a:.5f} against {mean_b:.5f} for the base weights'
    if not finite:
        reason = f'the held-out scores are not finite ({scores})'
    elif not mean_a < mean_b:
        reason = f'the adapted weights scored no better on the held-out keyframes ({scores})'
    elif p > significance:
        reason = (f'the adapted weights scored better on the held-out keyframes by {-100 * change:.2f} % ({scores}; '
                  f'{better_runs} of {n} runs better), a gain {n} held-out runs cannot tell from noise: p = {p:.3f} > '
                  f'{significance:g} by a sign-flip test (the smallest p {n} runs can give is {2.0 ** -n:.3f})')
    else:
        reason = None
    return HeldOutVerdict(better=reason is None, runs=n, runs_better=better_runs, mean_change=change, p_value=p,
                          significance=float(significance), reason=reason)


def runs_needed(significance: float) -> int:
    """The fewest runs whose sign-flip test can reach ``significance``: the smallest p that n runs give is 2^-n."""
    return max(1, math.ceil(math.log2(1.0 / significance) - 1e-12)) if significance < 1 else 1


def veto(base_n: Sequence[float], adapted_n: Sequence[float], significance: float, kind: str) -> Optional[str]:
    """Why a second score vetoes adapted weights that the judge approved: they score worse on it, by the same
    one-sided sign-flip test at ``significance`` the other way round; None when it does not."""
    worse = judge(adapted_n, base_n, significance, kind)
    if not worse.better:
        return None
    return (f'the depth judge approved the adapted weights, but their held-out {kind} score is worse by '
            f'{100 * (1.0 / (1.0 + worse.mean_change) - 1.0):.2f} % ({worse.runs_better} of {worse.runs} runs worse, '
            f'sign-flip p = {worse.p_value:.3f}): not written')
