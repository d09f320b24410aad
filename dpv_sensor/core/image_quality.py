"""Degenerate camera frames: all black, all white / saturated, flat (no contrast) or random noise.

Such a frame carries no depth information: a plane sweep over it matches nothing (flat, black, white) or
everything equally badly (noise), yet a network still returns a peaked DPV for it. :func:`assess` says
whether a frame is usable and, if not, why, in one short reason string (for a log line and a diagnostics
counter). numpy and OpenCV, no ROS, no torch; a 640x480 frame costs a few milliseconds.

The tests, in this order (thresholds are module constants, chosen so that no frame of the real and rendered
sequences we evaluate on is flagged, while the synthetic degenerate frames are, with a wide margin: the
neighbour ratio below is at most 0.13 on the frames of the shared real and rendered sequences (every third
frame checked), up to 0.83 on a finely textured 80x60 test plane seen from afar (its texture aliases), and
1.00 +- 0.02 on noise):

- ``black``: at least ``DARK_FRACTION`` of the pixels have every channel <= ``DARK_LEVEL``;
- ``saturated``: at least ``SATURATED_FRACTION`` of the pixels have a channel >= ``SATURATED_LEVEL``
  (an all-white frame is saturated);
- ``flat``: the grey-level standard deviation is below ``FLAT_STD`` (a uniformly coloured frame, a lens
  cap in daylight, a frozen exposure);
- ``noise``: neighbouring pixels are as different as two random pixels: the mean squared difference of
  horizontal and vertical neighbours over twice the grey-level variance (1 for independent noise, small for
  any image of a scene, whose neighbours are correlated) is above ``NOISE_RATIO``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Optional

import cv2
import numpy as np

__all__ = ['ImageQuality', 'assess', 'DARK_LEVEL', 'DARK_FRACTION', 'SATURATED_LEVEL', 'SATURATED_FRACTION',
           'FLAT_STD', 'NOISE_RATIO']

DARK_LEVEL = 10
DARK_FRACTION = 0.97
SATURATED_LEVEL = 250
SATURATED_FRACTION = 0.9
FLAT_STD = 2.0
NOISE_RATIO = 0.92


@dataclass(frozen=True)
class ImageQuality:
    """``ok`` is False for a degenerate frame; ``reason`` names the test that failed and its figure
    (None when ok); ``stats`` holds every figure measured (dark/saturated fractions, grey std, neighbour
    ratio)."""
    ok: bool
    reason: Optional[str] = None
    stats: Dict[str, float] = field(default_factory=dict)


def assess(image_hw3: np.ndarray) -> ImageQuality:
    """Whether an RGB (or BGR: the tests are symmetric in the channels) uint8 HxWx3 frame is usable."""
    img = np.asarray(image_hw3)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f'image must be uint8 HxWx3, got {img.dtype} {img.shape}')
    img = np.ascontiguousarray(img)
    n = img.shape[0] * img.shape[1]
    c0, c1, c2 = cv2.split(img)
    lo = cv2.min(cv2.min(c0, c1), c2)
    hi = cv2.max(cv2.max(c0, c1), c2)
    dark = float(np.count_nonzero(hi <= DARK_LEVEL)) / n
    saturated = float(np.count_nonzero(hi >= SATURATED_LEVEL)) / n
    grey = cv2.transform(img, np.full((1, 3), 1.0 / 3.0, np.float32))     # the channel mean, float32
    mean, sd = cv2.meanStdDev(grey)
    std = float(sd[0, 0])
    var = std * std
    if var > 0.0 and min(grey.shape[:2]) >= 2:
        dx = cv2.norm(grey[:, 1:], grey[:, :-1], cv2.NORM_L2SQR) / (grey.shape[0] * (grey.shape[1] - 1))
        dy = cv2.norm(grey[1:, :], grey[:-1, :], cv2.NORM_L2SQR) / ((grey.shape[0] - 1) * grey.shape[1])
        ratio = float((dx + dy) / 2.0 / (2.0 * var))
    else:
        ratio = 0.0
    stats = {'dark_fraction': dark, 'saturated_fraction': saturated, 'grey_std': std, 'neighbour_ratio': ratio,
             'min_level': float(lo.min())}
    if dark >= DARK_FRACTION:
        return ImageQuality(False, f'black: {dark:.0%} of the pixels at or below level {DARK_LEVEL}', stats)
    if saturated >= SATURATED_FRACTION:
        return ImageQuality(False, f'saturated: {saturated:.0%} of the pixels at or above level {SATURATED_LEVEL}',
                            stats)
    if std < FLAT_STD:
        return ImageQuality(False, f'flat: grey-level std {std:.2f} < {FLAT_STD:g}', stats)
    if ratio > NOISE_RATIO:
        return ImageQuality(False, f'noise: neighbouring pixels as different as random ones (ratio {ratio:.2f} > '
                            f'{NOISE_RATIO:g})', stats)
    return ImageQuality(True, None, stats)
