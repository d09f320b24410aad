"""Where the metric anchors overrule the networks: the judge's map that hears a few dozen anchors, the classical
sweep's depth blended in by confidence (core.anchors, stream.metric_anchors, stream.classical_fallback), with
answers worked out by hand, and through the pipeline with the networks' depth of a region doubled."""
import math

import numpy as np
import pytest

from dpv_sensor.core import anchors as A
from dpv_sensor.stream import metric_anchors as MA

K = np.array([[500.0, 0.0, 160.0], [0.0, 500.0, 128.0], [0.0, 0.0, 1.0]])
SIZE_HW = (256, 320)
BAND = math.log(1.25)


def test_confidence_sigma_and_band_by_hand():
    # 0.9 of a Gaussian within log 1.25 = 0.22314: sigma = 0.22314 / (sqrt 2 erfinv 0.9) = 0.22314 / 1.644854
    assert A.confidence_sigma(np.array([0.9]))[0] == pytest.approx(0.135661, rel=1e-5)
    assert A.band_confidence(np.array([0.135661]))[0] == pytest.approx(0.9, rel=1e-5)
    # one sigma either side holds 68.27 %
    assert A.band_confidence(np.array([BAND]))[0] == pytest.approx(0.682689, rel=1e-5)


def test_blend_by_hand():
    ca = A.band_confidence(np.array([0.2]))                 # sigma 0.2 at 2 m
    cb = A.band_confidence(np.array([0.1]))                 # sigma 0.1 at 1 m
    d, c, w = A.blend_log_depth(np.array([2.0]), ca, np.array([1.0]), cb)
    # weights 1 / 0.04 and 1 / 0.01: b has 100 / 125 = 0.8; log d = 0.2 log 2
    assert w[0] == pytest.approx(0.8, rel=1e-6)
    assert d[0] == pytest.approx(2.0 ** 0.2, rel=1e-6)
    # the smaller std (0.1), widened by the mixture's spread 0.8 x 0.2 x (log 2)^2: sqrt(0.01 + 0.076872) = 0.29474
    assert c[0] == pytest.approx(A.band_confidence(np.array([math.sqrt(0.01 + 0.16 * math.log(2) ** 2)]))[0])
    assert c[0] == pytest.approx(A.band_confidence(np.array([0.29474]))[0], rel=1e-4)
    d, c, w = A.blend_log_depth(np.array([1.0]), ca, np.array([1.0]), cb)
    assert c[0] == pytest.approx(cb[0])                     # agreeing: the larger confidence, no credit for both
    d, c, w = A.blend_log_depth(np.array([2.0]), ca, np.array([1.0]), np.array([0.0]))
    assert w[0] == 0.0 and d[0] == pytest.approx(2.0) and c[0] == pytest.approx(ca[0])


@pytest.mark.parametrize('x,y', [(0, 0), (319, 255), (0, 130), (160, 128), (141, 107)])
def test_the_judge_counts_a_lone_anchor_as_its_own_weight_anywhere(x, y):
    """A lone exact anchor at a corner, an edge, the middle, next to a node: the judge's support at its own pixel is
    its weight 1 / (0 + 0 + 0.1^2) = 100, whatever share of it the grid reads back there (3/4 per axis at an end
    node, 1/2 at an interior one: 0.42 in a corner, 1/8 in the middle); the cautious map's is that share of it."""
    depth = np.full(SIZE_HW, 2.0)
    uv = np.array([[float(x), float(y)]])
    anchors = A.Anchors(uv, np.array([2.0 * math.exp(0.1)]), np.zeros(1), np.zeros(1), np.zeros(1, np.int64), K)
    fit = A.ScaleFit(0.1, 0.0, 1, 1, np.ones(1))
    cfg = A.AnchorConfig(grid_depth_bins=16)
    judge = A.fit_scale_map(np.array([0.1]), anchors, uv, depth, fit, (math.log(0.3), math.log(8.0)), cfg,
                            in_anchor_weights=True)
    assert judge.support_hw[y, x] == pytest.approx(100.0, rel=1e-4)
    # the judge's map is the anchors' weighted mean, here the lone anchor's 0.1, its sigma sqrt(1 / 100)
    assert judge.log_scale_hw[y, x] == pytest.approx(0.1, rel=1e-4)
    assert judge.sigma_hw[y, x] == pytest.approx(0.1, rel=1e-4)
    cautious = A.fit_scale_map(np.array([0.1]), anchors, uv, depth, fit, (math.log(0.3), math.log(8.0)), cfg)
    gy, gx = (y + 0.5) / 256 * 6 - 0.5, (x + 0.5) / 320 * 8 - 0.5
    gz = (math.log(2.0) - math.log(0.3)) / (math.log(8.0) - math.log(0.3)) * 15
    back = (A.axis_readback(np.clip([gy], 0, 5), 6) * A.axis_readback(np.clip([gx], 0, 7), 8)
            * A.axis_readback(np.array([gz]), 16))[0]
    assert cautious.support_hw[y, x] == pytest.approx(100.0 * back, rel=1e-4)


def test_axis_readback_by_hand():
    # 5 nodes: 1/2 at an interior node, 3/4 at an end node, half way between two interior nodes
    # 0.25 (1/2) + 0.5 (1/4) + 0.25 (1/2) = 3/8
    assert A.axis_readback(np.array([2.0, 0.0, 4.0, 1.5]), 5) == pytest.approx([0.5, 0.75, 0.75, 0.375])
    assert A.axis_readback(np.array([0.3]), 1) == pytest.approx([1.0])


def _anchors(uv, depth, sigma):
    n = len(depth)
    return A.Anchors(np.asarray(uv, float), np.asarray(depth, float), np.full(n, sigma), np.zeros(n),
                     np.zeros(n, np.int64), K)


def _table_scene(n_table=40, seed=0, sigma=0.1):
    """A wall at 3 m, a table at 0.8 m in rows 160+; ``n_table`` anchors on the table and as many on the wall, each
    of std ``sigma`` (about what the window's pairs give), scattered at random."""
    depth = np.full(SIZE_HW, 3.0, np.float32)
    depth[160:] = 0.8
    rng = np.random.default_rng(seed)
    uv = np.r_[np.c_[rng.uniform(5, 315, n_table), rng.uniform(170, 250, n_table)],
               np.c_[rng.uniform(5, 315, n_table), rng.uniform(5, 150, n_table)]]
    z = depth[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)].astype(float)
    return depth, _anchors(uv, z, sigma)


def test_the_judge_hears_forty_anchors_that_the_cautious_map_drowns():
    """Forty anchors of std 0.1 on a table the networks put at twice its depth: the cautious map's prior (worth two
    anchors' weight against an eighth of each anchor's read back) leaves the table within 10 % of where the
    networks put it; the judge counts the anchors' own weights, overrules the table, and brings it over half the
    way back; the wall, where the networks were right, keeps its depth and confidence exactly."""
    gt, anchors = _table_scene()
    net = gt.copy()
    net[160:] *= 2.0
    x = np.c_[anchors.uv_n2, np.ones(len(anchors))]
    log_ratio = np.log(anchors.depth_n) - np.log(A.sample_depth(net, x[:, :2]))
    fit = A.fit_log_scale(log_ratio, anchors)
    cautious = A.fit_scale_map(log_ratio, anchors, anchors.uv_n2, net, fit, (math.log(0.3), math.log(8.0)))
    assert abs(np.median(cautious.log_scale_hw[200:])) < math.log(1.1)
    conf = np.full(SIZE_HW, 0.95, np.float32)
    aligner = MA.AnchorAligner('dense', depth_range=(0.3, 8.0), judge='counted')
    d, c, rep = aligner.apply(net, conf, K, anchors)
    table = (slice(180, 256), slice(0, 320))
    assert rep.overruled_pixels > 0.5 * 96 * 320
    assert np.median(d[table] / gt[table]) < 1.35                # over half the way back in log depth (2^0.5 = 1.41)
    assert np.median(c[table]) < 0.5                          # no longer published as confident
    wall = (slice(0, 140), slice(0, 320))
    assert np.array_equal(d[wall], net[wall]) and np.array_equal(c[wall], conf[wall])


def test_anchors_that_agree_within_their_sigma_overrule_nothing():
    """The networks 5 % too far on the table: inside three sigma of forty anchors of std 0.1 (the judge's sigma
    there is about 0.03 with the 3 % shared bias; 3 sigma is 0.09 > log 1.05 = 0.049), nothing is overruled and
    the fallback is never asked for."""
    gt, anchors = _table_scene()
    net = gt.copy()
    net[160:] *= 1.05
    asked = []
    aligner = MA.AnchorAligner('dense', depth_range=(0.3, 8.0), judge='counted')
    d, c, rep = aligner.apply(net, np.full(SIZE_HW, 0.9, np.float32), K, anchors,
                              fallback=lambda: asked.append(1))
    assert rep.overruled_pixels == 0 and not asked and rep.fallback is None


def test_the_classical_depth_is_blended_in_where_the_networks_are_overruled():
    """The networks put the table at twice its depth; the sweep has it right at confidence 0.8 (its texture), and
    nothing at all on the blank wall: the table ends nearer the truth than the judge alone brings it, the wall is
    the networks' as before, and the counters say where the sweep outweighed the networks."""
    gt, anchors = _table_scene()
    net = gt.copy()
    net[160:] *= 2.0
    conf = np.full(SIZE_HW, 0.95, np.float32)
    sweep_d = gt.copy()
    sweep_c = np.where(np.arange(SIZE_HW[0])[:, None] >= 160, 0.8, 0.0).astype(np.float32) * np.ones(SIZE_HW)
    plain = MA.AnchorAligner('dense', depth_range=(0.3, 8.0), judge='counted')
    d0, c0, _ = plain.apply(net, conf, K, anchors)
    aligner = MA.AnchorAligner('dense', depth_range=(0.3, 8.0), judge='counted')
    d, c, rep = aligner.apply(net, conf, K, anchors, fallback=lambda: (sweep_d, sweep_c.astype(np.float32)))
    table = (slice(180, 256), slice(0, 320))
    err, err0 = np.abs(np.log(d[table] / gt[table])), np.abs(np.log(d0[table] / gt[table]))
    assert np.median(err) < 0.02 and np.median(err) < 0.5 * np.median(err0), (np.median(err), np.median(err0))
    assert np.median(c[table]) > np.median(c0[table])             # the sweep's confidence where it outweighed
    assert rep.fallback == 'blended' and rep.fallback_pixels > 0.9 * 76 * 320
    st = aligner.status
    assert st.keyframes_fallback == 1 and st.pixels_fallback == rep.fallback_pixels
    wall = (slice(0, 140), slice(0, 320))
    assert np.array_equal(d[wall], d0[wall]) and np.array_equal(c[wall], c0[wall])
    # no classical depth for the keyframe: said so, and the networks' corrected depth is published
    d2, _c2, rep2 = MA.AnchorAligner('dense', depth_range=(0.3, 8.0), judge='counted').apply(net, conf, K, anchors,
                                                                             fallback=lambda: None)
    assert rep2.fallback == 'no classical depth for this keyframe' and np.array_equal(d2, d0)


# ---------------------------------------------------------------------------------------------------------------
# through the pipeline: a rendered room, exact poses as the odometry, the shipped networks at a small size; the
# networks' depth of the lower part of every keyframe doubled just before the anchors

@pytest.fixture(scope='module')
def doubled_run():
    import torch
    from dpv_sensor.data.synthetic import render_sequence
    from dpv_sensor.evaluation import runner as RN
    from dpv_sensor.evaluation.runner import resize_nearest
    from dpv_sensor.stream import estimator as EST
    from dpv_sensor.stream.frame import Frame
    from dpv_sensor.stream.pipeline import Pipeline
    room = render_sequence(50, 30, width=320, height=240)
    index = {float(room.stamp(i)): i for i in range(len(room))}
    hold = EST.Estimator._hold_to_anchors

    def doubled(self, ref, depth, conf, fallback=None):
        gt = resize_nearest(np.asarray(room.depth(index[float(ref.stamp)]), np.float32), tuple(depth.shape[-2:]))
        gt[int(0.55 * gt.shape[0]):] *= 2.0
        return hold(self, ref, torch.as_tensor(gt)[None], torch.full_like(conf, 0.95), fallback)

    mp = pytest.MonkeyPatch()
    mp.setattr(EST.Estimator, '_hold_to_anchors', doubled)
    try:
        config, _ = RN.build_config({'processing_width': 160, 'processing_height': 128,
                                     'anchor_fallback': 'classical', 'anchor_judge': 'counted'})
        pipe = Pipeline(config)
        frames = [Frame(stamp=float(room.stamp(i)), image=room.image(i), K_33=np.asarray(room.K, np.float64),
                        T_world_cam_44=np.asarray(room.pose(i)), frame_id='camera') for i in range(len(room))]
        outs = [o for o in (pipe.push(f).output for f in frames) if o is not None and o.is_keyframe]
    finally:
        mp.undo()
    return room, index, outs, pipe


def test_pipeline_overrules_a_doubled_region_and_blends_the_sweep_in(doubled_run):
    from dpv_sensor.evaluation.runner import resize_nearest
    room, index, outs, pipe = doubled_run
    assert pipe.estimator.config.anchor_fallback == 'classical' and pipe.estimator.measurement == 'network'
    overruled = [o for o in outs if o.anchors is not None and o.anchors.overruled_pixels > 0]
    assert len(overruled) >= 3, [o.anchors for o in outs]
    low_ratio, low_conf = [], []
    for o in overruled:
        gt = resize_nearest(np.asarray(room.depth(index[o.stamp]), np.float32), o.depth_hw.shape)
        H = gt.shape[0]
        low, high = slice(int(0.6 * H), H), slice(0, int(0.5 * H))
        ok = np.isfinite(o.depth_hw) & (gt > 0)
        low_ratio.append(np.median((o.depth_hw / gt)[low][ok[low]]))
        low_conf.append(np.median(o.confidence_hw[low]))
        # the part the networks had right keeps its depth
        assert np.median((o.depth_hw / gt)[high][ok[high]]) == pytest.approx(1.0, abs=0.01)
        assert o.anchors.fallback == 'blended' and o.anchors.fallback_pixels > 0
        assert o.timings_ms['anchors.classical'] > 0
    # the anchors (all on the textured floor, on a part of it in some keyframes) bring the doubled part well back
    # where they cover most of it, and take its confidence
    assert sorted(low_ratio)[1] < 1.35, low_ratio
    assert sorted(low_conf)[1] < 0.5, low_conf
    st = pipe.status.anchors
    assert st['keyframes_fallback'] == len(overruled) and st['pixels_fallback'] > 0


def test_no_fallback_when_the_measurement_is_the_sweep_or_when_switched_off():
    from dpv_sensor.evaluation import runner as RN
    from dpv_sensor.stream.pipeline import Pipeline
    for params in ({'measurement': 'classical'}, {}, {'depth_anchors': 'off'},
                   {'weights': '/nonexistent/weights.safetensors'}):       # auto falls back to the sweep
        params = dict({'anchor_fallback': 'classical'}, **params) if params else params
        config, _ = RN.build_config(dict({'processing_width': 96, 'processing_height': 72}, **params))
        est = Pipeline(config).estimator
        assert est.fallback is None, params
    assert est.measurement == 'classical'


def test_the_judge_does_not_reach_where_no_anchor_is():
    """Every anchor on the table the networks doubled; the wall above it stands exactly where the doubled table now
    seems to be (1.6 m), so it shares the table's bins of depth and only the image grid's reach separates them: the
    wall more than a cell (43 px) above the table keeps its depth and confidence (rows 0-100; the table starts at
    row 160, its anchors at 170)."""
    gt, anchors = _table_scene()
    gt[:160] = 1.6
    on_table = anchors.uv_n2[:, 1] >= 160
    a = _anchors(anchors.uv_n2[on_table], anchors.depth_n[on_table], 0.1)
    net = gt.copy()
    net[160:] *= 2.0
    conf = np.full(SIZE_HW, 0.95, np.float32)
    d, c, rep = MA.AnchorAligner('dense', depth_range=(0.3, 8.0), judge='counted').apply(net, conf, K, a)
    assert rep.overruled_pixels > 0
    top = (slice(0, 100), slice(0, 320))
    assert np.array_equal(d[top], net[top]) and np.array_equal(c[top], conf[top])


def test_scattered_anchors_correct_nothing_and_scale_mode_blends_nothing():
    """A third of the anchors say the depth is right, a third 1.5x too far, a third 1.5x too near, in the same
    places: no map can agree with most of them, nothing changes; with depth_anchors 'scale' a whole image 1.3x too
    far is overruled, but the sweep is not blended into the whole image."""
    gt, anchors = _table_scene(n_table=60)
    z = anchors.depth_n.copy()
    z[0::3] *= 1.5
    z[1::3] /= 1.5
    conf = np.full(SIZE_HW, 0.9, np.float32)
    counted = MA.AnchorAligner('dense', depth_range=(0.3, 8.0), judge='counted')
    d, c, rep = counted.apply(gt, conf, K, _anchors(anchors.uv_n2, z, 0.05))
    assert d is gt and c is conf and rep.reason.startswith('the anchors do not agree with a scale map'), rep
    asked = []
    d, c, rep = MA.AnchorAligner('scale', depth_range=(0.3, 8.0)).apply(
        gt * 1.3, conf, K, anchors, fallback=lambda: asked.append(1))
    assert rep.overruled_pixels == gt.size and not asked and rep.fallback is None


def test_the_cautious_default_leaves_the_doubled_table_and_counts_nothing_overruled():
    """anchor_judge 'cautious' (the default), as before the counted judge: forty anchors of std 0.1 on a table at
    twice its depth and forty on the wall the networks got right agree with no one scale (half within 1.5 sigma of
    it), so nothing is applied; the table keeps its depth and confidence (what the counted judge is for, and why it
    is not the default: it also follows clusters of biased anchors)."""
    gt, anchors = _table_scene()
    net = gt.copy()
    net[160:] *= 2.0
    d, c, rep = MA.AnchorAligner('dense', depth_range=(0.3, 8.0)).apply(net, np.full(SIZE_HW, 0.95, np.float32),
                                                                        K, anchors)
    assert rep.overruled_pixels == 0 and rep.reason.startswith('the anchors do not agree on a scale'), rep
    assert d is net
    with pytest.raises(ValueError, match='anchor_judge'):
        MA.AnchorAligner('dense', judge='strict')
