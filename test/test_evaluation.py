"""The evaluation runner (dpv_sensor/evaluation/offline.py) and the `evaluate` tool, on tiny in-memory sequences."""
from __future__ import annotations

import csv
import json
import math

import cv2
import numpy as np
import pytest

from dpv_sensor.evaluation import offline as E
from dpv_sensor.data.sequence import Sequence

H, W = 30, 40


def _plane_depth(K, T_world_cam, n=np.array([0.15, -0.1, 1.0]), c=3.0):
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(H * W)])
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    return ((c - n @ t) / (n @ (R @ rays))).reshape(H, W).astype(np.float32)


def _plane_texture(K, T_world_cam, depth):
    """Grey level of the textured plane seen at each pixel: a fixed pattern of the world point's x and y, so that
    all frames agree (what a plane sweep needs to find the depth)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(H * W)])
    X = T_world_cam[:3, :3] @ (rays * depth.ravel()) + T_world_cam[:3, 3:4]
    x, y = X[0], X[1]
    g = (128 + 50 * np.sin(9.0 * x + 2.0 * y) + 40 * np.sin(3.0 * x - 11.0 * y + 1.0)
         + 30 * np.sign(np.sin(5.0 * x * y + 4 * x)))
    return np.clip(g, 0, 255).reshape(H, W)


def _gt_sequence(n=6, stamp0=10.0, rendered=False):
    """A camera moving past a slanted plane: GT depth exact; images are per-frame noise, or with ``rendered`` the
    plane's texture as each camera sees it."""
    K = np.array([[35.0, 0, (W - 1) / 2], [0, 35.0, (H - 1) / 2], [0, 0, 1]])
    rng = np.random.default_rng(0)
    poses, depths, images = [], [], []
    for i in range(n):
        T = np.eye(4)
        T[:3, 3] = [0.04 * i, -0.01 * i, 0.03 * i]
        poses.append(T)
        d = _plane_depth(K, T)
        if rendered:
            images.append(np.repeat(_plane_texture(K, T, d)[..., None], 3, axis=2).astype(np.uint8))
        else:
            # a smooth random texture (pixel noise would be rejected as a degenerate frame)
            images.append(cv2.resize(rng.integers(0, 255, (H // 4 + 1, W // 4 + 1, 3), dtype=np.uint8), (W, H),
                                     interpolation=cv2.INTER_LINEAR))
        d[0, :5] = 0.0                      # a few invalid GT pixels
        depths.append(d)
    stamps = stamp0 + np.arange(n) / 10.0
    return Sequence.from_arrays(images, depths, np.stack(poses), K, stamps, name='plane')


def _records(seq, scale=1.0, conf=True):
    recs = []
    for i in range(len(seq)):
        gt = seq.depth(i)
        pred = np.where(gt > 0, gt * scale, np.nan).astype(np.float32)
        c = None
        if conf:
            c = np.linspace(0, 1, gt.size, dtype=np.float32).reshape(gt.shape)
        recs.append(E.KeyframeRecord(index=i, stamp=seq.stamp(i), depth_hw=pred, confidence_hw=c, K_33=seq.K,
                                     gt_depth_hw=gt, gt_T_world_cam_44=seq.pose(i), T_world_cam_44=seq.pose(i),
                                     image_hw3=seq.image(i), reset_reason='first frame' if i == 0 else None,
                                     time_ms=10.0 + i))
    return recs


# ---------------------------------------------------------------------------------------------
# configuration parsing
# ---------------------------------------------------------------------------------------------

def test_parse_overrides_types_and_errors():
    ov = E.parse_overrides(['filter_mode=global', 'damping=0.5', 'num_planes=32', 'publish_between_keyframes=true',
                            'pose_source=noisy', 'min_coverage=0.3'])
    assert ov == {'filter_mode': 'global', 'damping': 0.5, 'num_planes': 32, 'publish_between_keyframes': True,
                  'pose_source': 'noisy', 'min_coverage': 0.3}
    assert isinstance(ov['num_planes'], int)
    with pytest.raises(ValueError, match='unknown configuration key'):
        E.parse_overrides(['no_such_key=1'])
    with pytest.raises(ValueError, match='key=value'):
        E.parse_overrides(['filter_mode'])
    cfg, values = E.build_config(ov)
    assert cfg.filter_mode == 'global' and cfg.num_planes == 32 and cfg.min_coverage == 0.3
    with pytest.raises(ValueError, match='filter_mode'):
        E.build_config({'filter_mode': 'kalman'})


def test_variants_are_the_cartesian_product():
    v = E.variants_from_specs(['filter_mode=none,global', 'pose_source=gt,noisy'])
    assert v == [{'filter_mode': 'none', 'pose_source': 'gt'}, {'filter_mode': 'none', 'pose_source': 'noisy'},
                 {'filter_mode': 'global', 'pose_source': 'gt'}, {'filter_mode': 'global', 'pose_source': 'noisy'}]
    assert E.variants_from_specs([]) == [{}]
    assert E.variants_from_specs(['num_planes=16,32']) == [{'num_planes': 16}, {'num_planes': 32}]


# ---------------------------------------------------------------------------------------------
# scoring and reports
# ---------------------------------------------------------------------------------------------

def test_score_exact_records_and_report_files(tmp_path):
    seq = _gt_sequence()
    recs = _records(seq)
    acc = E.score_records(recs)
    s = E.summarize(acc, recs, configuration={'test': True})
    assert s['metric']['frame_mean']['abs_rel'] == pytest.approx(0.0, abs=1e-7)
    assert s['metric']['frame_mean']['delta1'] == 1.0
    assert s['coverage']['frame_mean'] == 1.0
    # exact depth of a translating camera: consecutive keyframes agree (first frame has no predecessor)
    assert s['temporal_consistency']['num_pairs'] == len(seq) - 1
    assert s['temporal_consistency']['pair_mean'] < 1e-4
    assert s['num_resets'] == 1 and s['time_ms_per_keyframe']['mean'] == pytest.approx(12.5)
    assert math.isnan(acc.rows[0]['temporal']) and acc.rows[1]['temporal_pixels'] > 0.5 * H * W
    files = E.write_report(tmp_path, acc, recs, s, montage_frames=3, title='exact')
    for key in ('frames_csv', 'montage', 'sparsification', 'summary'):
        assert (tmp_path / files[key].split('/')[-1]).is_file()
    with open(tmp_path / 'frames.csv') as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(seq) and rows[0]['index'] == '0' and 'ms_abs_rel' in rows[0]
    summary = json.loads((tmp_path / 'summary.json').read_text())   # strict JSON (NaN -> null)
    assert summary['configuration'] == {'test': True}
    assert len(summary['confidence']['mean_curves']['sparsification']) == 100


def test_score_scaled_records_and_reset_skips_temporal():
    seq = _gt_sequence()
    recs = _records(seq, scale=1.1)
    recs[3].reset_reason = 'camera jumped'
    acc = E.score_records(recs)
    s = acc.summary()
    assert s['metric']['frame_mean']['abs_rel'] == pytest.approx(0.1, rel=1e-5)
    assert s['median_scaled']['frame_mean']['abs_rel'] == pytest.approx(0.0, abs=1e-6)
    assert s['metric']['frame_mean']['delta1'] == 1.0
    # pairs (0,1), (1,2), (3,4), (4,5): the reset at record 3 breaks the chain
    assert s['temporal_consistency']['num_pairs'] == len(seq) - 2
    # a uniform 10 % scale error does not move rigidly with the camera: frame a's scaled points, moved by
    # the true motion, miss frame b's scaled surface by a little - small, but not zero
    assert 0.0 < s['temporal_consistency']['pair_mean'] < 0.05


def test_depth_limits_restrict_scored_pixels():
    seq = _gt_sequence(3)
    recs = _records(seq, conf=False)
    recs[0].depth_hw = recs[0].depth_hw * 2.0
    lo = float(np.min(seq.depth(0)[seq.depth(0) > 0]))
    acc_all = E.score_records(recs)
    acc_none = E.score_records(recs, min_depth=lo - 1.0, max_depth=lo - 0.5)
    assert acc_all.rows[0]['abs_rel'] == pytest.approx(1.0, rel=1e-5)
    assert acc_none.rows[0]['num_pixels'] == 0 and math.isnan(acc_none.rows[0]['abs_rel'])


# ---------------------------------------------------------------------------------------------
# recorded outputs: bag and exported folder
# ---------------------------------------------------------------------------------------------

def _write_output_bag(path, seq, frames, scale, start_ns):
    from dpv_sensor.ros import msgs as MS
    from dpv_sensor.data import rosbag_io as R
    NS = R.NS
    with R.BagWriter(path) as bag:
        for i in range(len(seq)):
            t = start_ns + int(round((seq.stamp(i) - seq.stamp(0)) * NS))
            bag.write(R.IMAGE_TOPIC, R.IMAGE, MS.rgb_to_image(seq.image(i), t, frame_id='cam', types=R.ROSBAGS), t)
            if i in frames:
                d = seq.depth(i) * scale
                bag.write(R.DEPTH_TOPIC, R.IMAGE, MS.depth_to_image(d, t, frame_id='cam', types=R.ROSBAGS), t)
                c = np.full(d.shape, 0.7, np.float32)
                bag.write(R.CONFIDENCE_TOPIC, R.IMAGE, MS.confidence_to_image(c, t, frame_id='cam', types=R.ROSBAGS), t)
                bag.write(R.DEPTH_INFO_TOPIC, R.CAMERA_INFO,
                          MS.K_to_camera_info(seq.K, W, H, t, frame_id='cam', types=R.ROSBAGS), t)
        # a depth image whose stamp matches no frame
        t = start_ns + 123_456_789
        bag.write(R.DEPTH_TOPIC, R.IMAGE, MS.depth_to_image(seq.depth(0), t, frame_id='cam', types=R.ROSBAGS), t)


def test_bag_and_export_are_matched_by_stamp(tmp_path):
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.data.bag_export import export_depth_bag
    seq = _gt_sequence(6, stamp0=10.0)
    bag = tmp_path / 'out_bag'
    _write_output_bag(bag, seq, frames={1, 3, 4}, scale=1.1, start_ns=1_700_000_000 * R.NS)
    recs, info = E.records_from_bag(bag, seq)             # auto offset: first camera image = frame 0
    assert [r.index for r in recs] == [1, 3, 4]
    assert info['matched'] == 3 and info['unmatched'] == 1
    assert info['stamp_offset_s'] == pytest.approx(1_700_000_000 - 10.0)
    assert np.allclose(recs[0].K_33, seq.K) and recs[0].confidence_hw[0, 0] == pytest.approx(0.7)
    s = E.evaluate_records(recs, tmp_path / 'bag_eval', E.EvalOptions(progress=False))
    assert s['metric']['frame_mean']['abs_rel'] == pytest.approx(0.1, rel=1e-4)
    assert s['median_scaled']['frame_mean']['abs_rel'] == pytest.approx(0.0, abs=1e-5)
    assert (tmp_path / 'bag_eval' / 'montage.png').is_file()
    # without the offset nothing matches
    recs0, info0 = E.records_from_bag(bag, seq, stamp_offset=0.0)
    assert recs0 == [] and info0['unmatched'] == 4

    # the same outputs exported to a folder (depth in mm) give the same numbers up to mm rounding
    out = tmp_path / 'export'
    export_depth_bag(bag, out, progress=False)
    recs_e, info_e = E.records_from_export(out, seq, stamp_offset=1_700_000_000 - 10.0)
    assert [r.index for r in recs_e] == [1, 3, 4] and info_e['unmatched'] == 1
    s_e = E.evaluate_records(recs_e, None, E.EvalOptions(progress=False))
    assert s_e['metric']['frame_mean']['abs_rel'] == pytest.approx(0.1, abs=1e-3)
    assert recs_e[0].confidence_hw[0, 0] == pytest.approx(0.7, abs=1e-4)


def test_cli_bag_and_bad_config(tmp_path, capsys):
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.data.sequence import write_sequence
    from dpv_sensor.tools import evaluate as tool
    seq = _gt_sequence(4, stamp0=0.0)
    folder = write_sequence(tmp_path / 'gt', seq, lossless=True)
    bag = tmp_path / 'bag'
    _write_output_bag(bag, seq, frames={0, 2}, scale=1.0, start_ns=5 * R.NS)
    rc = tool.main(['bag', str(bag), '--gt', str(folder), '--out', str(tmp_path / 'cli'), '--quiet'])
    assert rc == 0
    out = capsys.readouterr().out
    assert '| abs_rel | sq_rel |' in out and 'matched 2 depth images' in out
    summary = json.loads((tmp_path / 'cli' / 'summary.json').read_text())
    assert summary['metric']['frame_mean']['abs_rel'] < 1e-3       # mm-rounded GT vs float prediction
    rc = tool.main(['sequence', str(folder), '--config', 'filter_mode=kalman', '--out', str(tmp_path / 'x')])
    assert rc == 2 and 'filter_mode' in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# running the estimator
# ---------------------------------------------------------------------------------------------

TINY = {'measurement': 'classical', 'processing_width': 40, 'processing_height': 32, 'num_planes': 8,
        'keyframe_max_interval': 1, 'd_min': 1.0, 'd_max': 8.0, 'filter_mode': 'global', 'window_mode': 'causal'}


def test_run_sequence_records_match_keyframes(tmp_path):
    import torch
    torch.set_num_threads(1)
    seq = _gt_sequence(6, rendered=True)
    opts = E.EvalOptions(progress=False, montage_frames=2)
    summary, recs = E.evaluate_sequence(seq, dict(TINY, num_planes=32), tmp_path, opts, return_records=True)
    # causal window: the first keyframe has no stereo partner, every later frame is a keyframe output
    assert [r.index for r in recs] == [1, 2, 3, 4, 5]
    for r in recs:
        assert r.stamp == seq.stamp(r.index)
        assert r.depth_hw.shape == r.gt_depth_hw.shape == (H, W)          # output_resolution=input
        assert np.array_equal(r.gt_depth_hw, seq.depth(r.index))
    assert summary['estimator_status']['measurement'] == 'classical'
    assert summary['configuration']['depth_limits'] == [1.0, 8.0]       # the estimator's planes by default
    assert summary['num_keyframes'] == 5
    # the classical plane sweep finds the textured plane: 32 planes over 1-8 m are ~9 % apart at 3 m, and the
    # scores stay within two of them (per-frame noise images instead: abs_rel 0.24, delta1 0.40)
    assert summary['metric']['frame_mean']['abs_rel'] < 0.12 and summary['metric']['frame_mean']['delta1'] > 0.9
    assert {p.name for p in tmp_path.iterdir()} >= {'frames.csv', 'summary.json', 'montage.png', 'sparsification.png'}


def test_processing_resolution_and_noisy_poses_and_compare(tmp_path):
    import torch
    torch.set_num_threads(1)
    seq = _gt_sequence(5, rendered=True)
    opts = E.EvalOptions(progress=False, montage_frames=1)
    s, recs = E.evaluate_sequence(seq, dict(TINY, output_resolution='processing', pose_source='noisy'), None, opts,
                                  return_records=True)
    # processing_width wide with the input's (40x30) aspect ratio
    assert recs[0].depth_hw.shape == recs[0].gt_depth_hw.shape == (30, 40)
    assert s['configuration']['options']['pose_source'] == 'noisy'
    assert s['pose_error']['mean_m'] > 0                              # the estimator got drifting poses
    res = E.compare(seq, TINY, E.variants_from_specs(['filter_mode=none,global']), tmp_path, opts)
    assert [r['filter'] for r in res['rows']] == ['none', 'global']
    # the textured plane is found with 8 planes too (noise images: abs_rel 0.21, d1 0.50)
    assert all(r['abs_rel'] < 0.2 and r['d1'] > 0.7 for r in res['rows']), \
        [(r['abs_rel'], r['d1']) for r in res['rows']]
    assert s['metric']['frame_mean']['abs_rel'] < 0.25         # drifting poses, still the plane
    md = (tmp_path / 'compare.md').read_text()
    assert md.count('\n| filter_mode=') == 2
    assert json.loads((tmp_path / 'compare.json').read_text())['rows'][0]['name'] == 'filter_mode=none'
    assert (tmp_path / 'compare_sparsification.png').is_file()


def test_window_graph_plot_draws_every_factor_kind(tmp_path):
    from dpv_sensor.evaluation.plots import window_graph_plot
    factors = {'prior': [(0.0, 0.0)], 'odometry': [(0.0, 0.1), (0.1, 0.2)],
               'photometric': [(0.2, 0.0), (0.2, 0.1), (0.1, 0.0), (0.1, 0.0)], 'keypoint': [(0.1, 0.2)]}
    out = window_graph_plot([0.0, 0.1, 0.2], factors, tmp_path / 'g.png', reference=0.2, title='t')
    assert out.is_file() and out.stat().st_size > 5000
