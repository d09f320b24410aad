"""Tests of dpv_sensor.core.filter.DPVFilter: update modes, fusion on analytic scenes, reset rules."""
import math
import os
import sys

import pytest
import torch

sys.path.insert(0, os.path.dirname(__file__))
from synthetic_planes import DT, Rect, intrinsics, render_scene, rot_y, se3  # noqa: E402

from dpv_sensor.core import dpv  # noqa: E402
from dpv_sensor.core.filter import MOTION_REFERENCE_S, DPVFilter, FilterStep, jump_limit  # noqa: E402

W, H, D = 40, 30, 32
D_MIN, D_MAX = 0.5, 6.0
PLANES = dpv.depth_planes(D_MIN, D_MAX, D, dtype=DT)
K = intrinsics(W, H, 36.0)
WALL = Rect(z=4.0, seed=1)
BOX = Rect(z=1.8, x0=-0.35, x1=0.35, y0=-0.3, y1=0.3, seed=2)


def noisy_dpv(gt_bhw, gen, sigma=1.5, cap=4.0, noise=0.6, outliers=0.2):
    """Soft, noisy measurement DPV around the GT plane index.

    Energy above the peak: 0.5*((k - f)/sigma)^2 capped at ``cap`` (a measurement never rules a
    plane out completely), plus N(0, noise) per voxel; a fraction ``outliers`` of the pixels peaks
    at a random plane instead. Pixels without GT are uniform.
    """
    B, h, w = gt_bhw.shape
    f = dpv.depth_to_index(gt_bhw, D_MIN, D_MAX, D)
    rnd = torch.rand(B, h, w, generator=gen, dtype=DT) * (D - 1)
    out = torch.rand(B, h, w, generator=gen, dtype=DT) < outliers
    f = torch.where(out, rnd, f)
    k = torch.arange(D, dtype=DT).reshape(1, D, 1, 1)
    E = (0.5 * ((k - f[:, None]) / sigma) ** 2).clamp(max=cap)
    E = E + noise * torch.randn(B, D, h, w, generator=gen, dtype=DT)
    E = torch.where((gt_bhw > 0)[:, None], E, torch.zeros_like(E))
    return dpv.normalize_log(-E)


def abs_rel(logp, gt, mask=None):
    valid = gt > 0 if mask is None else (gt > 0) & mask
    pred = dpv.expected_depth(logp, PLANES)
    return ((pred - gt).abs() / gt)[valid].mean().item()


def camera(i, step=0.03):
    """Camera i of a sideways sweep (``step`` m per frame, slight yaw and drop), world z forward."""
    return se3(rot_y(math.radians(10 * step * i)), (step * i - 0.1, 0.66 * step * i, 0.0))


def run_sequence(modes, n, scene_at, seed=0, damping=0.8, step=0.03):
    """Feed the same noisy measurements to one filter per mode; return abs_rel per mode per frame."""
    filters = {m: DPVFilter(mode=m, damping=damping) for m in modes}
    errs = {m: [] for m in modes}
    gen = torch.Generator().manual_seed(seed)
    masks = []
    for i in range(n):
        T = camera(i, step)
        img, gt = render_scene(scene_at(i), K, T, H, W)
        meas = noisy_dpv(gt, gen)
        masks.append(gt)
        for m, f in filters.items():
            out = f.step(meas, K, T, 0.1 * i, PLANES)
            errs[m].append((out.logp_bdhw, gt))
    return errs


def test_bayes_and_global_improve_monotonically_and_beat_none():
    n = 6
    errs = run_sequence(('none', 'bayes', 'global'), n, lambda i: [WALL, BOX])
    curves = {m: [abs_rel(lp, gt) for lp, gt in v] for m, v in errs.items()}
    print({m: [round(x, 4) for x in c] for m, c in curves.items()})
    for m in ('bayes', 'global'):
        c = curves[m]
        assert all(c[i + 1] < c[i] for i in range(n - 1)), (m, c)
        assert c[-1] < 0.6 * curves['none'][-1], (m, c, curves['none'])
    # frame 0 is the measurement alone in every mode
    assert curves['bayes'][0] == pytest.approx(curves['none'][0])
    # without filtering, the error does not go down
    assert min(curves['none'][1:]) > 0.8 * curves['none'][0]


def test_global_damping_recovers_faster_after_disocclusion():
    """A box in front of the wall for 10 frames, then removed: the wall behind it is disoccluded.

    Bayes has accumulated a confident belief in the box depth there and needs many frames to
    unlearn it; global damping (lambda = 0.8) forgets geometrically and recovers faster. The camera
    creeps (5 mm per frame) so the box region keeps its history before the change.
    """
    t0, n, step = 10, 18, 0.005
    errs = run_sequence(('bayes', 'global'), n, lambda i: [WALL, BOX] if i < t0 else [WALL], seed=1, step=step)
    # the disoccluded region: where the box was seen at frame t0 - 1, re-rendered in each later frame
    curves = {}
    for m, v in errs.items():
        c = []
        for i in range(t0, n):
            _, gt_box = render_scene([WALL, BOX], K, camera(i, step), H, W)
            lp, gt = v[i]
            region = gt_box < gt - 0.5
            c.append(abs_rel(lp, gt, region))
        curves[m] = c
    print({m: [round(x, 3) for x in c] for m, c in curves.items()})

    def recovery(c, thr=0.15):
        return next((i for i, x in enumerate(c) if x < thr), len(c))

    assert recovery(curves['global']) < recovery(curves['bayes']), curves
    assert sum(curves['global']) < 0.7 * sum(curves['bayes']), curves
    # before the change, bayes is at least as good as global (it integrates more)
    pre = {m: abs_rel(*v[t0 - 1]) for m, v in errs.items()}
    assert pre['bayes'] <= pre['global'] * 1.05, pre


# ------------------------------------------------------------------ update equations by hand

def _two_steps(mode, meas1, meas2, **kw):
    f = DPVFilter(mode=mode, **kw)
    T = se3()
    f.step(meas1, K, T, 0.0, PLANES)
    return f.step(meas2, K, T, 0.1, PLANES)


def test_update_equations():
    gen = torch.Generator().manual_seed(3)
    m1 = dpv.normalize_log(torch.randn(1, D, 3, 4, generator=gen, dtype=DT))
    m2 = dpv.normalize_log(torch.randn(1, D, 3, 4, generator=gen, dtype=DT))
    Kt = intrinsics(4, 3, 3.0)

    def two(mode, **kw):
        f = DPVFilter(mode=mode, **kw)
        first = f.step(m1, Kt, se3(), 0.0, PLANES)
        assert first.reset_reason == 'first frame' and first.predicted_logp_bdhw is None
        assert torch.allclose(first.logp_bdhw, m1)
        return f.step(m2, Kt, se3(), 0.1, PLANES)

    out = two('none')
    assert out.reset_reason is None and torch.allclose(out.logp_bdhw, m2)
    out = two('bayes')
    assert torch.allclose(out.predicted_logp_bdhw, m1)            # static camera: prediction = belief
    assert torch.allclose(out.logp_bdhw, dpv.normalize_log(m1 + m2))           # eq. 6: p ~ p_pred * p_meas
    out = two('global', damping=0.5)
    assert torch.allclose(out.logp_bdhw, dpv.normalize_log(0.5 * m1 + m2))     # eq. 8
    seen = {}

    def g(residual, image):
        seen['image'] = image
        return 0.25 * residual

    img = torch.rand(1, 3, 3, 4, dtype=DT)
    f = DPVFilter(mode='knet', knet=g)
    f.step(m1, Kt, se3(), 0.0, PLANES, image_b3hw=img)
    out = f.step(m2, Kt, se3(), 0.1, PLANES, image_b3hw=img)
    # eq. 9-10: E = E_pred + 0.25 (E_meas - E_pred) = 0.75 E_pred + 0.25 E_meas
    assert torch.allclose(out.logp_bdhw, dpv.normalize_log(0.75 * m1 + 0.25 * m2))
    assert seen['image'] is img
    # g = 0 keeps the prediction, g = identity takes the measurement
    f = DPVFilter(mode='knet', knet=lambda r, i: torch.zeros_like(r))
    f.step(m1, Kt, se3(), 0.0, PLANES)
    assert torch.allclose(f.step(m2, Kt, se3(), 0.1, PLANES).logp_bdhw, m1)
    f = DPVFilter(mode='knet', knet=lambda r, i: r)
    f.step(m1, Kt, se3(), 0.0, PLANES)
    assert torch.allclose(f.step(m2, Kt, se3(), 0.1, PLANES).logp_bdhw, m2)


def test_zero_probability_prediction_does_not_lock_a_voxel():
    Kt = intrinsics(4, 3, 3.0)
    locked = torch.full((1, D, 3, 4), -1e4, dtype=DT)
    locked[:, 3] = 0.0                                           # "certain" of plane 3, -1e4 elsewhere
    locked[:, 20, 0, 0] = -math.inf                              # and truly impossible plane 20 at one pixel
    meas = dpv.normalize_log(torch.zeros(1, D, 3, 4, dtype=DT).index_fill(1, torch.tensor([20]), 6.0))
    f = DPVFilter(mode='bayes')
    out = f.step(locked, Kt, se3(), 0.0, PLANES)
    assert torch.isfinite(out.logp_bdhw).all() and out.logp_bdhw.min() >= dpv.LOG_FLOOR - 1.0
    for i in range(1, 12):
        out = f.step(meas, Kt, se3(), 0.1 * i, PLANES)
        assert torch.isfinite(out.logp_bdhw).all()
    assert (out.logp_bdhw.argmax(1) == 20).all()


def test_nan_measurement_is_sanitised():
    Kt = intrinsics(4, 3, 3.0)
    m = torch.zeros(1, D, 3, 4, dtype=DT)
    m[0, :, 0, 0] = float('nan')
    out = DPVFilter(mode='bayes').step(m, Kt, se3(), 0.0, PLANES)
    assert torch.isfinite(out.logp_bdhw).all()
    assert torch.allclose(out.logp_bdhw.exp().sum(1), torch.ones(1, 3, 4, dtype=DT))


def test_invalid_arguments():
    with pytest.raises(ValueError):
        DPVFilter(mode='kalman')
    with pytest.raises(ValueError):
        DPVFilter(mode='knet')
    with pytest.raises(ValueError):
        DPVFilter(damping=1.5)


# ------------------------------------------------------------------ reset rules

@pytest.fixture
def warm():
    """A bayes filter with one step done at t = 1 s, identity pose; returns (filter, meas)."""
    Kt = intrinsics(8, 6, 6.0)
    gen = torch.Generator().manual_seed(5)
    meas = dpv.normalize_log(torch.randn(1, 8, 6, 8, generator=gen, dtype=DT))
    f = DPVFilter(mode='bayes', max_time_gap=0.5, max_translation=0.2, max_rotation_deg=10.0)
    planes = dpv.depth_planes(0.5, 4.0, 8, dtype=DT)
    first = f.step(meas, Kt, se3(), 1.0, planes)
    assert first.reset_reason == 'first frame'
    return f, meas, Kt, planes


def _check_reset(out: FilterStep, meas, words):
    assert out.reset_reason is not None and all(w in out.reset_reason for w in words), out.reset_reason
    assert out.predicted_logp_bdhw is None
    assert torch.allclose(out.logp_bdhw, meas)


def test_no_reset_on_small_motion(warm):
    f, meas, Kt, planes = warm
    out = f.step(meas, Kt, se3(rot_y(math.radians(5)), (0.1, 0.0, 0.05)), 1.3, planes)
    assert out.reset_reason is None and out.predicted_logp_bdhw is not None
    assert not torch.allclose(out.logp_bdhw, meas)


def test_reset_first_frame_and_explicit_reset(warm):
    f, meas, Kt, planes = warm
    f.reset()
    assert f.logp_bdhw is None
    _check_reset(f.step(meas, Kt, se3(), 1.1, planes), meas, ['first frame'])


def test_reset_time_gap(warm):
    f, meas, Kt, planes = warm
    _check_reset(f.step(meas, Kt, se3(), 1.6, planes), meas, ['time gap'])
    # and the filter continues normally from there
    assert f.step(meas, Kt, se3(), 1.7, planes).reset_reason is None


def test_reset_time_backwards(warm):
    f, meas, Kt, planes = warm
    _check_reset(f.step(meas, Kt, se3(), 0.9, planes), meas, ['backwards'])


def test_reset_nan_pose(warm):
    f, meas, Kt, planes = warm
    bad = se3().clone()
    bad[0, 0, 3] = float('nan')
    _check_reset(f.step(meas, Kt, bad, 1.1, planes), meas, ['non-finite pose'])
    assert torch.isfinite(f.logp_bdhw).all()
    # the frame after a NaN pose cannot be predicted either
    _check_reset(f.step(meas, Kt, se3(), 1.2, planes), meas, ['previous pose'])
    assert f.step(meas, Kt, se3(), 1.3, planes).reset_reason is None
    inf_pose = se3().clone()
    inf_pose[0, 1, 1] = float('inf')
    _check_reset(f.step(meas, Kt, inf_pose, 1.4, planes), meas, ['non-finite pose'])


def test_reset_translation_jump(warm):
    f, meas, Kt, planes = warm
    _check_reset(f.step(meas, Kt, se3(t=(0.0, 0.25, 0.0)), 1.1, planes), meas, ['pose jump', 'translation'])


def test_reset_rotation_jump(warm):
    f, meas, Kt, planes = warm
    _check_reset(f.step(meas, Kt, se3(rot_y(math.radians(12))), 1.1, planes), meas, ['pose jump', 'rotation'])


def test_jump_limit_is_a_speed_limit_with_a_floor():
    assert MOTION_REFERENCE_S == 1.0
    assert jump_limit(0.2, 0.0) == jump_limit(0.2, 0.5) == jump_limit(0.2, 1.0) == pytest.approx(0.2)
    assert jump_limit(0.2, 3.0) == pytest.approx(0.6) and jump_limit(10.0, 2.5) == pytest.approx(25.0)
    assert jump_limit(math.inf, 5.0) == math.inf


def test_distant_steps_with_continuous_motion_do_not_reset():
    """Keyframes of a stream whose frames in between were left out: steps 3 s apart, moving 0.5 m and
    turning 25 deg each time (above the 0.2 m / 10 deg thresholds, below 3 s x those per second). With the
    time-gap rule off (as the Estimator builds it) the filter keeps fusing; a faster motion still resets."""
    Kt = intrinsics(8, 6, 6.0)
    planes = dpv.depth_planes(0.5, 4.0, 8, dtype=DT)
    gen = torch.Generator().manual_seed(7)
    meas = dpv.normalize_log(torch.randn(1, 8, 6, 8, generator=gen, dtype=DT))
    f = DPVFilter(mode='bayes', max_time_gap=math.inf, max_translation=0.2, max_rotation_deg=10.0)
    assert f.step(meas, Kt, se3(), 0.0, planes).reset_reason == 'first frame'
    for k in range(1, 4):
        out = f.step(meas, Kt, se3(rot_y(math.radians(25 * k)), (0.5 * k, 0.0, 0.0)), 3.0 * k, planes)
        assert out.reset_reason is None and out.predicted_logp_bdhw is not None, (k, out.reset_reason)
    # 0.7 m in 3 s > 0.6 m; 35 deg in 3 s > 30 deg: teleports
    T = se3(rot_y(math.radians(75)), (1.5, 0.7, 0.0))
    _check_reset(f.step(meas, Kt, T, 12.0, planes), meas, ['pose jump', 'translation', 'in 3.000 s'])
    _check_reset(f.step(meas, Kt, T @ se3(rot_y(math.radians(35))), 15.0, planes), meas, ['pose jump', 'rotation'])
    # the time-gap rule, when a caller wants it, still judges the time between steps
    g = DPVFilter(mode='bayes', max_time_gap=2.0, max_translation=0.2, max_rotation_deg=10.0)
    g.step(meas, Kt, se3(), 0.0, planes)
    _check_reset(g.step(meas, Kt, se3(t=(0.1, 0.0, 0.0)), 3.0, planes), meas, ['time gap'])


def test_reset_layout_change(warm):
    f, meas, Kt, planes = warm
    _check_reset(f.step(meas, Kt, se3(), 1.1, dpv.depth_planes(0.4, 4.0, 8, dtype=DT)), meas, ['layout'])


def test_reset_per_batch_element():
    Kt = intrinsics(8, 6, 6.0)
    planes = dpv.depth_planes(0.5, 4.0, 8, dtype=DT)
    gen = torch.Generator().manual_seed(6)
    meas = dpv.normalize_log(torch.randn(2, 8, 6, 8, generator=gen, dtype=DT))
    f = DPVFilter(mode='bayes', max_translation=0.2)
    f.step(meas, Kt, se3().expand(2, 4, 4), 0.0, planes)
    T = torch.cat([se3(t=(0.05, 0, 0)), se3(t=(1.0, 0, 0))])
    out = f.step(meas, Kt, T, 0.1, planes)
    assert 'pose jump' in out.reset_reason and '[1]' in out.reset_reason
    assert torch.allclose(out.logp_bdhw[1], meas[1])            # element 1 restarted
    assert not torch.allclose(out.logp_bdhw[0], meas[0])        # element 0 fused
    assert out.predicted_logp_bdhw is not None


def test_predict_does_not_change_state(warm):
    f, meas, Kt, planes = warm
    before = f.logp_bdhw.clone()
    p = f.predict(se3(t=(0.05, 0.0, 0.0)))
    assert p.shape == meas.shape and torch.allclose(f.logp_bdhw, before)
    assert torch.allclose(f.predict(se3()), meas)


def _peaked_patch(k_plane, cols, D_=D, h=H, w=W, floor=-30.0):
    """A DPV that is sure of plane ``k_plane`` on the columns ``cols`` and uniform elsewhere."""
    logp = torch.full((1, D_, h, w), -math.log(D_), dtype=DT)
    patch = torch.full((1, D_, h, len(cols)), floor, dtype=DT)
    patch[:, k_plane] = 0.0
    logp[..., cols] = dpv.normalize_log(patch)
    return logp


@pytest.mark.parametrize('use_step', [False, True])
def test_prediction_moves_a_peaked_patch_by_the_hand_computed_shift(use_step):
    """Camera A at the origin is sure of plane k (depth z_k) on columns 20..25. Camera B is A moved t m to the
    right (world x), no rotation: a point at depth z seen at column u in A is at u - f * t / z in B, at the same
    depth. With t = 6 z_k / f the patch must appear 6 columns to the left, on the same plane (pure translation
    sideways keeps every depth), and the columns it left must lose the peak. (The farther planes of a moved ray
    look into A's uniform columns, so the peak keeps 0.6-0.8 of the mass, not all of it.)"""
    k, shift = 12, 6
    z_k = float(PLANES[k])
    f = float(K[0, 0, 0])
    t = shift * z_k / f
    cols = list(range(20, 26))
    meas = _peaked_patch(k, cols)
    filt = DPVFilter(mode='bayes', max_translation=10.0)
    filt.step(meas, K, se3(), 0.0, PLANES)
    T_b = se3(t=(t, 0.0, 0.0))
    if use_step:
        pred = filt.step(_peaked_patch(k, cols), K, T_b, 0.1, PLANES).predicted_logp_bdhw
    else:
        pred = filt.predict(T_b)
    p = pred.exp()[0]                                  # (D, H, W)
    moved = [c - shift for c in cols]                  # columns 14..19
    left_behind = [c for c in cols if c not in moved]  # 20..25
    assert float(p[k][:, moved].min()) > 0.5, 'the peak did not arrive where the hand-computed shift puts it'
    assert int(p[:, :, moved].argmax(0).unique().numel()) == 1 and int(p[:, :, moved].argmax(0)[0, 0]) == k
    assert float(p[k][:, left_behind + [moved[0] - 1]].max()) < 0.2, \
        'the peak stayed where it was or moved the wrong way'
    # moved the other way (the inverted relative pose) it would sit on columns 26..31
    assert float(p[k][:, [c + shift for c in cols]].max()) < 0.2
