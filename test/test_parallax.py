"""Parallax measure (hand-computed disparities), the source choice by it, the filter's per-pixel update
weight, and what the estimator does without parallax and with degenerate frames."""
import math
import sys
import pathlib

import numpy as np
import pytest
import torch

from dpv_sensor.core import dpv as dpv_ops
from dpv_sensor.stream.estimator import Estimator
from dpv_sensor.core.filter import DPVFilter
from dpv_sensor.core.parallax import disparity_span, parallax_support, pose_parallax_score, select_sources

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from test_estimator import frame_at, pose, small_config, sideways  # noqa: E402

# f = 100 px, principal point (50, 40), a 100 x 80 image
K = torch.tensor([[[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]]])


def T_src_ref(tx=0.0, tz=0.0, yaw_deg=0.0):
    T = torch.eye(4)
    a = math.radians(yaw_deg)
    T[:3, :3] = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    T[0, 3], T[2, 3] = tx, tz
    return T


def test_span_of_a_sideways_baseline_is_the_hand_computed_disparity():
    # the centre pixel's point at depth z projects to u = 50 + 100 * 0.1 / z in a source 0.1 m to the left:
    # between z = 2 / 1.25 = 1.6 and z = 2 * 1.25 = 2.5 it moves 100 * 0.1 * (1 / 1.6 - 1 / 2.5) = 2.25 px
    d = torch.full((1, 80, 100), 2.0)
    span = disparity_span(d, K, T_src_ref(tx=0.1)[None, None], 1.25)
    assert span[0, 40, 50].item() == pytest.approx(2.25, abs=1e-4)
    # the disparity of a sideways baseline does not depend on the pixel, and halves at twice the depth
    assert torch.allclose(span, torch.full_like(span, 2.25), atol=1e-3)
    span4 = disparity_span(torch.full((1, 80, 100), 4.0), K, T_src_ref(tx=0.1)[None, None], 1.25)
    assert span4[0, 40, 50].item() == pytest.approx(1.125, abs=1e-4)


def test_pure_rotation_has_no_parallax_and_the_best_source_counts():
    d = torch.full((1, 80, 100), 2.0)
    rot = disparity_span(d, K, T_src_ref(yaw_deg=10.0)[None, None], 1.25)
    assert rot.abs().max().item() < 1e-3
    both = disparity_span(d, K, torch.stack([T_src_ref(yaw_deg=10.0), T_src_ref(tx=0.2)])[None], 1.25)
    assert both[0, 40, 50].item() == pytest.approx(4.5, abs=1e-3)
    # forward motion: no parallax at the centre (focus of expansion), some off-centre:
    # the source is 0.1 m further forward (z_src = z - 0.1):
    # u_src - 50 = 100 * x / (z - 0.1) with x = (u - 50) z / 100 at the reference; at u = 90: x = 0.4 z
    fwd = disparity_span(d, K, T_src_ref(tz=-0.1)[None, None], 1.25)
    assert fwd[0, 40, 50].item() == pytest.approx(0.0, abs=1e-4)
    expect = 100 * 0.4 * (1.6 / 1.5 - 2.5 / 2.4)     # = 1.0 px
    assert fwd[0, 40, 90].item() == pytest.approx(abs(expect), rel=1e-3)


def test_a_source_that_does_not_see_the_point_gives_no_parallax():
    d = torch.full((1, 80, 100), 2.0)
    far_left = T_src_ref(tx=3.0)[None, None]          # the point lands 150 px right of the source's centre
    assert disparity_span(d, K, far_left, 1.25)[0, 40, 50].item() > 10
    assert disparity_span(d, K, far_left, 1.25, src_hw=(80, 100))[0, 40, 50].item() == 0.0
    nan = d.clone()
    nan[0, 0, 0] = float('nan')
    assert disparity_span(nan, K, T_src_ref(tx=0.1)[None, None], 1.25)[0, 0, 0].item() == 0.0


def test_support_is_linear_up_to_full_and_off_at_zero():
    s = torch.tensor([0.0, 0.5, 1.0, 3.0])
    assert parallax_support(s, 1.0).tolist() == [0.0, 0.5, 1.0, 1.0]
    assert parallax_support(s, 0.0).tolist() == [1.0] * 4


def test_pose_score_and_source_selection():
    K33 = K[0].numpy().astype(np.float64)
    ref = np.eye(4)
    side = np.eye(4)
    side[0, 3] = 0.1
    turned = np.eye(4)
    turned[:3, :3] = T_src_ref(yaw_deg=10.0)[:3, :3].numpy()
    # the sideways source moves every pixel by 2.25 px (at 2 m) and sees most of the image
    assert pose_parallax_score(ref, side, K33, (80, 100), 2.0) == pytest.approx(2.25, rel=0.02)
    assert pose_parallax_score(ref, turned, K33, (80, 100), 2.0) < 1e-3
    far = np.eye(4)
    far[0, 3] = 3.0                                     # long baseline, but it sees nothing of the reference
    assert pose_parallax_score(ref, far, K33, (80, 100), 2.0) == 0.0
    # pool of 7 keyframes, reference 6: the four closest in time that reach 1 px, else the best of the rest
    scores = [3.0, 0.1, 2.0, 0.2, 1.5, 0.3, 0.0]
    assert select_sources(6, range(7), scores, 4, 1.0) == [0, 2, 4, 5]
    assert select_sources(6, range(7), scores, 2, 1.0) == [2, 4]
    assert select_sources(2, range(3), [1, 1, 1], 4, 1.0) == [0, 1]


def test_filter_update_weight_keeps_or_replaces_the_belief():
    D, H, W = 8, 4, 5
    depths = dpv_ops.depth_planes(0.5, 4.0, D)
    Kv = torch.tensor([[[4.0, 0, 2.0], [0, 4.0, 1.5], [0, 0, 1]]])
    eye = torch.eye(4)[None]
    first = dpv_ops.one_hot_log(torch.full((1, H, W), 2), D)
    second = dpv_ops.one_hot_log(torch.full((1, H, W), 6), D)
    f = DPVFilter(mode='bayes', max_time_gap=math.inf)
    # after a reset a zero-weight measurement leaves the uniform belief
    out = f.step(first, Kv, eye, 0.0, depths, update_weight_bhw=torch.zeros(1, H, W))
    assert torch.allclose(out.logp_bdhw.exp(), torch.full((1, D, H, W), 1.0 / D), atol=1e-6)
    f.reset()
    f.step(first, Kv, eye, 0.0, depths)
    w = torch.zeros(1, H, W)
    w[0, :, 3:] = 1.0                                    # the right columns have parallax, the rest none
    out = f.step(second, Kv, eye, 0.1, depths, update_weight_bhw=w)
    # weight 0: exactly the prediction (the camera did not move: the first belief)
    assert torch.allclose(out.logp_bdhw[..., :3], out.predicted_logp_bdhw[..., :3], atol=1e-5)
    assert (out.logp_bdhw[..., :3].argmax(1) == 2).all()
    # weight 1: the plain update (bayes: the product of two disjoint one-hots is flat between the floors)
    plain = DPVFilter(mode='bayes', max_time_gap=math.inf)
    plain.step(first, Kv, eye, 0.0, depths)
    ref = plain.step(second, Kv, eye, 0.1, depths).logp_bdhw
    assert torch.allclose(out.logp_bdhw[..., 3:], ref[..., 3:], atol=1e-5)


def turning(n, deg=2.0, **kw):
    return [frame_at(i, pose(yaw_deg=deg * i), **kw) for i in range(n)]


def test_turning_in_place_publishes_no_confident_depth_while_a_baseline_does():
    cfg = small_config(parallax_full_px=2.0)
    est = Estimator(cfg)
    outs = [o for o in (est.push(f) for f in turning(6)) if o is not None]
    assert outs
    conf = np.concatenate([o.confidence_hw.ravel() for o in outs])
    assert np.mean(conf <= 0.05) >= 0.99
    assert est.status.parallax['median_span_px'] < 0.05
    # a sideways baseline of 10 cm per keyframe, plane at 2 m: the oldest source moves the pixels by
    # 57.6 px * 0.4 m * (1.25 / 2 m - 1 / 2.5 m) = 5.2 px > 2 px: confidence as without the rule
    est_on = Estimator(cfg)
    a = [o for o in (est_on.push(f) for f in sideways(5, step=0.1)) if o is not None][-1]
    assert est_on.status.parallax['median_span_px'] == pytest.approx(5.2, rel=0.1)
    est_off = Estimator(small_config(parallax_full_px=0.0))
    b = [o for o in (est_off.push(f) for f in sideways(5, step=0.1)) if o is not None][-1]
    ok = np.isfinite(a.depth_hw) & np.isfinite(b.depth_hw)
    assert np.median(a.confidence_hw[ok]) == pytest.approx(np.median(b.confidence_hw[ok]), rel=0.05)


def test_a_rotation_after_a_baseline_keeps_the_belief_confident():
    """The belief built with parallax is carried through a turn in place (the prediction warps it exactly)."""
    cfg = small_config(parallax_full_px=2.0)
    est = Estimator(cfg)
    frames = sideways(5) + [frame_at(5 + i, pose(x=0.03 * 4, yaw_deg=1.0 * (i + 1))) for i in range(3)]
    outs = [est.push(f) for f in frames]
    last = outs[-1]
    before = outs[4]
    ok = np.isfinite(last.depth_hw)
    assert ok.mean() > 0.5
    assert np.median(last.confidence_hw[ok]) > 0.5 * np.median(before.confidence_hw[np.isfinite(before.depth_hw)])


def degenerate_images(h=60, w=80):
    rng = np.random.default_rng(0)
    return {'black': np.zeros((h, w, 3), np.uint8), 'white': np.full((h, w, 3), 255, np.uint8),
            'saturated': np.full((h, w, 3), (255, 252, 251), np.uint8),
            'noise': rng.integers(0, 256, (h, w, 3)).astype(np.uint8)}


@pytest.mark.parametrize('mode', ['causal', 'centered'])
def test_degenerate_frames_leave_the_belief_unchanged_and_publish_nothing(mode):
    est = Estimator(small_config(window_mode=mode))
    frames = sideways(6)
    for f in frames[:5]:
        est.push(f)
    belief = est.filter.logp_bdhw.clone()
    window = [kf.index for kf in est.window]
    last_frame = est._last_frame
    for k, (name, img) in enumerate(degenerate_images().items()):
        f = frames[5]
        bad = type(f)(stamp=f.stamp + 0.001 * (k + 1), image=img, K_33=f.K_33, T_world_cam_44=f.T_world_cam_44,
                      frame_id='cam')
        assert est.push(bad) is None, name
        assert est.status.last_degenerate_reason.startswith(name if name != 'white' else 'saturated')
    assert torch.equal(est.filter.logp_bdhw, belief)
    assert [kf.index for kf in est.window] == window and est._last_frame is last_frame
    st = est.status
    assert st.frames_degenerate == 4 and 'degenerate image' in st.last_drop_reason
    # the stream goes on as if they had not come
    assert est.push(frames[5]) is not None


def test_degenerate_frames_on_a_fresh_estimator_publish_nothing():
    est = Estimator(small_config())
    for i, img in enumerate(degenerate_images().values()):
        f = frame_at(i, pose(x=0.03 * i))
        assert est.push(type(f)(stamp=f.stamp, image=img, K_33=f.K_33, T_world_cam_44=f.T_world_cam_44)) is None
    assert est.filter.logp_bdhw is None and len(est.window) == 0
    # off: they are processed like any frame
    est = Estimator(small_config(reject_degenerate_frames=False))
    outs = [est.push(type(f)(stamp=f.stamp, image=np.zeros((60, 80, 3), np.uint8), K_33=f.K_33,
                             T_world_cam_44=f.T_world_cam_44)) for f in sideways(3)]
    assert outs[-1] is not None


def test_degenerate_frames_at_the_defaults_leave_the_network_belief_unchanged():
    """Default configuration (packaged network, K-Net filter): a degenerate frame is no keyframe and no output."""
    from dpv_sensor.stream.estimator import EstimatorConfig
    est = Estimator(EstimatorConfig(processing_width=64, processing_height=48))
    frames = [frame_at(i, pose(x=0.06 * i)) for i in range(4)]
    for f in frames[:3]:
        est.push(f)
    assert est.status.measurement == 'network'
    belief = est.filter.logp_bdhw.clone()
    for k, img in enumerate(degenerate_images().values()):
        f = frames[3]
        assert est.push(type(f)(stamp=f.stamp + 0.001 * k, image=img, K_33=f.K_33,
                                T_world_cam_44=f.T_world_cam_44)) is None
    assert torch.equal(est.filter.logp_bdhw, belief)
    assert est.status.frames_degenerate == 4


def _kf(i, x=0.0, yaw=0.0):
    from dpv_sensor.stream.keyframes import Keyframe
    return Keyframe(index=i, frame_index=i, stamp=float(i), T_world_cam_44=pose(x=x, yaw_deg=yaw), image_b3hw=None,
                    K_b33=None, input_size=(80, 60), input_K_33=np.eye(3))


def test_window_pool_chooses_sources_by_score_and_keeps_the_reference():
    from dpv_sensor.stream.keyframes import KeyframeWindow
    # keyframe i sits at x = xs[i]; the score is the baseline to the reference in cm
    xs = [0.0, 0.10, 0.11, 0.12, 0.13, 0.135, 0.14, 0.145]
    score = lambda ref, kf: 100 * abs(ref.T_world_cam_44[0, 3] - kf.T_world_cam_44[0, 3])  # noqa: E731
    plain, pooled = KeyframeWindow(5), KeyframeWindow(5, pool=8)
    for i, x in enumerate(xs):
        plain.append(_kf(i, x))
        pooled.append(_kf(i, x))
    # causal: the latest four without a pool; with it, those at >= 2 cm, closest in time, then the best rest
    ref, src = plain.select('causal', score, 2.0)
    assert ref.index == 7 and [k.index for k in src] == [3, 4, 5, 6]
    ref, src = pooled.select('causal', score, 2.0)
    assert ref.index == 7 and [k.index for k in src] == [0, 1, 2, 3]
    ref, src = pooled.select('causal')                     # no score: the latest ones
    assert [k.index for k in src] == [3, 4, 5, 6]
    # centered: same reference (two keyframes of latency), sources from both sides of the pool
    # scores to the reference 5: 13.5, 3.5, 2.5, 1.5, 0.5 | 0.5, 1.0 cm; at >= 0.9, by time distance: 3, 7, 2, 1
    ref, src = pooled.select('centered', score, 0.9)
    assert ref.index == 5 and [k.index for k in src] == [1, 2, 3, 7]
    ref, src = pooled.select('centered')
    assert ref.index == 5 and [k.index for k in src] == [3, 4, 6, 7]


def test_estimator_with_a_pool_still_outputs_in_both_modes():
    for mode in ('causal', 'centered'):
        est = Estimator(small_config(window_mode=mode, source_pool=8))
        outs = [o for o in (est.push(f) for f in sideways(10, step=0.02)) if o is not None]
        assert len(outs) == (9 if mode == 'causal' else 8)
        assert np.isfinite(outs[-1].depth_hw).mean() > 0.5


def test_rotation_noise_is_a_fraction_of_the_rotational_image_motion():
    from dpv_sensor.core.parallax import rotation_noise_px
    T = torch.stack([T_src_ref(yaw_deg=10.0), T_src_ref(tx=0.1)])[None]
    noise = rotation_noise_px(T, 100.0, 0.02)
    # 2 % of 100 px * 10 deg (0.1745 rad) = 0.349 px; a pure translation adds nothing
    assert noise[0, 0].item() == pytest.approx(0.02 * 100 * math.radians(10.0), rel=1e-4)
    assert noise[0, 1].item() == pytest.approx(0.0, abs=1e-3)
    spans = disparity_span(torch.full((1, 80, 100), 2.0), K, T, per_source=True)
    assert spans.shape == (2, 1, 80, 100) and spans[1, 0, 40, 50].item() == pytest.approx(2.25, abs=1e-3)
