"""Rectification of distorted camera images (numpy + OpenCV, no ROS).

The estimator models a pinhole camera. A camera_info with lens distortion (``plumb_bob``: k1, k2, p1, p2,
k3; ``rational_polynomial``: k1, k2, p1, p2, k3, k4, k5, k6) describes images whose straight lines bend;
used as they are, the plane sweep warps with the wrong rays and the depth is wrong towards the borders.
A :class:`Rectifier` computes the undistortion map once per calibration (``cv2.initUndistortRectifyMap``)
and remaps every image with it (``cv2.remap``, bilinear), so the per-image cost is one remap.

Intrinsics of the rectified image (``K``; its distortion is zero):

- the calibration's projection matrix ``P`` (its left 3x3) when it is given and valid: by the ROS
  CameraInfo convention ``P`` holds the intrinsics of the rectified image, so the published camera_info
  then agrees with what ``image_proc`` would publish for the same camera;
- otherwise ``cv2.getOptimalNewCameraMatrix`` with ``alpha = 0``: the largest view in which every pixel
  comes from inside the source image. Black, unseen borders (``alpha = 1``) would give the plane sweep
  pixels with no texture and fake edges along the border of the valid region.

The rectification rotation ``R`` of the calibration is not applied (it aligns stereo pairs; for one
camera it is the identity, and a rotated image would no longer match the camera pose from odometry).

:class:`RectifierCache` keeps the rectifier of the current calibration and builds a new one only when
the calibration changes, which is what a node receiving camera_info with every image needs.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import cv2
import numpy as np

__all__ = ['DISTORTION_MODELS', 'Calibration', 'Rectifier', 'RectifierCache', 'UnsupportedDistortion']

DISTORTION_MODELS = ('plumb_bob', 'rational_polynomial')
# coefficient counts cv2 accepts (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]])
_CV_COUNTS = (4, 5, 8, 12, 14)


class UnsupportedDistortion(ValueError):
    """The calibration's distortion model or coefficients cannot be rectified here."""


def _tuple(a, n: Optional[int] = None) -> Tuple[float, ...]:
    v = tuple(float(x) for x in np.asarray(a, dtype=np.float64).reshape(-1))
    if n is not None and len(v) != n:
        raise UnsupportedDistortion(f'expected {n} numbers, got {len(v)}')
    return v


@dataclass(frozen=True)
class Calibration:
    """One camera calibration, hashable (the cache key): image size, K (row-major 9), distortion model and
    coefficients, and P (row-major 12, or empty)."""
    width: int
    height: int
    K: Tuple[float, ...]
    model: str
    D: Tuple[float, ...]
    P: Tuple[float, ...] = ()

    @classmethod
    def from_fields(cls, K_33, D, model: str, size: Tuple[int, int], P_34=None) -> 'Calibration':
        """From plain values (``size`` = (width, height); ``P_34`` optional)."""
        P = () if P_34 is None else _tuple(P_34)
        if P and len(P) != 12:
            raise UnsupportedDistortion(f'P has {len(P)} entries, expected 12')
        return cls(int(size[0]), int(size[1]), _tuple(K_33, 9), str(model or ''), _tuple(D), P)

    @property
    def distorted(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return any(abs(x) > 1e-12 for x in self.D)


class Rectifier:
    """Undistortion of the images of one calibration (see the module docstring).

    Attributes: ``calibration``; ``K`` (3x3 float64, intrinsics of the rectified image, whose distortion
    is zero); ``size`` (width, height, the same as the input). :meth:`rectify` maps one image.
    Raises :class:`UnsupportedDistortion` for another distortion model or an unusable coefficient count.
    """

    def __init__(self, calibration: Calibration):
        c = calibration
        if c.model not in DISTORTION_MODELS:
            raise UnsupportedDistortion(f'distortion model {c.model!r} is not supported (only '
                                        f'{", ".join(DISTORTION_MODELS)}); rectify the images before the node, '
                                        'e.g. with image_proc')
        D = np.array(c.D, dtype=np.float64)
        if D.size not in _CV_COUNTS:
            if D.size < 14 and not np.any(D[4:]) and D.size >= 4:
                D = D[:5] if D.size >= 5 else D[:4]      # trailing zeros only: drop them
            else:
                raise UnsupportedDistortion(f'{c.model} with {D.size} coefficients (OpenCV takes 4, 5, 8, 12 '
                                            'or 14)')
        if c.width <= 0 or c.height <= 0:
            raise UnsupportedDistortion(f'image size {c.width}x{c.height} in the calibration')
        self.calibration = c
        self.size = (c.width, c.height)
        K_in = np.array(c.K, dtype=np.float64).reshape(3, 3)
        self.K = self._new_K(K_in, D, c)
        self._map1, self._map2 = cv2.initUndistortRectifyMap(K_in, D, None, self.K, self.size, cv2.CV_16SC2)

    @staticmethod
    def _new_K(K_in: np.ndarray, D: np.ndarray, c: Calibration) -> np.ndarray:
        if len(c.P) == 12:
            P = np.array(c.P, dtype=np.float64).reshape(3, 4)
            K = P[:, :3].copy()
            if np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and K[2, 2] != 0:
                return K / K[2, 2]
        K, _roi = cv2.getOptimalNewCameraMatrix(K_in, D, (c.width, c.height), 0.0, (c.width, c.height))
        return np.asarray(K, dtype=np.float64)

    @property
    def D(self) -> np.ndarray:
        """Distortion of the rectified image: five zeros (plumb_bob)."""
        return np.zeros(5)

    def rectify(self, image: np.ndarray) -> np.ndarray:
        """The rectified image (same size, dtype and channels), bilinear; pixels from outside the source
        (none with alpha 0 up to rounding) are black. Raises ValueError when the image size differs from the
        calibration's."""
        h, w = image.shape[:2]
        if (w, h) != self.size:
            raise ValueError(f'image is {w}x{h} but the calibration is for {self.size[0]}x{self.size[1]}')
        return cv2.remap(image, self._map1, self._map2, interpolation=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)


class RectifierCache:
    """The rectifier of the latest calibration, rebuilt only when the calibration changes.

    :meth:`get` returns None for a calibration without distortion (nothing to do), the cached
    :class:`Rectifier` when the calibration is unchanged, else a new one; it raises
    :class:`UnsupportedDistortion` for what cannot be rectified. ``builds`` counts the maps computed.
    """

    def __init__(self):
        self._key: Optional[Calibration] = None
        self._rectifier: Optional[Rectifier] = None
        self.builds = 0

    def get(self, K_33, D: Sequence[float], model: str, size: Tuple[int, int], P_34=None) -> Optional[Rectifier]:
        cal = Calibration.from_fields(K_33, D, model, size, P_34)
        if not cal.distorted:
            return None
        if cal != self._key:
            self._rectifier = Rectifier(cal)
            self._key = cal
            self.builds += 1
        return self._rectifier

    def for_camera_info(self, msg) -> Optional[Rectifier]:
        """:meth:`get` for a sensor_msgs/CameraInfo (read by field name: k, d, distortion_model, width,
        height, p; nothing ROS is imported here)."""
        return self.get(msg.k, list(msg.d), msg.distortion_model, (int(msg.width), int(msg.height)),
                        msg.p if len(msg.p) == 12 else None)
