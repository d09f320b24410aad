"""Fitting a confidence calibration map (``dpv_sensor.core.confidence_calibration``) from (confidence, hit) pairs,
and how calibrated a confidence is before and after it.

The fit, in three steps:

1. **Equal-count bins**: the pairs sorted by confidence and cut into ``bins`` (default :data:`FIT_BINS`) bins of
   (nearly) the same number of pixels; per bin its mean confidence, its share of hits and its pixel count. Bins
   whose mean confidences are equal (a value shared by many pixels, e.g. 0 where the parallax rule leaves no
   support) are merged, so the knots' confidences increase strictly.
2. **Pool adjacent violators**, weighted by the pixel counts: wherever a bin's share of hits is below the one
   before it, the two (and any neighbours that then violate) are pooled into their weighted mean. The result is the
   non-decreasing sequence closest to the bins' shares in weighted least squares (isotonic regression).
3. **Knots**: one per bin at its mean confidence with its pooled share, the inner knots of a flat run dropped,
   and flat ends added at confidence 0 and 1; the map is linear between them (:meth:`ConfidenceCalibration.apply`).

A monotone map keeps the order of the pixels (it can only tie them), so it changes calibration (ECE, the share
kept at a threshold and their delta1) but not how well the confidence ranks errors (AUSE, confident-half ratio).
The figures come from :mod:`dpv_sensor.evaluation.metrics` (:func:`~dpv_sensor.evaluation.metrics.calibration_summary`,
ECE over its 10 equal-width bins).

:func:`isotonic_knots` is steps 1-3 on their own; :func:`fit_logistic` fits a map on several cues instead
(``dpv_sensor.core.confidence_map``, the confidence study's maps).
"""
from __future__ import annotations

import datetime
import json
import pathlib
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from dpv_sensor.common import to_jsonable
from dpv_sensor.core.confidence_calibration import ConfidenceCalibration, save
from dpv_sensor.evaluation import metrics as M

__all__ = ['FIT_BINS', 'FIT_FRACTION', 'equal_count_bins', 'pool_adjacent_violators', 'isotonic_knots',
           'fit_calibration', 'calibration_report', 'record_events', 'split_records', 'calibrate_records',
           'write_calibration', 'fit_logistic']

# equal-count bins of the fit: enough to follow the curve, each with thousands of pixels on a real run
FIT_BINS = 24
# the share of a run's keyframes (the first ones) the map is fitted on; it is scored on the rest
FIT_FRACTION = 0.5
_SAME_CONFIDENCE = 1e-9


def equal_count_bins(conf_n: np.ndarray, hit_n: np.ndarray, bins: int = FIT_BINS
                     ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean confidence, share of hits, pixel count) of ``bins`` equal-count bins of the pairs sorted by
    confidence (at most one bin per pixel), bins of equal mean confidence merged. ValueError without pairs."""
    c = np.asarray(conf_n, np.float64).ravel()
    h = np.asarray(hit_n, np.float64).ravel()
    if c.size != h.size:
        raise ValueError(f'{c.size} confidences but {h.size} hits')
    if c.size == 0:
        raise ValueError('no (confidence, hit) pairs to fit on')
    if not np.all(np.isfinite(c)):
        raise ValueError('the confidences hold NaN or infinity')
    order = np.argsort(c, kind='stable')
    c, h = c[order], h[order]
    k = max(1, min(int(bins), c.size))
    cuts = np.linspace(0, c.size, k + 1).round().astype(np.int64)
    xs, ys, ws = [], [], []
    for a, b in zip(cuts[:-1], cuts[1:]):
        if b <= a:
            continue
        x, y, w = float(c[a:b].mean()), float(h[a:b].mean()), float(b - a)
        if xs and x - xs[-1] <= _SAME_CONFIDENCE:          # same confidence as the bin before: one bin
            tot = ws[-1] + w
            xs[-1] = (xs[-1] * ws[-1] + x * w) / tot
            ys[-1] = (ys[-1] * ws[-1] + y * w) / tot
            ws[-1] = tot
        else:
            xs.append(x)
            ys.append(y)
            ws.append(w)
    return np.asarray(xs), np.asarray(ys), np.asarray(ws)


def pool_adjacent_violators(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The non-decreasing sequence closest to ``y`` in least squares weighted by ``w`` (> 0): adjacent values
    that decrease are pooled into their weighted mean until none does. Same length as ``y``."""
    y = np.asarray(y, np.float64)
    w = np.asarray(w, np.float64)
    if y.shape != w.shape or y.ndim != 1:
        raise ValueError('y and w must be 1-D arrays of one length')
    if np.any(w <= 0):
        raise ValueError('weights must be positive')
    means, weights, sizes = [], [], []
    for yi, wi in zip(y, w):
        means.append(yi)
        weights.append(wi)
        sizes.append(1)
        while len(means) > 1 and means[-2] > means[-1]:
            wt = weights[-2] + weights[-1]
            means[-2] = (means[-2] * weights[-2] + means[-1] * weights[-1]) / wt
            weights[-2] = wt
            sizes[-2] += sizes[-1]
            del means[-1], weights[-1], sizes[-1]
    return np.repeat(np.asarray(means), sizes)


def _knots(x: np.ndarray, y: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Knots of the map through (x, y) (x strictly increasing, y non-decreasing): the inner points of a flat run
    dropped, flat ends added at 0 and 1."""
    keep = np.ones(x.size, bool)
    keep[1:-1] = ~((y[1:-1] == y[:-2]) & (y[1:-1] == y[2:]))
    x, y = x[keep], y[keep]
    if x[0] > 0.0:
        x, y = np.concatenate([[0.0], x]), np.concatenate([[y[0]], y])
    if x[-1] < 1.0:
        x, y = np.concatenate([x, [1.0]]), np.concatenate([y, [y[-1]]])
    return np.clip(x, 0.0, 1.0), np.clip(y, 0.0, 1.0)


def isotonic_knots(conf_n: np.ndarray, hit_n: np.ndarray, bins: int = FIT_BINS
                   ) -> Tuple[np.ndarray, np.ndarray, int]:
    """(confidence knots, probability knots, bins used) of the monotone map: equal-count bins,
    pool-adjacent-violators, flat runs and ends as :func:`_knots` leaves them."""
    x, y, w = equal_count_bins(conf_n, hit_n, bins)
    kx, ky = _knots(x, pool_adjacent_violators(y, w))
    return kx, ky, int(x.size)


def fit_calibration(conf_n: np.ndarray, hit_n: np.ndarray, estimator: Dict[str, Any], *, bins: int = FIT_BINS,
                    fitted_on: Optional[Dict[str, Any]] = None) -> ConfidenceCalibration:
    """The monotone map from the confidence to the share of hits (see the module docstring). ``estimator``: the
    signature of the estimator that produced the confidences (``stream.estimator_config.calibration_signature``);
    ``fitted_on``: metadata, completed with the number of pixels, the bins and the date."""
    kx, ky, used = isotonic_knots(conf_n, hit_n, bins)
    meta = dict(fitted_on or {})
    meta.setdefault('pixels', int(np.asarray(conf_n).size))
    meta.setdefault('bins', used)
    meta.setdefault('date', datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'))
    return ConfidenceCalibration(tuple(float(v) for v in kx), tuple(float(v) for v in ky), dict(estimator), meta)


def calibration_report(conf_n: np.ndarray, hit_n: np.ndarray, calibration: ConfidenceCalibration) -> Dict[str, Any]:
    """``raw`` and ``calibrated``: :func:`~dpv_sensor.evaluation.metrics.calibration_summary` of the confidence
    and of the map applied to it, on the same pixels."""
    c = np.asarray(conf_n, np.float64).ravel()
    return {'raw': M.calibration_summary(c, hit_n), 'calibrated': M.calibration_summary(calibration.apply(c), hit_n)}


# ----------------------------------------------------------------------------------------------------------------
# a run's keyframe records (evaluation.runner.KeyframeRecord): fit on the first part, score on the rest
# ----------------------------------------------------------------------------------------------------------------

def record_events(records: Sequence, min_depth: Optional[float], max_depth: Optional[float]
                  ) -> Tuple[np.ndarray, np.ndarray]:
    """(confidence float32, hit bool) of every scored pixel of the records (:func:`metrics.confidence_events`,
    GT in [min_depth, max_depth] as ``evaluate`` scores it), concatenated."""
    conf: List[np.ndarray] = [np.zeros(0, np.float32)]
    hit: List[np.ndarray] = [np.zeros(0, bool)]
    for r in records:
        if r.confidence_hw is None:
            raise ValueError(f'keyframe {r.index} has no confidence image')
        c, h = M.confidence_events(r.depth_hw, r.gt_depth_hw, r.confidence_hw, min_depth, max_depth)
        conf.append(c.astype(np.float32))
        hit.append(h)
    return np.concatenate(conf), np.concatenate(hit)


def split_records(records: Sequence, fit_fraction: float = FIT_FRACTION) -> Tuple[list, list]:
    """(the first ``fit_fraction`` of the records in time, the rest), at least one in each part; ValueError with
    fewer than two records or a fraction outside (0, 1)."""
    if not 0.0 < float(fit_fraction) < 1.0:
        raise ValueError(f'the fit fraction must lie strictly between 0 and 1, got {fit_fraction}')
    ordered = sorted(records, key=lambda r: r.stamp)
    if len(ordered) < 2:
        raise ValueError(f'{len(ordered)} keyframe output(s): at least two are needed, one to fit on and one to '
                         'score on (a longer recording, or more camera motion)')
    n_fit = min(len(ordered) - 1, max(1, int(round(fit_fraction * len(ordered)))))
    return ordered[:n_fit], ordered[n_fit:]


def _part(records: Sequence, conf: np.ndarray, hit: np.ndarray, calibration: ConfidenceCalibration
          ) -> Dict[str, Any]:
    frames = [int(r.index) for r in records]
    return {'keyframes': len(records), 'frames': [min(frames), max(frames)], 'pixels': int(conf.size),
            **calibration_report(conf, hit, calibration)}


def calibrate_records(records: Sequence, estimator: Dict[str, Any], *, min_depth: Optional[float],
                      max_depth: Optional[float], fit_fraction: float = FIT_FRACTION, bins: int = FIT_BINS,
                      source: str = '', extra: Optional[Dict[str, Any]] = None
                      ) -> Tuple[ConfidenceCalibration, Dict[str, Any]]:
    """Fit a map on the first ``fit_fraction`` of a run's keyframe records and score it on the rest.

    ``estimator``: the signature of the estimator that produced them (``calibration_signature``); ``extra``: more
    metadata for the map's ``fitted_on`` (e.g. the parameters). Returns (the map, the report: ``fit`` and
    ``held_out`` parts, each with its keyframes, frame range, pixels and the ``raw`` / ``calibrated``
    :func:`metrics.calibration_summary`)."""
    fit, held = split_records(records, fit_fraction)
    c_fit, h_fit = record_events(fit, min_depth, max_depth)
    c_held, h_held = record_events(held, min_depth, max_depth)
    frames = [int(r.index) for r in fit]
    meta = {'source': source, 'frames': [min(frames), max(frames)], 'keyframes': len(fit),
            'pixels': int(c_fit.size), 'fit_fraction': float(fit_fraction), 'depth_limits': [min_depth, max_depth],
            **(extra or {})}
    calibration = fit_calibration(c_fit, h_fit, estimator, bins=bins, fitted_on=meta)
    report = {'source': source, 'estimator': estimator, 'fit_fraction': float(fit_fraction),
              'depth_limits': [min_depth, max_depth], 'event': 'true depth within x1.25 of the published depth',
              'fit': _part(fit, c_fit, h_fit, calibration), 'held_out': _part(held, c_held, h_held, calibration),
              'knots': {'confidence': list(calibration.confidence), 'probability': list(calibration.probability)}}
    held_cal = report['held_out']['calibrated']
    calibration.fitted_on.update({'held_out_frames': report['held_out']['frames'],
                                  'held_out_ece_raw': report['held_out']['raw']['ece'],
                                  'held_out_ece_calibrated': held_cal['ece']})
    return calibration, report


def write_calibration(out, calibration: ConfidenceCalibration, report: Dict[str, Any],
                      title: Optional[str] = None) -> Dict[str, pathlib.Path]:
    """``out``/calibration.json (the map), report.json and reliability.png (the held-out keyframes' reliability
    diagram, raw and calibrated); returns {name: path}."""
    from dpv_sensor.evaluation import plots
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {'calibration': save(calibration, out / 'calibration.json'), 'report': out / 'report.json'}
    files['report'].write_text(json.dumps(to_jsonable(report), indent=1) + '\n')
    held = report['held_out']
    files['reliability'] = plots.reliability_plot(
        {'raw': held['raw'], 'calibrated': held['calibrated']}, out / 'reliability.png',
        title=(title or 'confidence calibration') + f": held-out frames {held['frames'][0]}-{held['frames'][1]}")
    return files


def fit_logistic(cues: Dict[str, np.ndarray], hit_n: np.ndarray, inputs: Sequence[str], *, l2: float = 1.0,
                 iterations: int = 50):
    """A :class:`~dpv_sensor.core.confidence_map.ConfidenceMap` on ``inputs`` fitted by maximum likelihood (Newton's
    method on standardised inputs, an L2 penalty ``l2`` on their weights, not on the intercept). A negative weight
    of the confidence's logit is held at 0 (the map stays non-decreasing in the confidence)."""
    from dpv_sensor.core import confidence_map as CM
    X = CM.design_matrix(cues, inputs)
    y = np.asarray(hit_n, np.float64).ravel()
    mu, sd = X.mean(0), X.std(0)
    sd = np.where(sd > 1e-12, sd, 1.0)
    Z = (X - mu) / sd
    free = np.ones(len(inputs), bool)
    for _ in range(2):
        w, b = _newton_logistic(Z[:, free], y, l2, iterations)
        full = np.zeros(len(inputs))
        full[free] = w
        if CM.CONFIDENCE_INPUT in inputs and full[list(inputs).index(CM.CONFIDENCE_INPUT)] < 0:
            free[list(inputs).index(CM.CONFIDENCE_INPUT)] = False
            continue
        break
    weights = full / sd
    return CM.ConfidenceMap(tuple(inputs), tuple(float(v) for v in weights), float(b - np.sum(weights * mu)))


def _newton_logistic(Z: np.ndarray, y: np.ndarray, l2: float, iterations: int) -> Tuple[np.ndarray, float]:
    n, k = Z.shape
    A = np.hstack([np.ones((n, 1)), Z])
    theta = np.zeros(k + 1)
    theta[0] = np.log(max(y.mean(), 1e-6) / max(1 - y.mean(), 1e-6))
    reg = np.full(k + 1, float(l2))
    reg[0] = 0.0
    for _ in range(iterations):
        p = 1.0 / (1.0 + np.exp(-(A @ theta)))
        g = A.T @ (p - y) + reg * theta
        H = (A * (p * (1 - p))[:, None]).T @ A + np.diag(reg + 1e-9)
        step = np.linalg.solve(H, g)
        theta -= step
        if np.max(np.abs(step)) < 1e-8:
            break
    return theta[1:], float(theta[0])
