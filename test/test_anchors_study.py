"""The anchors study's scoring (studies.anchors.score_windows) on keyframes worked out by hand."""
import numpy as np
import pytest

from dpv_sensor.core.anchors import AnchorConfig
from dpv_sensor.studies.anchors import score_windows

K = np.array([[100.0, 0.0, 16.0], [0.0, 100.0, 12.0], [0.0, 0.0, 1.0]])


def _row(scale, vetoed=False):
    gt = np.full((24, 32), 2.0, np.float32)
    return {'stamp': 0.0, 'depth': gt * scale, 'conf': np.full_like(gt, 0.9), 'K': K, 'gt': gt,
            'window': None, 'direction_ratio': (1.2, 1.05) if vetoed else None, 'depth_range': (0.3, 8.0)}


def test_keyframes_without_a_window_score_the_same_in_every_mode():
    s = score_windows([_row(1.1), _row(0.8, vetoed=True)], AnchorConfig())
    assert s['keyframes'] == 2 and s['anchors_per_keyframe'] == 0.0 and s['anchor_accuracy_median'] is None
    for mode in ('off', 'scale', 'dense'):
        f = s['modes'][mode]
        assert f['abs_rel'] == pytest.approx((0.1 + 0.2) / 2)            # |1.1 - 1| and |0.8 - 1|, per frame
        assert f['image_scale']['q25'] == pytest.approx(0.8 + 0.25 * 0.3)
        assert f['image_scale']['scaled_abs_rel'] == pytest.approx(0.0, abs=1e-6)
        assert f['delta1'] == pytest.approx(1.0)                           # both within x1.25


def test_no_veto_triangulates_the_keyframes_the_veto_leaves_without_anchors():
    """Two views 0.3 m apart along x of a wall 2 m away, matched as SIFT's pairs: vetoed, the keyframe has no
    anchors; with veto=False its anchors sit at the wall's depth."""
    from dpv_sensor.stream.window_refiner_config import PairMatches
    u, v = np.meshgrid(np.arange(4.0, 29.0, 3.0), np.arange(3.0, 22.0, 3.0))
    p_ref = np.c_[u.ravel(), v.ravel()]
    p_src = p_ref - np.array([100.0 * 0.3 / 2.0, 0.0])               # x_src = x_ref - t: f t / z pixels
    T_src = np.eye(4)
    T_src[0, 3] = 0.3
    window = ([PairMatches(0.0, 1.0, p_ref, p_src, K)], {0.0: np.eye(4), 1.0: T_src}, {})
    row = dict(_row(1.0, vetoed=True), window=window)
    vetoed = score_windows([row], AnchorConfig())
    assert vetoed['anchors_per_keyframe'] == 0.0 and vetoed['anchor_accuracy_median'] is None
    kept = score_windows([row], AnchorConfig(), veto=False)
    assert kept['anchors_per_keyframe'] == len(p_ref)
    assert kept['anchor_accuracy_median'] == pytest.approx(1.0, abs=1e-6)
