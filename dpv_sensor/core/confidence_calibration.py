"""A confidence calibration map: the raw confidence (the DPV's mass in the x1.25 band around the published depth)
-> the probability that the true depth lies within x1.25 of the published one, measured on a recording with depth
ground truth. numpy and torch only; no stream, no ROS.

The map is monotone (non-decreasing) and piecewise linear through a few knots (an isotonic fit, see
``dpv_sensor.evaluation.calibration_fit``), held constant outside the first and the last knot. It lives in a small
JSON file::

    {"format": "dpv_sensor.confidence_calibration", "version": 1,
     "event": "true depth within x1.25 of the published depth",
     "knots": {"confidence": [0.0, 0.12, ...], "probability": [0.31, 0.31, ...]},
     "estimator": {"measurement": "network", "weights": "lite.safetensors", "processing_size": [320, 256],
                   "depth_planes": {"d_min": 0.3, "d_max": 8.0, "num_planes": 64}, "confidence": "ratio 1.25"},
     "fitted_on": {"source": ..., "frames": ..., "pixels": ..., "date": ..., ...}}

``estimator`` is what the raw confidence was measured with (:func:`signature`): a map is only valid for the same
measurement model, weights file, processing size, depth planes and confidence definition, and
:meth:`ConfidenceCalibration.check_signature` refuses another. ``fitted_on`` is free-form metadata (what the map was
fitted on and how well it did); it must be a JSON object. :func:`load` refuses a malformed file with a
:class:`CalibrationError` that says what is wrong, and a file larger than :data:`MAX_FILE_BYTES` (or not a regular
file) before it reads any of it: a map is a few kB.
"""
from __future__ import annotations

import json
import math
import pathlib
import stat
from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np

from dpv_sensor.common import to_jsonable

__all__ = ['FORMAT', 'VERSION', 'EVENT', 'SIGNATURE_KEYS', 'MAX_FILE_BYTES', 'CalibrationError',
           'ConfidenceCalibration', 'signature', 'from_dict', 'load', 'save']

FORMAT = 'dpv_sensor.confidence_calibration'
VERSION = 1
EVENT = 'true depth within x1.25 of the published depth'
# the estimator settings a map depends on (the keys of signature()), in the order mismatches are reported
SIGNATURE_KEYS = ('measurement', 'weights', 'processing_size', 'depth_planes', 'confidence')
_PLANE_TOL = 1e-6
# the largest calibration file load() reads: a fitted map has at most a few hundred knots and a little metadata (a
# few kB); anything near this is not a calibration file, and is refused from its size before it is read
MAX_FILE_BYTES = 4 * 1024 * 1024


class CalibrationError(ValueError):
    """A calibration file that cannot be used: unreadable, malformed, or fitted for another estimator."""


def signature(measurement: str, weights: Optional[str], processing_size: Sequence[int],
              depth_range: Sequence[float], num_planes: int, confidence: str) -> Dict[str, Any]:
    """The estimator settings a map is valid for: the measurement model ('network' / 'classical'), the weights file
    name (its base name; None for the classical model), the processing size [width, height], the depth planes
    (d_min, d_max, count) and the confidence definition (e.g. 'ratio 1.25')."""
    return {'measurement': str(measurement),
            'weights': None if not weights else pathlib.PurePath(str(weights)).name,
            'processing_size': [int(processing_size[0]), int(processing_size[1])],
            'depth_planes': {'d_min': float(depth_range[0]), 'd_max': float(depth_range[1]),
                             'num_planes': int(num_planes)},
            'confidence': str(confidence)}


def _same(key: str, a: Any, b: Any) -> bool:
    if key == 'depth_planes':
        return int(a['num_planes']) == int(b['num_planes']) and all(
            math.isclose(float(a[k]), float(b[k]), rel_tol=_PLANE_TOL, abs_tol=_PLANE_TOL) for k in ('d_min', 'd_max'))
    return a == b


def _describe(key: str, value: Any) -> str:
    if key == 'processing_size':
        return f'{value[0]}x{value[1]}'
    if key == 'depth_planes':
        return f"{value['num_planes']} planes {value['d_min']:g}-{value['d_max']:g} m"
    return 'none' if value is None else repr(value)


@dataclass(frozen=True)
class ConfidenceCalibration:
    """The map's knots (``confidence`` strictly increasing in [0, 1], ``probability`` non-decreasing in [0, 1]),
    the estimator it was fitted for (:func:`signature`) and free metadata; ``path`` where it was loaded from."""
    confidence: Tuple[float, ...]
    probability: Tuple[float, ...]
    estimator: Dict[str, Any]
    fitted_on: Dict[str, Any] = field(default_factory=dict)
    path: Optional[str] = None

    @property
    def name(self) -> str:
        """The file name (without folders), or 'in memory'."""
        return pathlib.PurePath(self.path).name if self.path else 'in memory'

    def apply(self, conf):
        """The calibrated confidence of ``conf`` (a numpy array, a torch tensor or a number; same type, shape and
        dtype back): linear between the knots, the end values outside them."""
        if type(conf).__module__ == 'torch':
            return self._apply_torch(conf)
        c = np.asarray(conf)
        out = np.interp(c.astype(np.float64), self.confidence, self.probability)
        if np.ndim(conf) == 0 and not isinstance(conf, np.ndarray):
            return float(out)
        return out.astype(c.dtype if np.issubdtype(c.dtype, np.floating) else np.float64)

    def _apply_torch(self, conf):
        import torch
        x = torch.as_tensor(self.confidence, dtype=torch.float64, device=conf.device)
        y = torch.as_tensor(self.probability, dtype=torch.float64, device=conf.device)
        c = conf.to(torch.float64).clamp(x[0], x[-1])
        if len(self.confidence) == 1:
            return torch.full_like(conf, float(y[0]))
        i = torch.searchsorted(x, c.contiguous(), right=True).clamp(1, len(self.confidence) - 1)
        x0, x1, y0, y1 = x[i - 1], x[i], y[i - 1], y[i]
        return (y0 + (c - x0) / (x1 - x0) * (y1 - y0)).to(conf.dtype)

    def check_signature(self, actual: Dict[str, Any]) -> None:
        """Raise :class:`CalibrationError` naming every setting where ``actual`` (:func:`signature` of the estimator
        that would apply the map) differs from what the map was fitted with."""
        diffs = [f'{key} {_describe(key, self.estimator.get(key))} (the estimator: {_describe(key, actual[key])})'
                 for key in SIGNATURE_KEYS if not _same(key, self.estimator.get(key), actual[key])]
        if diffs:
            raise CalibrationError('fitted for another estimator: ' + '; '.join(diffs) +
                                   '. Fit a calibration with these settings (the calibrate tool) or use the '
                                   'settings it was fitted with')

    def to_dict(self) -> Dict[str, Any]:
        """The file's JSON object."""
        return {'format': FORMAT, 'version': VERSION, 'event': EVENT,
                'knots': {'confidence': list(self.confidence), 'probability': list(self.probability)},
                'estimator': self.estimator, 'fitted_on': self.fitted_on}


def _number_list(knots: Dict[str, Any], key: str) -> Tuple[float, ...]:
    values = knots.get(key)
    if not isinstance(values, list):
        raise CalibrationError(f'knots.{key} must be a list of numbers, got {type(values).__name__}')
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in values):
        raise CalibrationError(f'knots.{key} must hold numbers only')
    out = tuple(float(v) for v in values)
    bad = [v for v in out if not math.isfinite(v)]
    if bad:
        raise CalibrationError(f'knots.{key} holds a non-finite value ({bad[0]})')
    outside = [v for v in out if not 0.0 <= v <= 1.0]
    if outside:
        raise CalibrationError(f'knots.{key} holds {outside[0]:g}, outside [0, 1]')
    return out


def _check_estimator(est: Any) -> Dict[str, Any]:
    if not isinstance(est, dict):
        raise CalibrationError("'estimator' must be an object (what the map was fitted with)")
    missing = [k for k in SIGNATURE_KEYS if k not in est]
    if missing:
        raise CalibrationError(f"'estimator' lacks {', '.join(missing)}")
    try:
        signature(est['measurement'], est['weights'], est['processing_size'],
                  (est['depth_planes']['d_min'], est['depth_planes']['d_max']), est['depth_planes']['num_planes'],
                  est['confidence'])
    except (TypeError, ValueError, KeyError, IndexError) as exc:
        raise CalibrationError(f"'estimator' is malformed ({type(exc).__name__}: {exc})") from None
    return est


def from_dict(data: Any, path: Optional[str] = None) -> ConfidenceCalibration:
    """A :class:`ConfidenceCalibration` from the file's JSON object, checked: format and version, knots (at least
    two, numbers in [0, 1], no NaN, confidence strictly increasing, probability non-decreasing, equal counts), the
    estimator block (:data:`SIGNATURE_KEYS`) and ``fitted_on`` (an object). Raises :class:`CalibrationError`."""
    if not isinstance(data, dict):
        raise CalibrationError('not a calibration file: the JSON is not an object')
    missing = [k for k in ('format', 'version', 'knots', 'estimator') if k not in data]
    if missing:
        raise CalibrationError(f"missing key{'s' if len(missing) > 1 else ''} {', '.join(missing)}")
    if data['format'] != FORMAT:
        raise CalibrationError(f"format is {data['format']!r}, expected {FORMAT!r}")
    if data['version'] != VERSION or isinstance(data['version'], bool):
        raise CalibrationError(f"version {data['version']!r} is not supported (this build reads version {VERSION})")
    knots = data['knots']
    if not isinstance(knots, dict):
        raise CalibrationError("'knots' must be an object with 'confidence' and 'probability' lists")
    x, y = _number_list(knots, 'confidence'), _number_list(knots, 'probability')
    if len(x) != len(y):
        raise CalibrationError(f'knots.confidence has {len(x)} values but knots.probability {len(y)}')
    if len(x) < 2:
        raise CalibrationError(f'a map needs at least two knots, got {len(x)}')
    for i in range(1, len(x)):
        if not x[i] > x[i - 1]:
            raise CalibrationError(f'knots.confidence is not strictly increasing ({x[i - 1]:g} then {x[i]:g})')
        if y[i] < y[i - 1]:
            raise CalibrationError(f'knots.probability decreases ({y[i - 1]:g} then {y[i]:g} at confidence '
                                   f'{x[i]:g}): the map must be monotone')
    fitted_on = data.get('fitted_on', {})
    if not isinstance(fitted_on, dict):
        raise CalibrationError("'fitted_on' must be an object")
    return ConfidenceCalibration(x, y, _check_estimator(data['estimator']), fitted_on, path)


def load(path) -> ConfidenceCalibration:
    """The calibration in ``path`` (:func:`from_dict`); :class:`CalibrationError` when it is missing, not a regular
    file, larger than :data:`MAX_FILE_BYTES` (judged from its size before anything is read), unreadable, not JSON or
    malformed (the message says what, not where: the caller names the file or the setting)."""
    p = pathlib.Path(path)
    try:
        st = p.stat()
        if not stat.S_ISREG(st.st_mode):
            raise CalibrationError('not a regular file')
        if st.st_size > MAX_FILE_BYTES:
            raise CalibrationError(f'{st.st_size} bytes, larger than the {MAX_FILE_BYTES} bytes a calibration file '
                                   'may have (a map is a few kB); not read')
        with p.open('rb') as f:
            raw = f.read(MAX_FILE_BYTES + 1)        # a file that grew since its stat is still read only this far
        if len(raw) > MAX_FILE_BYTES:
            raise CalibrationError(f'larger than the {MAX_FILE_BYTES} bytes a calibration file may have')
        text = raw.decode('utf-8')
    except FileNotFoundError:
        raise CalibrationError('no such file') from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f'cannot be read ({exc})') from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CalibrationError(f'not JSON ({exc})') from None
    return from_dict(data, str(p))


def save(calibration: ConfidenceCalibration, path) -> pathlib.Path:
    """Write the calibration as JSON (checked with :func:`from_dict` first); returns the path."""
    data = to_jsonable(calibration.to_dict())
    from_dict(data)
    p = pathlib.Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(data, indent=1) + '\n')
    return p
