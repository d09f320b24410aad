"""The streaming estimator (dpv_sensor/stream/estimator.py) and keyframe selection (dpv_sensor/stream/keyframes.py).

Scenes: a textured fronto-parallel plane rendered exactly by ray casting (numpy, below) for the
behavioural tests, and the procedural renderer ``data.synthetic.render_sequence`` for accuracy.
Images are tiny (input 80x60 .. 160x120, processing 64x48 .. 160x120, 16-32 planes).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dpv_sensor import params as P
from dpv_sensor.stream.estimator import Estimator, EstimatorConfig, PoseRefinementRequest
from dpv_sensor.evaluation.runner import EvalOptions, run_sequence
from dpv_sensor.evaluation.scoring import score_records
from dpv_sensor.stream.frame import DepthOutput, Frame
from dpv_sensor.stream.keyframes import KeyframeSelector, KeyframeWindow, pose_delta

torch.set_num_threads(1)

PLANE_Z = 2.0


# ----------------------------------------------------------------------------------------------------
# a tiny exact scene: textured plane z_world = PLANE_Z, cameras looking along +z
# ----------------------------------------------------------------------------------------------------

def intrinsics(w, h, f_rel=0.9):
    f = f_rel * w
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


def rot_y(deg):
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def pose(x=0.0, y=0.0, z=0.0, yaw_deg=0.0):
    T = np.eye(4)
    T[:3, :3] = rot_y(yaw_deg)
    T[:3, 3] = (x, y, z)
    return T


def texture(x, y):
    """Smooth aperiodic pattern in [0, 1] of world-plane coordinates (metres)."""
    t = 0.5 + 0.18 * np.sin(x * 31.0 + 0.3) + 0.15 * np.sin(y * 23.0 + x * 7.0) \
        + 0.1 * np.sin((x - y) * 53.0 + 1.1) + 0.07 * np.sin(x * 97.0 - y * 61.0)
    return np.clip(t, 0.0, 1.0)


def render(T_world_cam, K, w, h):
    """(uint8 RGB image, z-depth) of the plane seen by camera T_world_cam."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(h * w)])
    R, c = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d = R @ rays
    s = (PLANE_Z - c[2]) / d[2]                     # ray parameter = camera z-depth (rays have z = 1)
    X = c[:, None] + d * s
    g = texture(X[0], X[1]).reshape(h, w)
    img = np.stack([g, 0.8 * g + 0.1, 1.0 - 0.6 * g], -1)
    return (img * 255).round().astype(np.uint8), s.reshape(h, w).astype(np.float32)


def frame_at(i, T, w=80, h=60, dt=1 / 30.0, stamp=None, K=None):
    K = intrinsics(w, h) if K is None else K
    img, _ = render(T, K, w, h)
    return Frame(stamp=i * dt if stamp is None else stamp, image=img, K_33=K, T_world_cam_44=T, frame_id='cam')


def small_config(**kw) -> EstimatorConfig:
    base = dict(measurement='classical', processing_width=64, processing_height=48, num_planes=16,
                d_min=0.5, d_max=8.0, keyframe_translation=0.0, keyframe_rotation_deg=0.0,
                keyframe_max_interval=1, window_mode='causal')
    base.update(kw)
    return EstimatorConfig(**base)


def push_all(est, frames):
    return [est.push(f) for f in frames]


def sideways(n, step=0.03, **kw):
    return [frame_at(i, pose(x=step * i), **kw) for i in range(n)]


# ----------------------------------------------------------------------------------------------------
# configuration
# ----------------------------------------------------------------------------------------------------

def test_config_from_node_parameters():
    values = P.validate(P.defaults())
    cfg = EstimatorConfig.from_params(values)
    for name in ('preset', 'weights', 'measurement', 'device', 'torch_threads', 'processing_width',
                 'processing_height', 'd_min',
                 'd_max', 'num_planes', 'filter_mode', 'damping', 'reset_time_gap', 'odom_max_speed',
                 'odom_max_rate_deg', 'window_mode', 'keyframe_translation', 'keyframe_rotation_deg',
                 'keyframe_max_interval', 'publish_between_keyframes', 'output_resolution', 'pose_refinement'):
        assert name in P.SPEC_BY_NAME, name            # every node-facing field is a declared parameter
        assert getattr(cfg, name) == values[name], name
    values['window_mode'] = 'centered'
    values['processing_width'] = 96
    cfg = EstimatorConfig.from_params(values)
    assert cfg.window_mode == 'centered' and cfg.processing_size == (96, 256)
    with pytest.raises(ValueError, match='window_mode'):
        EstimatorConfig(window_mode='sideways').validate()
    with pytest.raises(ValueError, match='torch_threads'):
        EstimatorConfig(torch_threads=65).validate()


def test_torch_threads_is_applied_at_construction():
    try:
        torch.set_num_threads(2)
        Estimator(small_config())                               # 0: torch's setting is left alone
        assert torch.get_num_threads() == 2
        est = Estimator(small_config(torch_threads=1))
        assert torch.get_num_threads() == 1 and est.status.torch_threads == 1
    finally:
        torch.set_num_threads(1)


# ----------------------------------------------------------------------------------------------------
# keyframe selection rules, by hand
# ----------------------------------------------------------------------------------------------------

def test_pose_delta():
    t, r = pose_delta(pose(), pose(x=0.3, y=0.4, yaw_deg=20.0))
    assert t == pytest.approx(0.5) and r == pytest.approx(20.0)


def test_keyframe_baseline_threshold_pure_translation():
    sel = KeyframeSelector(translation=0.1, rotation_deg=10.0, max_interval=100)
    decisions = [sel.decide(pose(x=0.03 * i)) for i in range(10)]
    kf = [i for i, d in enumerate(decisions) if d.is_keyframe]
    # 0 (first), then 0.12 m from x=0 at frame 4 (0.09 m at frame 3 is not enough), then frame 8
    assert kf == [0, 4, 8]
    assert [decisions[i].reason for i in kf] == ['first', 'baseline', 'baseline']
    assert decisions[4].translation == pytest.approx(0.12)


def test_keyframe_rotation_threshold():
    sel = KeyframeSelector(translation=0.1, rotation_deg=10.0, max_interval=100)
    decisions = [sel.decide(pose(yaw_deg=3.0 * i)) for i in range(10)]
    kf = [i for i, d in enumerate(decisions) if d.is_keyframe]
    assert kf == [0, 4, 8]                                     # 12 deg > 10 deg, 9 deg is not
    assert decisions[4].reason == 'rotation' and decisions[4].rotation_deg == pytest.approx(12.0)


def test_keyframe_frame_count_fallback_and_disabled_thresholds():
    sel = KeyframeSelector(translation=0.1, rotation_deg=10.0, max_interval=5)
    kf = [i for i in range(12) if sel.decide(pose(x=0.001 * i)).is_keyframe]
    assert kf == [0, 5, 10]
    # thresholds of 0 disable baseline/rotation: only the paper's fixed spacing remains
    sel = KeyframeSelector(translation=0.0, rotation_deg=0.0, max_interval=5)
    kf = [i for i in range(12) if sel.decide(pose(x=0.5 * i, yaw_deg=20 * i)).is_keyframe]
    assert kf == [0, 5, 10]
    sel.reset()
    assert sel.decide(pose(x=0.5)).reason == 'first'


def test_estimator_uses_the_keyframe_rules():
    est = Estimator(small_config(keyframe_translation=0.1, keyframe_max_interval=100))
    outs = push_all(est, sideways(9))                          # 0.03 m per frame: keyframes 0, 4, 8
    assert est.status.keyframes == 3
    assert [i for i, o in enumerate(outs) if o is not None] == [4, 8]
    assert all(o.is_keyframe for o in outs if o is not None)


def test_window_selection_causal_and_centered():
    win = KeyframeWindow(5)

    def add(i):
        from dpv_sensor.stream.keyframes import Keyframe
        win.append(Keyframe(index=i, frame_index=i, stamp=float(i), T_world_cam_44=np.eye(4), image_b3hw=None,
                            K_b33=None, input_size=(4, 4), input_K_33=np.eye(3)))

    add(0)
    assert win.select('causal') is None and win.select('centered') is None
    add(1)
    ref, srcs = win.select('causal')
    assert ref.index == 1 and [s.index for s in srcs] == [0]
    assert win.select('centered') is None
    add(2)
    ref, srcs = win.select('centered')
    assert ref.index == 0 and [s.index for s in srcs] == [1, 2]
    for i in range(3, 7):
        add(i)
    ref, srcs = win.select('causal')
    assert ref.index == 6 and [s.index for s in srcs] == [2, 3, 4, 5]
    ref, srcs = win.select('centered')
    assert ref.index == 4 and [s.index for s in srcs] == [2, 3, 5, 6]


# ----------------------------------------------------------------------------------------------------
# latency and output geometry
# ----------------------------------------------------------------------------------------------------

def test_causal_and_centered_latency():
    frames = sideways(7)
    stamps = [f.stamp for f in frames]
    causal = push_all(Estimator(small_config(window_mode='causal')), frames)
    # causal: no output for the first keyframe (no stereo), then every keyframe at once, own stamp
    assert causal[0] is None
    assert [o.stamp for o in causal[1:]] == stamps[1:]
    centered = push_all(Estimator(small_config(window_mode='centered')), frames)
    # centered: the reference is two keyframes behind; the push of frame k returns frame k-2
    assert centered[0] is None and centered[1] is None
    assert [o.stamp for o in centered[2:]] == stamps[:-2]
    for o, f in zip(centered[2:], frames[:-2]):
        np.testing.assert_allclose(o.T_world_cam_44, f.T_world_cam_44)


@pytest.mark.parametrize('resolution', ['input', 'processing'])
def test_outputs_keep_stamp_size_and_scaled_K(resolution):
    w, h = 100, 60                                   # processing 64x48: anisotropic scaling 0.64 x 0.8
    frames = sideways(5, w=w, h=h)
    est = Estimator(small_config(output_resolution=resolution))
    outs = push_all(est, frames)
    K_in = frames[0].K_33
    for o, f in zip(outs[1:], frames[1:]):
        assert isinstance(o, DepthOutput) and o.stamp == f.stamp and o.is_keyframe
        if resolution == 'input':
            assert o.depth_hw.shape == (h, w) and o.confidence_hw.shape == (h, w)
            np.testing.assert_allclose(o.K_33, K_in)
        else:
            # processing_width wide with the input's aspect ratio: 64 x round(64 * 60 / 100) = 64 x 38
            assert o.depth_hw.shape == (38, 64) and o.confidence_hw.shape == (38, 64)
            sx, sy = 64 / w, 38 / h
            K = np.array(K_in)
            expected = np.array([[K[0, 0] * sx, 0, (K[0, 2] + 0.5) * sx - 0.5],
                                 [0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5], [0, 0, 1]])
            np.testing.assert_allclose(o.K_33, expected)
        assert o.depth_hw.dtype == np.float32 and o.confidence_hw.dtype == np.float32
        nan = np.isnan(o.depth_hw)
        assert np.all(o.confidence_hw[nan] == 0.0)
        assert np.all((o.confidence_hw >= 0) & (o.confidence_hw <= 1))
        assert (~nan).mean() > 0.5
        assert 'total' in o.timings_ms and 'measurement' in o.timings_ms


def test_plane_depth_is_recovered_and_unseen_pixels_are_nan():
    # camera moves right: the sources (to the left) never see the right image border at near depths
    frames = sideways(6, step=0.05, w=160, h=120)
    est = Estimator(small_config(num_planes=32, processing_width=128, processing_height=96))
    out = push_all(est, frames)[-1]
    d = out.depth_hw
    valid = np.isfinite(d)
    assert 0.7 < valid.mean() < 1.0
    rel = np.abs(d[valid] - PLANE_Z) / PLANE_Z
    assert np.median(rel) < 0.03
    # the missing pixels are on the side the sources cannot see: seen from the sources (further left),
    # points at the reference's right border project beyond their right border
    cols_missing = (~valid).mean(0)
    assert cols_missing[-5:].mean() > 0.5 and cols_missing[:5].mean() == 0.0


# ----------------------------------------------------------------------------------------------------
# accuracy on the procedural renderer
# ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize('seed,mode', [(2, 'centered'), (7, 'centered'), (2, 'causal')])
def test_classical_estimator_beats_constant_depth_on_rendered_sequence(seed, mode):
    """Rooms with textured walls (the NCC plane sweep needs texture), keyframes every 10 cm; the baseline
    is the best constant depth per frame (the GT median: an oracle). Seeds chosen for rooms with depth
    structure (a camera facing one flat wall makes the constant nearly perfect)."""
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(seed=seed, num_frames=60, width=160, height=120, plain_wall_prob=0.0)
    cfg = EstimatorConfig(measurement='classical', processing_width=160, processing_height=120, num_planes=32,
                          keyframe_translation=0.1, keyframe_rotation_deg=0.0, keyframe_max_interval=100,
                          window_mode=mode)
    records, status = run_sequence(seq, cfg, EvalOptions(progress=False), keep_images=False)
    acc = score_records(records, min_depth=status.depth_range[0], max_depth=status.depth_range[1])
    assert len(acc.rows) >= 3
    baseline = []
    for row in acc.rows:
        gt = seq.depth(row['index'])
        m = (gt >= 0.3) & (gt <= 8.0)
        baseline.append(np.mean(np.abs(np.median(gt[m]) - gt[m]) / gt[m]))
    summary = acc.summary()
    abs_rel = summary['metric']['frame_mean']['abs_rel']
    assert abs_rel < 0.7 * float(np.mean(baseline)), (abs_rel, np.mean(baseline))
    assert summary['coverage']['frame_mean'] > 0.8
    assert status.measurement == 'classical'


# ----------------------------------------------------------------------------------------------------
# measurement model selection
# ----------------------------------------------------------------------------------------------------

def test_missing_weights_fall_back_to_classical(tmp_path):
    path = tmp_path / 'nothing_here.safetensors'
    est = Estimator(small_config(measurement='auto', weights=str(path), filter_mode='knet'))
    st = est.status
    assert st.measurement == 'classical'
    assert 'fallback' in st.measurement_reason and str(path) in st.measurement_reason
    assert 'not found' in st.measurement_reason
    assert st.filter_mode == 'global' and any('knet' in n for n in st.notes)
    assert st.depth_readout == 'mean'                       # 'auto' with the classical model
    assert push_all(est, sideways(3))[-1] is not None


def test_corrupt_weights_fall_back_to_classical(tmp_path):
    from dpv_sensor.core.nets import DPVNet, save_checkpoint
    torch.manual_seed(0)
    path = tmp_path / 'lite.safetensors'
    save_checkpoint(path, DPVNet('lite'), {'training_data': 'none (test)'})
    est = Estimator(small_config(measurement='auto', weights=str(path)))
    assert est.status.measurement == 'network' and est.status.weights == str(path)
    data = bytearray(path.read_bytes())
    data[-100] ^= 0xFF                                         # flip bits in the tensor data
    path.write_bytes(bytes(data))
    est = Estimator(small_config(measurement='auto', weights=str(path)))
    st = est.status
    assert st.measurement == 'classical'
    assert 'CheckpointError' in st.measurement_reason and 'checksum' in st.measurement_reason
    path.write_bytes(b'not a checkpoint at all')
    assert 'not a safetensors file' in Estimator(small_config(measurement='auto', weights=str(path))
                                                 ).status.measurement_reason


def test_depth_readout_is_applied_and_checked():
    """The same sequence read out with 'mean' and with 'median': different depth maps, and an unknown
    readout is refused naming the field."""
    outs = {r: push_all(Estimator(small_config(measurement='classical', depth_readout=r)), sideways(4))[-1]
            for r in ('mean', 'median')}
    a, b = outs['mean'].depth_hw, outs['median'].depth_hw
    both = np.isfinite(a) & np.isfinite(b)
    assert both.mean() > 0.5 and np.abs(a[both] - b[both]).max() > 1e-3
    with pytest.raises(ValueError, match='depth_readout'):
        small_config(depth_readout='mode').validate()


def test_confidence_definition_is_applied_and_checked():
    """confidence='plane' publishes the +-1-plane mass, 'ratio' the delta-band probability (the default):
    same depth, different confidence images; ratio 1.5 is more lenient than 1.25; bad values are refused."""
    outs = {c: push_all(Estimator(small_config(confidence=c, confidence_ratio=r)), sideways(4))[-1]
            for c, r in (('plane', 1.25), ('ratio', 1.25), ('ratio', 1.5))}
    assert EstimatorConfig().confidence == 'ratio' and EstimatorConfig().confidence_ratio == 1.25
    np.testing.assert_array_equal(outs['plane'].depth_hw, outs['ratio'].depth_hw)
    ok = np.isfinite(outs['plane'].depth_hw)
    assert np.abs(outs['plane'].confidence_hw[ok] - outs['ratio'].confidence_hw[ok]).max() > 1e-3
    est = Estimator(small_config(confidence='ratio', confidence_ratio=1.5))
    assert est.status.confidence == 'ratio 1.5'
    wider = push_all(est, sideways(4))[-1]
    assert (wider.confidence_hw[ok] >= outs['ratio'].confidence_hw[ok] - 1e-6).all()
    with pytest.raises(ValueError, match='confidence'):
        small_config(confidence='entropy').validate()
    with pytest.raises(ValueError, match='confidence_ratio'):
        small_config(confidence_ratio=1.0).validate()


def test_min_confidence_masks_depth_and_keeps_confidence():
    """The node parameter min_confidence is applied by the estimator, so offline evaluation scores what
    the node publishes: depth below it is NaN (no estimate), its confidence is still reported."""
    full = push_all(Estimator(small_config()), sideways(4))[-1]
    thr = float(np.quantile(full.confidence_hw[np.isfinite(full.depth_hw)], 0.5))
    cut = push_all(Estimator(small_config(min_confidence=thr)), sideways(4))[-1]
    low = np.isfinite(full.depth_hw) & (full.confidence_hw < thr)
    assert low.mean() > 0.1
    assert np.isnan(cut.depth_hw[low]).all()
    np.testing.assert_array_equal(cut.confidence_hw, full.confidence_hw)
    keep = np.isfinite(full.depth_hw) & ~low
    np.testing.assert_array_equal(cut.depth_hw[keep], full.depth_hw[keep])
    with pytest.raises(ValueError, match='min_confidence'):
        small_config(min_confidence=1.5).validate()


def test_measurement_network_without_weights_is_an_error(tmp_path):
    from dpv_sensor.core.nets import CheckpointError
    with pytest.raises(CheckpointError, match='not found'):
        Estimator(small_config(measurement='network', weights=str(tmp_path / 'missing.safetensors')))


def test_network_measurement_caches_features_and_uses_knet():
    from dpv_sensor.core.nets import DPVNet
    torch.manual_seed(0)
    net = DPVNet('lite')
    calls = []
    original = net.extract_features
    net.extract_features = lambda img: (calls.append(tuple(img.shape)), original(img))[1]
    est = Estimator(small_config(measurement='auto', filter_mode='knet', output_resolution='processing'), model=net)
    assert est.status.measurement == 'network' and est.status.filter_mode == 'knet'
    assert est.status.depth_readout == 'relative'           # 'auto' with the network
    outs = push_all(est, sideways(5))
    # every keyframe's image went through the feature extractor exactly once (sources reuse the cache)
    assert len(calls) == 5 and all(c == (1, 3, 48, 64) for c in calls)
    for o in outs[1:]:
        assert o.depth_hw.shape == (48, 64) and np.isfinite(o.depth_hw).mean() > 0.5
        assert 'refine' in o.timings_ms
        d = o.depth_hw[np.isfinite(o.depth_hw)]
        assert np.all((d >= net.d_min - 1e-4) & (d <= net.d_max + 1e-4))
    assert est.status.depth_range == (net.d_min, net.d_max)


@pytest.mark.parametrize('precision', ['bfloat16', 'auto'])
def test_cpu_bfloat16_gives_the_float32_depths(precision):
    """cpu_precision: the shipped lite weights under CPU bfloat16 autocast publish the float32 depths to
    within a fraction of a plane (the cost volume, filter and readout stay float32), and the status says
    which precision ran; 'auto' is bfloat16 exactly where the CPU has native kernels."""
    from conftest import cpu_native_bf16
    from dpv_sensor.core.nets import default_weights_path, load_checkpoint
    net, _ = load_checkpoint(default_weights_path('lite'), preset='lite')
    frames = sideways(6, step=0.05, w=160, h=120)
    outs, status = {}, {}
    for p in ('float32', precision):
        est = Estimator(small_config(measurement='network', filter_mode='knet', processing_width=128,
                                     processing_height=96, cpu_precision=p), model=net)
        outs[p] = push_all(est, frames)[-1]
        status[p] = est.status.precision
    assert status['float32'] == 'float32'
    native = cpu_native_bf16()            # from the CPU's flags, not from the code that chooses
    if precision == 'auto' and native is None:
        pytest.skip("this system does not show its CPU's flags")
    bf16 = precision == 'bfloat16' or native
    assert status[precision].startswith('bfloat16 autocast') == bf16
    a, b = outs['float32'].depth_hw, outs[precision].depth_hw
    both = np.isfinite(a) & np.isfinite(b)
    assert both.mean() > 0.8
    rel = np.abs(a[both] - b[both]) / a[both]
    if bf16:
        assert rel.max() > 0                                     # autocast really ran
    assert np.median(rel) < 0.01 and np.mean(rel > 0.05) < 0.02
    with pytest.raises(ValueError, match='cpu_precision'):
        Estimator(small_config(cpu_precision='float16'))


# ----------------------------------------------------------------------------------------------------
# drops and resets
# ----------------------------------------------------------------------------------------------------

def test_nan_pose_is_dropped():
    est = Estimator(small_config())
    frames = sideways(4)
    assert est.push(frames[0]) is None
    bad = Frame(stamp=frames[1].stamp, image=frames[1].image, K_33=frames[1].K_33,
                T_world_cam_44=np.full((4, 4), np.nan))
    assert est.push(bad) is None
    st = est.status
    assert st.frames_dropped == 1 and 'not finite' in st.last_drop_reason and st.resets == 0
    none_pose = Frame(stamp=0.04, image=frames[1].image, K_33=frames[1].K_33, T_world_cam_44=None)
    assert est.push(none_pose) is None and 'no pose' in est.status.last_drop_reason
    out = est.push(frames[2])                                  # the stream goes on: keyframes 0 and 2
    assert out is not None and out.reset_reason in (None, 'first frame') and est.status.resets == 0


def test_time_going_backwards_resets():
    est = Estimator(small_config())
    outs = push_all(est, sideways(4))
    assert outs[-1] is not None and est.status.resets == 0
    back = frame_at(0, pose(x=0.12), stamp=0.01)
    assert est.push(back) is None                              # first keyframe of the new stream
    st = est.status
    assert st.resets == 1 and 'backwards' in st.last_reset_reason
    assert st.keyframes_in_window == 1
    out = est.push(frame_at(0, pose(x=0.15), stamp=0.05))
    assert out is not None and 'backwards' in out.reset_reason
    out = est.push(frame_at(0, pose(x=0.18), stamp=0.09))
    assert out is not None and out.reset_reason is None


def test_time_gap_and_pose_jump_reset():
    est = Estimator(small_config(reset_time_gap=0.5))
    push_all(est, sideways(3))
    est.push(frame_at(0, pose(x=0.09), stamp=2.0))
    assert est.status.resets == 1 and 'time gap' in est.status.last_reset_reason
    est.push(frame_at(0, pose(x=1.0), stamp=2.03))
    assert est.status.resets == 2 and 'teleported' in est.status.last_reset_reason
    assert est.push(frame_at(0, pose(x=1.0), stamp=2.03)) is None   # duplicate stamp: dropped, no reset
    assert est.status.resets == 2 and 'duplicate' in est.status.last_drop_reason


def smooth_path(t):
    """A continuous camera path: 0.4 m/s sideways, a slow sway in y, turning 8 deg/s."""
    return pose(x=0.4 * t, y=0.05 * math.sin(t), yaw_deg=8.0 * t)


def sparse_stream(n_pushed=5, every=100, rate=30.0, **kw):
    """Every `every`-th frame of a 30 Hz stream along `smooth_path` (the others were dropped by the caller):
    pushed frames 3.33 s and 1.33 m / 27 deg apart, each saying the sensor gap was one frame (1/30 s)."""
    frames = []
    for k in range(n_pushed):
        t = k * every / rate
        f = frame_at(0, smooth_path(t), stamp=t, **kw)
        f.sensor_gap_s = 1.0 / rate if k else None
        frames.append(f)
    return frames


def test_deliberate_drops_do_not_reset():
    """Keyframes seconds and metres apart, along a continuous path, with a camera stream that never stalled:
    neither the stream rules nor the filter restart (defaults: 1 s stream gap, 10 m/s and 720 deg/s teleports),
    so the filter fuses every keyframe into the previous belief."""
    frames = sparse_stream()
    dt, dr = pose_delta(frames[0].T_world_cam_44, frames[1].T_world_cam_44)
    assert frames[1].stamp - frames[0].stamp > 3.0 and dt > 1.3 and 25 < dr < 45
    cfg = small_config()
    assert (cfg.reset_time_gap, cfg.odom_max_speed, cfg.odom_max_rate_deg) == (1.0, 10.0, 720.0)
    est = Estimator(cfg)
    predictions = []
    step = est.filter.step
    est.filter.step = lambda *a, **kw: (lambda r: (predictions.append(r.predicted_logp_bdhw is not None), r)[1])(
        step(*a, **kw))
    outs = push_all(est, frames)
    assert est.status.resets == 0 and est.status.last_reset_reason is None
    assert all(o is not None for o in outs[1:])
    assert outs[1].reset_reason == 'first frame'                # the filter's start, not a restart
    assert [o.reset_reason for o in outs[2:]] == [None] * (len(frames) - 2)
    assert predictions == [False] + [True] * (len(frames) - 2)  # every later keyframe was predicted and fused


def pan(t):
    """A smooth pan at 90 deg/s (about the vertical axis, camera centre fixed)."""
    return pose(yaw_deg=90.0 * t)


def walk(t):
    """A smooth walk at 1.5 m/s (sideways), looking at the textured plane."""
    return pose(x=1.5 * t)


@pytest.mark.parametrize('path', [pan, walk], ids=['pan_90deg_s', 'walk_1.5m_s'])
@pytest.mark.parametrize('spacing', [0.1, 0.5, 1.5])
def test_fast_smooth_motion_with_frames_far_apart_does_not_reset(path, spacing):
    """Frames pushed 0.1-1.5 s apart (a busy node drops the rest) along fast but continuous motion, the camera
    stream itself continuous (sensor_gap_s one 30 Hz frame): no rule restarts anything, whatever the window."""
    for mode in ('causal', 'centered'):
        est = Estimator(small_config(window_mode=mode))
        frames = []
        for k in range(5):
            f = frame_at(0, path(k * spacing), stamp=k * spacing)
            f.sensor_gap_s = 1 / 30.0 if k else None
            frames.append(f)
        step = pose_delta(frames[0].T_world_cam_44, frames[1].T_world_cam_44)
        assert step[0 if path is walk else 1] == pytest.approx((1.5 if path is walk else 90.0) * spacing)
        outs = [o for o in push_all(est, frames) if o is not None]
        assert est.status.resets == 0, (mode, est.status.last_reset_reason)
        assert outs and all(o.reset_reason in (None, 'first frame') for o in outs)


def test_offline_pose_step_of_half_a_metre_resets():
    """Offline (poses pushed with the frames, no pose buffer): a 0.5 m step between consecutive 30 Hz frames is
    15 m/s, a teleport by the pose buffer's rule; the estimator restarts, through the pipeline too."""
    frames = sideways(3)
    frames.append(frame_at(3, frames[2].T_world_cam_44 @ pose(x=0.5)))
    for f in frames[1:]:
        f.sensor_gap_s = 1 / 30.0
    est = Estimator(small_config())
    outs = push_all(est, frames)
    assert est.status.resets == 1
    assert est.status.last_reset_reason.startswith('pose teleported: 0.500 m in 0.033 s (15.0 m/s > '
                                                      'odom_max_speed 10 m/s)')
    assert outs[3] is None                                      # first keyframe of the restarted stream
    from dpv_sensor.stream.pipeline import Pipeline
    pipe = Pipeline(small_config())
    for f in frames:
        f.sensor_gap_s = None
        pipe.push(f)
    assert pipe.estimator.status.resets == 1 and 'teleported' in pipe.estimator.status.last_reset_reason


def test_without_sensor_gap_the_time_since_the_previous_frame_counts():
    """Offline use (sensor_gap_s None): the same sparse frames look like a stalled stream and reset."""
    frames = sparse_stream(n_pushed=3)
    for f in frames:
        f.sensor_gap_s = None
    est = Estimator(small_config())
    push_all(est, frames)
    st = est.status
    assert st.resets == 2 and st.last_reset_reason.startswith('time gap 3.333 s since the previous frame')


def test_real_sensor_gap_resets():
    frames = sparse_stream(n_pushed=3)
    frames[2].sensor_gap_s = 1.5                                # the camera delivered nothing for 1.5 s
    est = Estimator(small_config())
    outs = push_all(est, frames)
    st = est.status
    assert st.resets == 1
    assert 'time gap 1.500 s in the camera stream > reset_time_gap 1 s' in st.last_reset_reason
    assert outs[2] is None                                      # first keyframe of the restarted stream
    assert est.push(frame_at(0, smooth_path(7.0), stamp=7.0)).reset_reason.startswith('time gap')


@pytest.mark.parametrize('extra,words', [
    (pose(x=40.0), 'm/s'),                                      # 40 m in 3.33 s: 12 m/s, faster than 10 m/s
])
def test_teleport_resets_even_between_distant_frames(extra, words):
    frames = sparse_stream(n_pushed=3)
    jump = frame_at(0, frames[2].T_world_cam_44 @ extra, stamp=frames[2].stamp)
    jump.sensor_gap_s = 1 / 30.0
    dt, dr = pose_delta(frames[1].T_world_cam_44, jump.T_world_cam_44)
    assert dt > 34.0
    est = Estimator(small_config())
    push_all(est, frames[:2] + [jump])
    assert est.status.resets == 1 and words in est.status.last_reset_reason
    assert 'odom_max_speed 10 m/s' in est.status.last_reset_reason


def test_teleport_between_consecutive_frames_resets():
    """Between 30 Hz frames a teleport is a step over 0.1 m faster than 10 m/s (0.33 m) or over 10 deg faster than
    720 deg/s (24 deg); smaller steps are motion."""
    for T, resets in ((pose(x=0.5), 1), (pose(x=0.03, yaw_deg=30.0), 1), (pose(x=0.3), 0), (pose(yaw_deg=20.0), 0)):
        est = Estimator(small_config())
        frames = sideways(2)
        frames.append(frame_at(2, frames[1].T_world_cam_44 @ T))
        frames[2].sensor_gap_s = 1 / 30.0
        push_all(est, frames)
        assert est.status.resets == resets, (T, est.status.last_reset_reason)
        if resets:
            assert 'teleported' in est.status.last_reset_reason


def test_invalid_sensor_gap_is_an_error():
    f = sideways(1)[0]
    f.sensor_gap_s = -0.1
    with pytest.raises(ValueError, match='sensor_gap_s'):
        Estimator(small_config()).push(f)


def test_image_size_change_resets():
    est = Estimator(small_config())
    outs = push_all(est, sideways(3, w=80, h=60))
    assert outs[-1].depth_hw.shape == (60, 80)
    bigger = [frame_at(i, pose(x=0.03 * i), w=96, h=72) for i in range(3, 6)]
    outs = push_all(est, bigger)
    st = est.status
    assert st.resets == 1 and 'image size changed from 80x60 to 96x72' in st.last_reset_reason
    assert outs[0] is None                                     # new first keyframe
    assert outs[1].depth_hw.shape == (72, 96) and 'size' in outs[1].reset_reason


def test_explicit_reset():
    est = Estimator(small_config())
    push_all(est, sideways(3))
    est.reset('operator request')
    assert est.status.resets == 1 and est.status.keyframes_in_window == 0
    assert est.push(frame_at(3, pose(x=0.09))) is None


# ----------------------------------------------------------------------------------------------------
# frames between keyframes
# ----------------------------------------------------------------------------------------------------

def test_publish_between_keyframes():
    frames = sideways(9, step=0.02, w=80, h=60)
    cfg = small_config(keyframe_max_interval=3, num_planes=32)
    quiet = push_all(Estimator(cfg), frames)
    assert [i for i, o in enumerate(quiet) if o is not None] == [3, 6]
    cfg.publish_between_keyframes = True
    est = Estimator(cfg)
    outs = push_all(est, frames)
    # frames 1, 2 come before the first output (no filter state yet), afterwards every frame has one
    assert [i for i, o in enumerate(outs) if o is not None] == [3, 4, 5, 6, 7, 8]
    for i in (4, 5, 7, 8):
        o = outs[i]
        assert not o.is_keyframe and o.stamp == frames[i].stamp
        np.testing.assert_allclose(o.T_world_cam_44, frames[i].T_world_cam_44)
        assert o.depth_hw.shape == (60, 80) and 'between' in o.timings_ms
        valid = np.isfinite(o.depth_hw)
        assert valid.mean() > 0.5 and np.all(o.confidence_hw[~valid] == 0)
        # the warped posterior still says "a plane at 2 m"; its accuracy matches the keyframe's
        kf_err = np.nanmedian(np.abs(outs[3 * (i // 3)].depth_hw - PLANE_Z))
        assert np.nanmedian(np.abs(o.depth_hw - PLANE_Z)) < max(1.5 * kf_err, 0.1)
    assert all(outs[i].is_keyframe for i in (3, 6))
    # centered windows would publish out of order: there between-keyframe outputs are off (noted)
    est = Estimator(small_config(keyframe_max_interval=3, publish_between_keyframes=True, window_mode='centered'))
    outs = push_all(est, frames)
    assert all(o.is_keyframe for o in outs if o is not None)
    assert any('publish_between_keyframes' in n for n in est.status.notes)


# ----------------------------------------------------------------------------------------------------
# pose refinement hook
# ----------------------------------------------------------------------------------------------------

def test_pose_refiner_hook_gets_the_window_and_its_poses_are_used():
    requests = []
    nudge = pose(y=0.001)

    def refiner(req: PoseRefinementRequest):
        requests.append(req)
        return [kf.T_world_cam_44 @ nudge for kf in req.keyframes]

    est = Estimator(small_config(pose_refinement='window'), pose_refiner=refiner)
    frames = sideways(4)
    outs = push_all(est, frames)
    assert len(requests) == 3                                  # one per window (keyframes 1, 2, 3)
    first, last = requests[0], requests[-1]
    assert len(first.keyframes) == 2 and first.reference == 1 and first.depth_hw is None
    assert len(last.keyframes) == 4 and last.reference == 3
    assert last.depth_hw is not None and last.depth_hw.shape == last.confidence_hw.shape == (12, 16)
    assert last.K_depth_33.shape == (3, 3)
    # the output carries the refined reference pose; the odometry pose is kept on the keyframe
    ref = last.keyframes[last.reference]
    np.testing.assert_allclose(outs[-1].T_world_cam_44, ref.T_world_cam_44)
    np.testing.assert_allclose(ref.odom_T_world_cam_44, frames[3].T_world_cam_44)
    assert not np.allclose(ref.T_world_cam_44, ref.odom_T_world_cam_44)
    assert est.status.pose_refiner is True


def test_a_refiner_that_reads_only_the_median_gets_every_second_pixel_of_the_predicted_depth():
    """``predicted_depth_stride``: the estimator predicts the reference's depth only at every stride-th volume pixel,
    with the intrinsics of that grid; the window refiner asks for 2 without photometric factors, 1 with them."""
    from dpv_sensor.stream.window_refiner import PoseRefinerConfig, WindowPoseRefiner
    assert WindowPoseRefiner(PoseRefinerConfig(max_sources=0)).predicted_depth_stride == 2
    assert WindowPoseRefiner(PoseRefinerConfig(max_sources=2)).predicted_depth_stride == 1
    class Recorder:
        def __init__(self, stride):
            self.predicted_depth_stride, self.requests = stride, []

        def __call__(self, req: PoseRefinementRequest):
            self.requests.append(req)
            return None                                        # keep the poses

    requests = {}
    for stride in (1, 2):
        hook = Recorder(stride)
        push_all(Estimator(small_config(pose_refinement='window'), pose_refiner=hook), sideways(4))
        requests[stride] = hook.requests
    full, half = requests[1][-1], requests[2][-1]
    assert full.depth_hw.shape == (12, 16) and half.depth_hw.shape == half.confidence_hw.shape == (6, 8)
    np.testing.assert_allclose(half.depth_hw.numpy(), full.depth_hw.numpy()[::2, ::2], rtol=1e-5)
    K_half = full.K_depth_33.copy()
    K_half[:2] /= 2
    np.testing.assert_allclose(half.K_depth_33, K_half)


def test_new_keyframes_start_from_the_refined_trajectory_and_tracking_loss_restarts():
    offset = pose(y=0.02)

    class Refiner:
        def __init__(self):
            self.seen = []                 # (reference pose before refinement, its odometry pose) per call
            self.tracking_lost = False
            self.last_result = None
            self.resets = 0

        def __call__(self, req):
            ref = req.keyframes[req.reference]
            self.seen.append((ref.T_world_cam_44.copy(), ref.odom_T_world_cam_44.copy()))
            self.tracking_lost = len(self.seen) == 3
            self.last_result = type('R', (), {'reason': 'alignment diverged'})()
            return [offset @ kf.odom_T_world_cam_44 for kf in req.keyframes]   # refined = odometry + 2 cm in y

        def reset(self):
            self.resets += 1

    refiner = Refiner()
    est = Estimator(small_config(odometry='none'), pose_refiner=refiner)      # visual odometry: a loss restarts
    frames = sideways(6)
    outs = push_all(est, frames)
    # call 1 (keyframe 1): keyframe 0 was never refined -> keyframe 1 starts at its odometry pose;
    # call 2 (keyframe 2): starts from keyframe 1's refined pose chained with the odometry motion
    np.testing.assert_allclose(refiner.seen[0][0], refiner.seen[0][1])
    np.testing.assert_allclose(refiner.seen[1][0], offset @ refiner.seen[1][1], atol=1e-12)
    np.testing.assert_allclose(outs[1].T_world_cam_44, offset @ frames[1].T_world_cam_44, atol=1e-12)
    # call 3 reports lost tracking: no output for keyframe 3, the filter restarts, the next output says why
    assert outs[3] is None
    assert est.status.resets == 1 and 'lost tracking' in est.status.last_reset_reason
    assert outs[4] is not None and 'alignment diverged' in outs[4].reset_reason
    assert outs[5].reset_reason is None
    est.reset('test')
    assert refiner.resets == 1
    assert est.status.pose_refinement_fallbacks == 0

    # odometry from a topic: the failed refinement falls back to the odometry for that keyframe, nothing restarts
    refiner = Refiner()
    est = Estimator(small_config(odometry='topic'), pose_refiner=refiner)
    outs = push_all(est, frames)
    assert outs[3] is not None and outs[3].reset_reason is None
    assert est.status.resets == 0 and est.status.pose_refinement_fallbacks == 1
    assert est.status.last_pose_refinement_fallback_reason == 'alignment diverged'
    assert all(o.reset_reason is None for o in outs[2:])


def test_refiner_that_keeps_the_odometry_is_counted_as_a_fallback():
    """A refiner that skipped a window (the camera turns in place) keeps tracking; the estimator counts it."""
    class Refiner:
        tracking_lost = False

        def __init__(self):
            self.last_result = None

        def __call__(self, req):
            self.last_result = type('R', (), {'skipped': 'turning in place: test', 'reason': None})()
            return [kf.odom_T_world_cam_44 for kf in req.keyframes]

    est = Estimator(small_config(), pose_refiner=Refiner())
    outs = push_all(est, sideways(4))
    assert est.status.resets == 0 and all(o is not None for o in outs[1:])
    assert est.status.pose_refinement_fallbacks == 3           # one per window (keyframes 1, 2, 3)
    assert est.status.last_pose_refinement_fallback_reason == 'turning in place: test'


def test_pose_refinement_requested_without_refiner_is_noted():
    est = Estimator(small_config(pose_refinement='window'))
    assert any('no pose refiner' in n for n in est.status.notes)


def test_run_sequence_records_and_scores():
    from dpv_sensor.data.sequence import Sequence
    frames = sideways(5, step=0.05, w=160, h=120)
    depths = [render(f.T_world_cam_44, f.K_33, 160, 120)[1] for f in frames]
    seq = Sequence.from_arrays([f.image for f in frames], depths, np.stack([f.T_world_cam_44 for f in frames]),
                               frames[0].K_33, stamps=[f.stamp for f in frames])
    cfg = small_config(num_planes=32, processing_width=128, processing_height=96)
    records, status = run_sequence(seq, cfg, EvalOptions(progress=False))
    rows = score_records(records, min_depth=status.depth_range[0], max_depth=status.depth_range[1]).rows
    assert [r['index'] for r in rows] == [1, 2, 3, 4]
    assert [r.stamp for r in records] == [f.stamp for f in frames[1:]]
    assert rows[-1]['abs_rel'] < 0.05 and rows[-1]['coverage'] > 0.8
    assert status.keyframes == 5
    # pose_source 'noisy': the estimator sees odometry-like poses (the depth is still scored against the GT)
    from dpv_sensor.data.trajectory import corrupt_trajectory
    noisy = corrupt_trajectory([seq.pose(i) for i in range(len(seq))], trans_noise_rel=0.5, rot_noise_deg=2.0, seed=1)
    options = EvalOptions(progress=False, pose_source='noisy', pose_noise=(0.5, 2.0), seed=1)
    # without the refinement window, which would correct part of the noise from the images
    cfg_off = small_config(num_planes=32, processing_width=128, processing_height=96, pose_refinement='off')
    bad_records, _ = run_sequence(seq, cfg_off, options)
    np.testing.assert_allclose(bad_records[-1].T_world_cam_44, noisy[-1])
    bad = score_records(bad_records, min_depth=status.depth_range[0], max_depth=status.depth_range[1]).rows
    assert bad[-1]['abs_rel'] > 2 * rows[-1]['abs_rel']


# ----------------------------------------------------------------------------------------------------
# devices
# ----------------------------------------------------------------------------------------------------

@pytest.mark.skipif(torch.cuda.is_available(), reason='this machine has CUDA')
def test_cuda_requested_without_cuda_is_a_clear_error():
    with pytest.raises(ValueError, match='CUDA is not available'):
        Estimator(small_config(device='cuda'))
    with pytest.raises(ValueError, match='not a torch device'):
        Estimator(small_config(device='gpu0'))


@pytest.mark.skipif(not torch.cuda.is_available(), reason='needs a CUDA device')
def test_cuda_matches_cpu():
    frames = sideways(5, step=0.05, w=160, h=120)
    outs = {}
    for dev in ('cpu', 'cuda'):
        est = Estimator(small_config(device=dev, num_planes=32, processing_width=128, processing_height=96))
        outs[dev] = push_all(est, frames)[-1]
        assert est.status.device.startswith(dev)
    a, b = outs['cpu'].depth_hw, outs['cuda'].depth_hw
    both = np.isfinite(a) & np.isfinite(b)
    assert both.mean() > 0.8 and np.isfinite(a).mean() == pytest.approx(np.isfinite(b).mean(), abs=0.02)
    assert np.median(np.abs(a[both] - b[both])) < 1e-3
    # the network under autocast (bfloat16) runs and gives depths in range
    from dpv_sensor.core.nets import DPVNet
    torch.manual_seed(0)
    est = Estimator(small_config(device='cuda', measurement='auto', filter_mode='knet'), model=DPVNet('lite'))
    out = push_all(est, sideways(4))[-1]
    assert out is not None and np.isfinite(out.depth_hw).mean() > 0.5


def test_output_size_keeps_the_input_aspect_ratio():
    from dpv_sensor.stream.estimator import output_size
    proc = small_config(processing_width=320, processing_height=256, output_resolution='processing')
    assert output_size(proc, (640, 480)) == (320, 240)          # not the 320x256 processing grid
    assert output_size(proc, (1280, 720)) == (320, 180)
    assert output_size(proc, (752, 480)) == (320, 204)          # 204.26 rounded
    assert output_size(small_config(output_resolution='input'), (640, 480)) == (640, 480)


# ----------------------------------------------------------------------------------------------------
# pose uncertainty
# ----------------------------------------------------------------------------------------------------

def _with_covariance(frames, var_per_frame):
    """The frames with an odometry pose covariance growing by ``var_per_frame`` per frame (integrated odometry)."""
    out = []
    for i, f in enumerate(frames):
        cov = np.eye(6) * (1e-9 + var_per_frame * i)
        out.append(Frame(stamp=f.stamp, image=f.image, K_33=f.K_33, T_world_cam_44=f.T_world_cam_44,
                         frame_id=f.frame_id, pose_covariance_66=cov))
    return out


def test_a_larger_odometry_covariance_never_raises_the_confidence_and_off_ignores_it():
    frames = sideways(6, step=0.05, w=160, h=120)
    means = []
    for var in (0.0, 1e-6, 1e-5, 1e-4):
        est = Estimator(small_config(num_planes=32, processing_width=128, processing_height=96))
        out = push_all(est, _with_covariance(frames, var))[-1]
        means.append(float(np.nanmean(out.confidence_hw)))
        st = est.status.pose_uncertainty
        # the covariance's growth between two keyframes (one frame apart) is the relative pose's; a constant one
        # (var 0) says nothing about the relative motion: without a twist covariance the poses count as exact
        if var:
            assert st['rot_deg_max'] == pytest.approx(math.degrees(math.sqrt(var * 4)), abs=2e-4)
        else:
            assert st['source'] == 'none (the pose covariance does not grow and there is no twist covariance)', st
    assert all(b <= a + 1e-6 for a, b in zip(means, means[1:]))
    assert means[-1] < means[0] - 0.05
    off = Estimator(small_config(num_planes=32, processing_width=128, processing_height=96, pose_uncertainty='off'))
    out_off = push_all(off, _with_covariance(frames, 1e-4))[-1]
    assert off.status.pose_uncertainty == {}
    assert float(np.nanmean(out_off.confidence_hw)) > means[-1]
    # drift: the odom_drift_* figures over the path (5 cm per keyframe, 4 sources back): never above exact poses
    drift = Estimator(small_config(num_planes=32, processing_width=128, processing_height=96,
                                   pose_uncertainty='drift', odom_time_sync_ms=0.0))
    push_all(drift, _with_covariance(frames, 1e-4))
    assert drift.status.pose_uncertainty['trans_mm_max'] == pytest.approx(1000 * 0.02 * 0.20 / math.sqrt(3),
                                                                            rel=1e-3)


def test_default_pose_uncertainty_reads_only_the_odometry_covariance():
    frames = sideways(6, step=0.05, w=160, h=120)
    cfg = dict(num_planes=32, processing_width=128, processing_height=96)
    assert small_config(**cfg).pose_uncertainty == 'covariance'
    plain = push_all(Estimator(small_config(**cfg)), frames)[-1]
    off = push_all(Estimator(small_config(pose_uncertainty='off', **cfg)), frames)[-1]
    np.testing.assert_array_equal(plain.confidence_hw, off.confidence_hw)      # no covariance: poses are exact
    np.testing.assert_array_equal(plain.depth_hw, off.depth_hw)
    drift = push_all(Estimator(small_config(pose_uncertainty='auto', **cfg)), frames)[-1]
    assert float(np.nanmean(drift.confidence_hw)) < float(np.nanmean(plain.confidence_hw))
    est = Estimator(small_config(**cfg))
    push_all(est, _with_covariance(frames, 1e-5))
    assert est.status.pose_uncertainty['source'] == 'covariance'
