"""Rectification of distorted images (dpv_sensor/core/rectify.py): a synthetic image distorted with known
coefficients through OpenCV's own model comes back to the pinhole image."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from dpv_sensor.core.rectify import Calibration, Rectifier, RectifierCache, UnsupportedDistortion

W, H = 320, 240
K = np.array([[250.0, 0.0, 161.0], [0.0, 252.0, 118.5], [0.0, 0.0, 1.0]])
PLUMB_BOB = [-0.28, 0.09, 0.001, -0.0015, -0.01]
RATIONAL = [0.4, -0.2, 0.001, -0.0015, 0.02, 0.7, -0.15, 0.05]


def _pinhole_image():
    """A smooth, textured pinhole image (sines, so bilinear resampling loses little)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    img = 127.5 + 60 * np.sin(u / 7.0) * np.cos(v / 9.0) + 50 * np.sin((u + 2 * v) / 13.0)
    return np.clip(img, 0, 255).astype(np.uint8)


def _distort(pinhole, K_pin, D):
    """The image the distorted camera (K, D) sees of the scene whose pinhole image (K_pin) is given:
    every distorted pixel looks up where its ray lands in the pinhole image."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    pts = np.stack([u.ravel(), v.ravel()], -1)[:, None]
    und = cv2.undistortPoints(pts, K, np.asarray(D, np.float64), P=K_pin,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-6))
    mx = und[:, 0, 0].reshape(H, W).astype(np.float32)
    my = und[:, 0, 1].reshape(H, W).astype(np.float32)
    return cv2.remap(pinhole, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


@pytest.mark.parametrize('model,D', [('plumb_bob', PLUMB_BOB), ('rational_polynomial', RATIONAL)])
def test_distorted_image_rectifies_back_to_the_pinhole_image(model, D):
    K_pin = K.copy()
    pinhole = _pinhole_image()
    distorted = _distort(pinhole, K_pin, D)
    assert np.abs(distorted.astype(float) - pinhole).mean() > 10.0      # the distortion is not negligible
    P = np.hstack([K_pin, np.zeros((3, 1))])
    rect = Rectifier(Calibration.from_fields(K, D, model, (W, H), P))
    out = rect.rectify(distorted)
    assert out.shape == pinhole.shape and out.dtype == pinhole.dtype
    # compare where both resamplings stayed inside their images (the distorted view does not see the corners)
    seen = rect.rectify(_distort(np.full_like(pinhole, 255), K_pin, D)) == 255
    assert seen[H // 4:3 * H // 4, W // 4:3 * W // 4].all()
    err = np.abs(out.astype(float) - pinhole)[seen]
    assert err.mean() < 2.0 and np.percentile(err, 99) < 8.0
    # the output camera: P's intrinsics, no distortion
    assert np.allclose(rect.K, K_pin) and not np.any(rect.D)


def test_without_P_alpha_zero_keeps_every_output_pixel_inside_the_source():
    rect = Rectifier(Calibration.from_fields(K, PLUMB_BOB, 'plumb_bob', (W, H)))
    assert rect.K.shape == (3, 3) and rect.K[2, 2] == 1.0
    # barrel distortion: the distorted frame sees more than the pinhole frame of the same K, and the largest
    # all-valid view keeps some of that, so the rectified focal length is smaller
    assert rect.K[0, 0] < K[0, 0]
    white = rect.rectify(np.full((H, W), 255, np.uint8))
    assert (white[1:-1, 1:-1] == 255).all()
    # a P of zeros (an uncalibrated projection) falls back to the same matrix
    rect0 = Rectifier(Calibration.from_fields(K, PLUMB_BOB, 'plumb_bob', (W, H), np.zeros(12)))
    assert np.allclose(rect0.K, rect.K)


def test_cache_builds_once_per_calibration_and_skips_undistorted_cameras():
    cache = RectifierCache()
    assert cache.get(K, [0.0] * 5, 'plumb_bob', (W, H)) is None
    a = cache.get(K, PLUMB_BOB, 'plumb_bob', (W, H))
    b = cache.get(K.copy(), list(PLUMB_BOB), 'plumb_bob', (W, H))
    assert a is b and cache.builds == 1
    c = cache.get(K, RATIONAL, 'rational_polynomial', (W, H))
    assert c is not a and cache.builds == 2
    colour = np.zeros((H, W, 3), np.uint8)
    assert c.rectify(colour).shape == (H, W, 3)
    with pytest.raises(ValueError, match='calibration is for 320x240'):
        c.rectify(np.zeros((H // 2, W // 2, 3), np.uint8))


def test_unsupported_models_are_refused_with_the_reason():
    with pytest.raises(UnsupportedDistortion, match='equidistant'):
        Rectifier(Calibration.from_fields(K, [0.1, 0.01, 0.0, 0.0], 'equidistant', (W, H)))
    with pytest.raises(UnsupportedDistortion, match='7 coefficients'):
        Rectifier(Calibration.from_fields(K, [0.1] * 7, 'plumb_bob', (W, H)))


def test_cache_reads_a_camera_info_by_field_name():
    from types import SimpleNamespace
    P = np.hstack([K * [[0.9], [0.9], [1.0]], np.zeros((3, 1))])
    msg = SimpleNamespace(k=K.ravel().tolist(), d=RATIONAL, distortion_model='rational_polynomial', width=W,
                          height=H, p=P.ravel().tolist())
    rect = RectifierCache().for_camera_info(msg)
    assert np.allclose(rect.K, P[:, :3])
