"""Metric anchors: triangulation, the anchors' sigma, the robust fits and the aligner, on tiny analytic cameras
whose answers are worked out by hand (core.anchors, stream.metric_anchors)."""
import math

import numpy as np
import pytest

from dpv_sensor.core import anchors as A
from dpv_sensor.stream import metric_anchors as MA

K = np.array([[500.0, 0.0, 160.0], [0.0, 500.0, 128.0], [0.0, 0.0, 1.0]])
SIZE_HW = (256, 320)


def _project(X_n3, T_cam_world=np.eye(4)):
    Xc = X_n3 @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    p = Xc @ K.T
    return p[:, :2] / p[:, 2:3]


def _translation(x, y=0.0, z=0.0):
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def _rotation_y(deg):
    a = math.radians(deg)
    T = np.eye(4)
    T[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
    return T


def _scene(n=300, seed=0, z=(1.5, 3.0)):
    rng = np.random.default_rng(seed)
    zs = rng.uniform(*z, n)
    uv = np.c_[rng.uniform(10, 310, n), rng.uniform(10, 246, n)]
    return np.c_[(uv - K[:2, 2]) / 500.0 * zs[:, None], zs]


def test_triangulation_recovers_exact_depth_and_rejects_behind():
    X = _scene(50)
    T_src_ref = _translation(-0.2)                       # the source 20 cm to the right of the reference
    a = A.triangulate_pair(_project(X), _project(X, T_src_ref), K, T_src_ref,
                           config=A.AnchorConfig(min_parallax_deg=0.5))
    assert len(a) == 50 and np.allclose(a.depth_n, X[:, 2], rtol=1e-9)
    # the inverse convention puts every point behind a camera
    b = A.triangulate_pair(_project(X), _project(X, T_src_ref), K, np.linalg.inv(T_src_ref))
    assert len(b) == 0 and b.rejected['behind'] == 50


def test_anchor_sigma_by_hand_two_views():
    # one point straight ahead at z = 2 m, the source 10 cm to the side: the rays meet at theta = atan(0.1 / 2)
    X = np.array([[0.0, 0.0, 2.0]])
    T_src_ref = _translation(-0.1)
    cfg = A.AnchorConfig(pixel_sigma_px=0.5, min_parallax_deg=0.5, max_sigma_log=1.0)
    a = A.triangulate_pair(_project(X), _project(X, T_src_ref), K, T_src_ref, sigma_rot_rad=0.001,
                           sigma_trans_m=0.002, config=cfg)
    tan_theta = 0.1 / 2.0
    # independent: sqrt(2) * (0.5 px / 500 px) / tan(theta) = 0.0282843; shared: hypot(0.001 / tan, 0.002 / 0.1)
    assert a.sigma_ind_n[0] == pytest.approx(math.sqrt(2) * 0.001 / tan_theta, rel=1e-6)
    assert a.sigma_ind_n[0] == pytest.approx(0.0282843, rel=1e-5)
    assert a.sigma_pair_n[0] == pytest.approx(math.hypot(0.02, 0.02), rel=1e-6)


def test_parallax_and_reprojection_rules():
    X = np.array([[0.0, 0.0, 2.0], [0.2, 0.1, 2.0]])
    T_src_ref = _translation(-0.02)                      # 0.57 deg of parallax at 2 m
    cfg = A.AnchorConfig(min_parallax_deg=1.0, max_sigma_log=1.0)
    a = A.triangulate_pair(_project(X), _project(X, T_src_ref), K, T_src_ref, config=cfg)
    assert len(a) == 0 and a.rejected['parallax'] == 2
    # 0.1 m baseline (2.9 deg); a match 3 px off the epipolar line (vertical) fails the 1.5 px reprojection limit
    T_src_ref = _translation(-0.1)
    pb = _project(X, T_src_ref)
    pb[1, 1] += 3.0
    a = A.triangulate_pair(_project(X), pb, K, T_src_ref, config=cfg)
    assert len(a) == 1 and a.rejected['reprojection'] == 1


def test_pure_rotation_gives_no_anchors():
    X = _scene(100)
    T_src_ref = _rotation_y(3.0)
    a = A.triangulate_pair(_project(X), _project(X, T_src_ref), K, T_src_ref)
    assert len(a) == 0


def test_track_triangulates_from_first_and_last_view_and_checks_the_middle():
    X = _scene(40)
    T_world = [np.eye(4), _translation(0.05), _translation(0.10)]
    pts = [_project(X, np.linalg.inv(T)) for T in T_world]
    a = A.triangulate_track(pts, T_world, K, 1, config=A.AnchorConfig(min_parallax_deg=0.5))
    assert len(a) == 40
    assert np.allclose(a.depth_n, X[:, 2], rtol=1e-9)          # same depth in the middle view (pure x motion)
    assert np.allclose(a.uv_n2, pts[1])
    pts[1] = pts[1].copy()
    pts[1][:5, 1] += 4.0                                       # five tracks that the middle view contradicts
    a = A.triangulate_track(pts, T_world, K, 1, config=A.AnchorConfig(min_parallax_deg=0.5))
    assert len(a) == 35 and a.rejected['reprojection'] == 5


def _anchors_at(uv, depth, sigma=0.02):
    n = len(depth)
    return A.Anchors(np.asarray(uv, float), np.asarray(depth, float), np.full(n, sigma), np.zeros(n),
                     np.zeros(n, np.int64), K)


def test_scale_fit_shrugs_off_twenty_percent_outliers():
    rng = np.random.default_rng(1)
    n = 200
    log_ratio = np.log(1.15) + rng.normal(0, 0.02, n)
    bad = rng.choice(n, n // 5, replace=False)
    log_ratio[bad] = rng.uniform(-1.0, 1.0, len(bad))          # 20 % anchors on moving things, mirrors, bad matches
    anchors = _anchors_at(np.zeros((n, 2)), np.ones(n))
    fit = A.fit_log_scale(log_ratio, anchors, A.AnchorConfig())
    assert fit.scale == pytest.approx(1.15, rel=0.02)
    assert fit.inliers < n
    assert A.fit_log_scale(log_ratio[:10], _anchors_at(np.zeros((10, 2)), np.ones(10)), A.AnchorConfig()) is None


def test_widened_confidence_by_hand():
    # c = 0.9 is a Gaussian log error of std log(1.25) / (sqrt 2 erfinv 0.9) = 0.13566; add 0.1 in quadrature
    s0 = math.log(1.25) / (math.sqrt(2) * 1.1630871)
    expect = math.erf(math.log(1.25) / (math.sqrt(2) * math.hypot(s0, 0.1)))
    assert A.widened_confidence(np.array([0.9]), 0.1)[0] == pytest.approx(expect, rel=1e-5)
    assert A.widened_confidence(np.array([0.9]), 0.0)[0] == pytest.approx(0.9, rel=1e-6)
    assert A.widened_confidence(np.array([0.0]), 0.1)[0] == 0.0


def _gt_scene():
    """A wall at 3 m with a near table (rows 160+) at 0.8 m, and anchors on a grid over both."""
    depth = np.full(SIZE_HW, 3.0, np.float32)
    depth[160:] = 0.8
    ys, xs = np.mgrid[8:256:16, 8:320:16]
    uv = np.c_[xs.ravel(), ys.ravel()].astype(float)
    return depth, uv, depth[ys.ravel(), xs.ravel()].astype(float)


def test_aligner_scale_brings_a_scaled_depth_back():
    gt, uv, z = _gt_scene()
    anchors = _anchors_at(uv, z)
    conf = np.full(SIZE_HW, 0.8, np.float32)
    d, c, rep = MA.AnchorAligner('scale').apply(gt * 1.15, conf, K, anchors)
    assert rep.applied == 'scale' and rep.scale == pytest.approx(1 / 1.15, rel=0.005)
    # the depth moves by the disagreement less one sigma of the anchors (fit and shared bias): 1.15 -> 1.15 e^-(...)
    sigma = math.hypot(rep.sigma, A.AnchorConfig().bias_sigma_log)
    assert sigma == pytest.approx(0.03, abs=0.002)
    assert np.median(d / gt) == pytest.approx(math.exp(sigma), rel=1e-4)
    assert np.all(c <= conf + 1e-6)                              # the fit's uncertainty only widens


def test_aligner_dense_overrules_a_near_table_put_at_twice_its_depth():
    gt, uv, z = _gt_scene()
    anchors = _anchors_at(uv, z)
    net = gt.copy()
    net[160:] *= 2.0                                             # the network puts the table at twice its depth
    conf = np.full(SIZE_HW, 0.95, np.float32)
    aligner = MA.AnchorAligner('dense')
    d, c, rep = aligner.apply(net, conf, K, anchors)
    table = (slice(200, 256), slice(0, 320))
    assert rep.overruled_pixels > 0 and aligner.status.keyframes_overruled == 1
    # the table's depth comes about half the way back (in log depth), and it is no longer published as confident
    assert np.median(d[table] / gt[table]) < 2.0 ** 0.55
    assert np.median(c[table]) < 0.7
    # the wall, where the network was right, keeps its depth and most of its confidence
    wall = (slice(0, 100), slice(0, 320))
    assert np.median(d[wall] / gt[wall]) == pytest.approx(1.0, abs=0.05)
    assert np.median(c[wall]) > 0.85


def test_aligner_without_enough_anchors_changes_nothing_bit_for_bit():
    gt, uv, z = _gt_scene()
    conf = np.full(SIZE_HW, 0.5, np.float32)
    aligner = MA.AnchorAligner('dense')
    d, c, rep = aligner.apply(gt, conf, K, _anchors_at(uv[:5], z[:5]))
    assert d is gt and c is conf and rep.applied == 'none' and rep.reason == 'too few anchors (5 < 20)'
    d, c, rep = aligner.apply(gt, conf, K, None)
    assert d is gt and c is conf and aligner.status.keyframes_checked == 1


def test_aligner_off_counts_but_does_not_touch():
    gt, uv, z = _gt_scene()
    conf = np.full(SIZE_HW, 0.5, np.float32)
    aligner = MA.AnchorAligner('off')
    d, c, rep = aligner.apply(gt * 1.2, conf, K, _anchors_at(uv, z))
    assert rep.scale == pytest.approx(1 / 1.2, rel=0.005) and rep.applied == 'none'
    assert np.array_equal(d, gt * 1.2) and c is conf
    with pytest.raises(ValueError, match='depth_anchors'):
        MA.AnchorAligner('global')


# ---------------------------------------------------------------------------------------------------------------
# through the pipeline (the node's code path): a rendered room, exact poses as the odometry, the classical model

PIPE = {'measurement': 'classical', 'processing_width': 96, 'processing_height': 72, 'num_planes': 32}


@pytest.fixture(scope='module')
def room():
    from dpv_sensor.data.synthetic import render_sequence
    return render_sequence(50, 30, width=320, height=240)


def _push_all(frames, **params):
    from dpv_sensor.evaluation import runner as RN
    from dpv_sensor.stream.pipeline import Pipeline
    config, _ = RN.build_config(dict(PIPE, **params))
    pipe = Pipeline(config)
    outs = [o for o in (pipe.push(f).output for f in frames) if o is not None and o.is_keyframe]
    return outs, pipe


def _frames(seq):
    from dpv_sensor.stream.frame import Frame
    return [Frame(stamp=float(seq.stamp(i)), image=seq.image(i), K_33=np.asarray(seq.K, np.float64),
                  T_world_cam_44=np.asarray(seq.pose(i)), frame_id='camera') for i in range(len(seq))]


def test_pipeline_brings_a_depth_scaled_by_1_15_back_to_the_truth(room, monkeypatch):
    """The published depth replaced by the rendered truth x 1.15 just before the anchors: the anchors, from the
    window's own flow and the odometry's poses, measure each keyframe's scale within 2 % of 1 / 1.15, and the
    published depth comes back to the truth but for the anchors' sigma (the correction's soft threshold)."""
    import torch
    from dpv_sensor.stream import estimator as EST
    from dpv_sensor.evaluation.runner import resize_nearest
    index = {float(room.stamp(i)): i for i in range(len(room))}
    hold = EST.Estimator._hold_to_anchors

    def scaled_truth(self, ref, depth, conf, fallback=None):
        gt = resize_nearest(np.asarray(room.depth(index[float(ref.stamp)]), np.float32), tuple(depth.shape[-2:]))
        return hold(self, ref, torch.as_tensor(gt * 1.15)[None], conf, fallback)

    monkeypatch.setattr(EST.Estimator, '_hold_to_anchors', scaled_truth)
    outs, pipe = _push_all(_frames(room), depth_anchors='scale')
    aligned = [o for o in outs if o.anchors is not None and o.anchors.applied == 'scale']
    assert len(aligned) >= 3, [o.anchors for o in outs]
    for o in aligned:
        gt = resize_nearest(np.asarray(room.depth(index[o.stamp]), np.float32), o.depth_hw.shape)
        ok = np.isfinite(o.depth_hw) & (gt > 0)
        assert o.anchors.scale == pytest.approx(1 / 1.15, rel=0.02), o.anchors
        sigma = math.hypot(o.anchors.sigma, A.AnchorConfig().bias_sigma_log)
        assert 1.0 <= np.median(o.depth_hw[ok] / gt[ok]) <= math.exp(sigma) + 0.02, o.anchors
    st = pipe.status.anchors
    assert st['keyframes_aligned'] == len(aligned) and st['anchors'] > 0


@pytest.mark.parametrize('target', ['output', 'belief'])
def test_with_anchor_target_belief_the_filter_takes_the_correction(room, monkeypatch, target):
    """The same depth x 1.15: with ``anchor_target: belief`` the filter's belief is moved by the correction of
    each aligned keyframe (its depth at the belief's pixels comes out 1/1.15 of what it was, but for the soft
    threshold), with ``output`` it is never touched."""
    import torch
    from dpv_sensor.core.filter import DPVFilter
    from dpv_sensor.stream import estimator as EST
    from dpv_sensor.evaluation.runner import resize_nearest
    index = {float(room.stamp(i)): i for i in range(len(room))}
    hold = EST.Estimator._hold_to_anchors
    rescale = DPVFilter.rescale_belief
    moved = []

    def scaled_truth(self, ref, depth, conf, fallback=None):
        gt = resize_nearest(np.asarray(room.depth(index[float(ref.stamp)]), np.float32), tuple(depth.shape[-2:]))
        return hold(self, ref, torch.as_tensor(gt * 1.15)[None], conf, fallback)

    def spy(self, log_scale_bhw):
        log_z = self._depths.log().view(1, -1, 1, 1)
        before = (self.logp_bdhw.exp() * log_z).sum(1)               # the belief's mean log depth
        # where the belief is surest (its largest plane mass in the top quarter) and not at the end planes, which
        # stand for everything beyond them and keep their mass
        prob = self.logp_bdhw.exp()
        peak = prob.amax(1)
        sure = (peak >= peak.quantile(0.75)) & (prob[:, 0] + prob[:, -1] < 0.05) & (log_scale_bhw != 0)
        rescale(self, log_scale_bhw)
        shift = ((self.logp_bdhw.exp() * log_z).sum(1) - before)[sure]
        moved.append((float(log_scale_bhw[log_scale_bhw != 0].median()), float(shift.median()),
                      float(log_scale_bhw[sure].median())))

    monkeypatch.setattr(EST.Estimator, '_hold_to_anchors', scaled_truth)
    monkeypatch.setattr(DPVFilter, 'rescale_belief', spy)
    outs, _pipe = _push_all(_frames(room), depth_anchors='scale', anchor_target=target)
    aligned = [o for o in outs if o.anchors is not None and o.anchors.applied == 'scale']
    assert len(aligned) >= 3, [o.anchors for o in outs]
    if target == 'output':
        assert moved == []
        return
    assert len(moved) == len(aligned)
    for (asked, _got, _sure), o in zip(moved, aligned):
        # the correction asked of the belief is the published depth's: towards the truth, less the soft threshold
        gt = resize_nearest(np.asarray(room.depth(index[o.stamp]), np.float32), o.depth_hw.shape)
        ok = np.isfinite(o.depth_hw) & (gt > 0)
        assert asked == pytest.approx(math.log(np.median(o.depth_hw[ok] / (1.15 * gt[ok]))), abs=0.01), moved
        assert -math.log(1.15) <= asked < -0.03, moved
    # the belief's mean log depth moved by it where the belief is surest (none such on the first keyframe, whose
    # belief is a single measurement)
    sure = [(got, asked_sure) for _a, got, asked_sure in moved if math.isfinite(got)]
    assert len(sure) >= 2, moved
    for got, asked_sure in sure:
        assert got == pytest.approx(asked_sure, abs=0.01), moved


class _TurnInPlace:
    """The room's first pose, turning about its vertical axis at 20 degrees a second: no translation at all."""

    def __init__(self, T0):
        self.T0 = np.asarray(T0, np.float64)

    def pose(self, t):
        a = math.radians(20.0) * float(t)
        R = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        T = self.T0.copy()
        T[:3, :3] = self.T0[:3, :3] @ R
        return T


def test_a_camera_turning_in_place_gets_no_anchors_and_the_same_depth_bit_for_bit():
    from dpv_sensor.data.synthetic import SyntheticScene
    from dpv_sensor.stream.frame import Frame
    scene = SyntheticScene(50, 160, 120)
    scene.trajectory = _TurnInPlace(scene.pose(0))
    frames = [Frame(stamp=float(scene.stamp(i)), image=scene.render_frame(i)['image'], K_33=np.asarray(scene.K),
                    T_world_cam_44=scene.pose(i), frame_id='camera') for i in range(24)]
    off, _ = _push_all(frames, depth_anchors='off')
    dense, pipe = _push_all(frames, depth_anchors='dense')
    assert len(off) == len(dense) >= 3
    for a, b in zip(off, dense):
        assert np.array_equal(a.depth_hw, b.depth_hw, equal_nan=True)
        assert np.array_equal(a.confidence_hw, b.confidence_hw)
        assert b.anchors.anchors == 0 and b.anchors.applied == 'none'
    assert pipe.status.anchors['keyframes_aligned'] == 0


@pytest.mark.parametrize('x,w,expected', [([1.0, 2.0, 3.0], [1, 1, 1], 2.0),
                                          ([1.0, 2.0, 3.0], [1, 1, 5], 3.0),
                                          ([1.0, 2.0], [1, 1], 1.5),          # half the weight exactly at 1.0
                                          ([3.0, 1.0, 2.0, 10.0], [1, 1, 1, 0.5], 2.0)])
def test_weighted_median_by_hand(x, w, expected):
    assert A.weighted_median(np.array(x), np.array(w, float)) == pytest.approx(expected)


def test_anchors_that_do_not_agree_on_a_scale_change_nothing():
    """A third of the anchors say the depth is right, a third 1.5x too far, a third 1.5x too near: no scale is
    applied, and the reason says so (a fit needs half of them within huber_k sigma of one scale)."""
    gt, uv, z = _gt_scene()
    z = z.copy()
    z[0::3] *= 1.5
    z[1::3] /= 1.5
    conf = np.full(SIZE_HW, 0.5, np.float32)
    aligner = MA.AnchorAligner('scale')
    d, c, rep = aligner.apply(gt, conf, K, _anchors_at(uv, z))
    assert d is gt and c is conf and rep.applied == 'none' and rep.reason.startswith('the anchors do not agree')
    assert aligner.status.keyframes_disagreeing == 1 and aligner.status.keyframes_aligned == 0


def _readback(f):
    """How much of a point's own splat a trilinear read at the same point gets back along one axis after the
    [1 2 1] / 4 blur, the point a fraction f past an interior node: 1/2 of each corner's square, 1/4 across."""
    return 0.5 * ((1 - f) ** 2 + f ** 2) + 0.5 * f * (1 - f)


def test_a_lone_anchor_moves_the_map_little():
    """The map's pull towards no correction is worth two anchors (grid_prior_anchors): one exact anchor saying
    log ratio 0.1 (inside the Huber threshold, 1.5 x 0.1) moves its own pixel by 0.1 * w / (w + prior), with w its
    weight 1 / 0.1^2 times what the blur leaves of it at its own position (about an eighth) and prior 2 / 0.1^2."""
    depth = np.full(SIZE_HW, 2.0)
    x, y = 140, 106                                    # next to the node at row 2, column 3
    gx, gy = (x + 0.5) / 320 * 8 - 0.5, (y + 0.5) / 256 * 6 - 0.5
    gz = (math.log(2.0) - math.log(0.3)) / (math.log(8.0) - math.log(0.3)) * 7
    w = 100.0 * _readback(gx % 1) * _readback(gy % 1) * _readback(gz % 1)
    uv = np.array([[float(x), float(y)]])
    anchors = A.Anchors(uv, np.array([2.0 * math.exp(0.1)]), np.zeros(1), np.zeros(1), np.zeros(1, np.int64), K)
    fit = A.ScaleFit(0.1, 0.0, 1, 1, np.ones(1))
    smap = A.fit_scale_map(np.array([0.1]), anchors, uv, depth, fit, (math.log(0.3), math.log(8.0)))
    assert w == pytest.approx(11.9, abs=0.2)
    assert smap.log_scale_hw[y, x] == pytest.approx(0.1 * w / (w + 200.0), rel=1e-6)
    assert smap.support_hw[y, x] == pytest.approx(w, rel=1e-6)
