"""A confidence map on cues: the probability that the published depth lies within x1.25 of the truth as a logistic
function of a few per-pixel and per-frame cues (``dpv_sensor.stream.confidence_features`` gathers them), the
confidence's logit first. numpy only; no stream, no ROS.

``INPUTS`` is the one home of how a cue enters the map (logs, fills for missing values); a map names the inputs it
uses, and its weights act on them as they are (no hidden scaling). The weight of ``logit_confidence`` is never
negative, so the map is non-decreasing in the confidence whatever the other cues are. The fit is
``dpv_sensor.evaluation.calibration_fit.fit_logistic``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Mapping, Sequence, Tuple

import numpy as np

__all__ = ['INPUTS', 'CONFIDENCE_INPUT', 'ConfidenceMap', 'design_matrix', 'logit']

CONFIDENCE_INPUT = 'logit_confidence'
# a confidence is clipped to [EPS, 1 - EPS] before its logit
EPS = 1e-3
# the photometric residual where no source sees the pixel (about the 95th percentile of seen pixels)
PHOTOMETRIC_MISSING = 0.15
TEXTURE_FLOOR = 1e-3
# a pose std (planes) beyond this, or not finite, counts as this much (no plane index is known any more)
POSE_SIGMA_CAP = 64.0


def logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(np.asarray(p, np.float64), EPS, 1.0 - EPS)
    return np.log(p / (1.0 - p))


def _f(name: str) -> Callable[[Mapping[str, np.ndarray]], np.ndarray]:
    return lambda c: np.asarray(c[name], np.float64)


def _photometric(name: str):
    return lambda c: np.nan_to_num(np.asarray(c[name], np.float64), nan=PHOTOMETRIC_MISSING)


INPUTS: Dict[str, Callable[[Mapping[str, np.ndarray]], np.ndarray]] = {
    CONFIDENCE_INPUT: lambda c: logit(c['confidence']),
    'entropy': _f('entropy'),
    'second_mode': _f('second_mode'),
    'log_parallax': lambda c: np.log1p(np.nan_to_num(np.asarray(c['parallax_px'], np.float64), nan=0.0)),
    'log_texture': lambda c: np.log(np.asarray(c['texture'], np.float64) + TEXTURE_FLOOR),
    'photometric': _photometric('photometric'),
    'views': _f('views'),
    'log_innovation': lambda c: np.log1p(np.nan_to_num(np.asarray(c['innovation'], np.float64), nan=0.0)),
    'first_keyframe': lambda c: np.isnan(np.asarray(c['innovation'], np.float64)).astype(np.float64),
    'log_pose_sigma': lambda c: np.log1p(np.clip(np.nan_to_num(np.asarray(c['pose_sigma'], np.float64),
                                                               nan=POSE_SIGMA_CAP, posinf=POSE_SIGMA_CAP),
                                                 0.0, POSE_SIGMA_CAP)),
    'log_depth': lambda c: np.log(np.asarray(c['depth'], np.float64)),
    'frame_logit_confidence': lambda c: logit(c['frame_confidence']),
    'frame_log_parallax': lambda c: np.log1p(np.nan_to_num(np.asarray(c['frame_parallax_px'], np.float64),
                                                           nan=0.0)),
    'frame_log_texture': lambda c: np.log(np.asarray(c['frame_texture'], np.float64) + TEXTURE_FLOOR),
    'frame_photometric': _photometric('frame_photometric'),
}


def design_matrix(cues: Mapping[str, np.ndarray], inputs: Sequence[str]) -> np.ndarray:
    """(n, len(inputs)) float64: each input of ``INPUTS`` computed from the cues (flattened)."""
    unknown = [k for k in inputs if k not in INPUTS]
    if unknown:
        raise KeyError(f'unknown map inputs {unknown}; known: {sorted(INPUTS)}')
    if not inputs:
        return np.zeros((np.size(cues['confidence']), 0))
    return np.stack([INPUTS[k](cues).ravel() for k in inputs], 1)


@dataclass(frozen=True)
class ConfidenceMap:
    """p = sigmoid(intercept + sum_j weights[j] * input_j)."""
    inputs: Tuple[str, ...]
    weights: Tuple[float, ...]
    intercept: float
    fitted_on: Dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        if len(self.inputs) != len(self.weights):
            raise ValueError(f'{len(self.weights)} weights for {len(self.inputs)} inputs')
        if CONFIDENCE_INPUT in self.inputs and self.weights[self.inputs.index(CONFIDENCE_INPUT)] < 0:
            raise ValueError(f'the weight of {CONFIDENCE_INPUT} must not be negative (the map is non-decreasing in '
                             'the confidence)')

    def apply(self, cues: Mapping[str, np.ndarray]) -> np.ndarray:
        """The calibrated confidence, the shape of ``cues['confidence']``, float64 in (0, 1)."""
        shape = np.shape(cues['confidence'])
        z = self.intercept + design_matrix(cues, self.inputs) @ np.asarray(self.weights, np.float64)
        return (1.0 / (1.0 + np.exp(-z))).reshape(shape)

    def to_dict(self) -> Dict[str, Any]:
        return {'inputs': list(self.inputs), 'weights': [float(w) for w in self.weights],
                'intercept': float(self.intercept), 'fitted_on': self.fitted_on}
