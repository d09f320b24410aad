"""The stream-table benchmark on a tiny case, and its pieces.

One run of the tool (held-out seed 50 rendered at 96x72, 12 frames, one noisy-odometry pose source, the classical
model at 96x72: ~30-60 s on a busy 2-core CPU) through the node process and lockstep bag replay; its cached JSON is
checked against values computed here, independently, from the recorded output bag and the GT sequence folder:
abs_rel, coverage and the constant baseline with plain numpy, the number of scored keyframes, no reset. A second
call with the same arguments runs nothing (resumable). The odometry noise and the consumer odometry have their own
small cases.
"""
import json
import math
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from ros_helpers import REPO
from dpv_sensor.benchmarks import stream_table as ST
from dpv_sensor.benchmarks import stream_table_inputs as SI
from dpv_sensor.benchmarks import stream_table_markdown as SM
from dpv_sensor.benchmarks import stream_table_runs as SR
from dpv_sensor.client.replay import parse_params

NODE = ['measurement=classical', 'processing_width=96', 'processing_height=72', 'num_planes=32', 'window_mode=causal']
ARGS = ['--seeds', '50', '--frames', '12', '--render-size', '96x72', '--no-gt', '--offset-ms', '0',
        '--noise-seeds', '0', '--keep-bags', '--quiet', '--params'] + NODE


def _run(out, timeout=300):
    cmd = [sys.executable, '-m', 'dpv_sensor.benchmarks.stream_table', '--out', str(out)] + ARGS
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope='module')
def table_run(tmp_path_factory):
    out = tmp_path_factory.mktemp('stream_table') / 'out'
    return out, _run(out)


def _run_json(out):
    key = SI.run_key('synthetic_seed50', 'noisy0', parse_params(NODE))
    return json.loads((out / 'runs' / f'{key}.json').read_text()), key


def test_table_fields_match_independent_values(table_run):
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.data.sequence import Sequence
    out, proc = table_run
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    run, key = _run_json(out)
    seq = Sequence(out / 'sequences' / 'synthetic_seed50')
    depth = R.read_depth_images(out / 'work' / key / 'output_bag', '/depth/image')
    stamps = np.array([seq.stamp(i) for i in range(len(seq))])
    assert run['keyframes_scored'] == len(depth) >= 2
    # abs_rel and coverage per frame by hand: pixels with a prediction and a valid GT depth
    all_gt = np.concatenate([np.asarray(seq.depth(i))[np.asarray(seq.depth(i)) > 0] for i in range(len(seq))])
    c = float(np.median(all_gt))
    abs_rel, cover, const = [], [], []
    for s in depth:
        j = int(np.argmin(np.abs(stamps - s.stamp_ns / 1e9)))
        assert abs(stamps[j] - s.stamp_ns / 1e9) < 1e-3
        gt = np.asarray(seq.depth(j), np.float64)
        p = np.asarray(s.data, np.float64)
        m = np.isfinite(p) & (p > 0) & (gt > 0)
        abs_rel.append(np.mean(np.abs(p[m] - gt[m]) / gt[m]))
        cover.append(m.sum() / (gt > 0).sum())
        const.append(np.mean(np.abs(c - gt[m]) / gt[m]))
    assert run['abs_rel'] == pytest.approx(np.mean(abs_rel), rel=1e-4)
    assert run['coverage'] == pytest.approx(np.mean(cover), rel=1e-6)
    assert run['constant']['constant_m'] == pytest.approx(c, rel=1e-6)
    assert run['constant']['abs_rel'] == pytest.approx(np.mean(const), rel=1e-4)
    # a smooth rendered walk with 2 % odometry drift: the filter never restarts; every keyframe is timed
    assert run['output_resets'] == 0 and run['output_reset_reasons'] == []
    assert run['keyframes_timed'] == int(run['node']['keyframes']) >= 3
    assert run['keyframe_ms_median'] > 0
    assert int(run['node']['dropped_total']) == 0 and run['node']['exit_code'] == 0
    co = run['consumer_odometry']
    assert co['pairs'] == len(depth) - 1
    assert co['ratio_trans'] == pytest.approx(co['hybrid']['predicted']['trans_m_median'] /
                                              co['hybrid']['gt_depth']['trans_m_median'])
    # the table: one noisy row with these numbers
    md = (out / f'stream_table_{SI.params_tag(parse_params(NODE))}.md').read_text()
    row = [ln for ln in md.splitlines() if ln.startswith('| synthetic_seed50 |')]
    assert len(row) == 1 and '| noisy ×1 |' in row[0] and f"| {run['abs_rel']:.3f} |" in row[0], md
    # calibration of the run: ECE and the kept share recomputed from the recorded depth and confidence images
    conf_imgs = R.read_depth_images(out / 'work' / key / 'output_bag', '/confidence/image')
    assert [c.stamp_ns for c in conf_imgs] == [s.stamp_ns for s in depth]
    confs, hits = [], []
    for s, ci in zip(depth, conf_imgs):
        j = int(np.argmin(np.abs(stamps - s.stamp_ns / 1e9)))
        gt = np.asarray(seq.depth(j), np.float64)
        p = np.asarray(s.data, np.float64)
        m = np.isfinite(p) & (p > 0) & (gt > 0)
        confs.append(np.asarray(ci.data, np.float64)[m][::8])
        hits.append((np.maximum(p[m] / gt[m], gt[m] / p[m]) < 1.25)[::8])
    conf, hit = np.concatenate(confs), np.concatenate(hits)
    cal = run['calibration']
    assert cal['num_pixels'] == conf.size
    assert cal['hit_rate'] == pytest.approx(hit.mean(), abs=1e-9)
    ece = 0.0
    for b in range(10):
        sel = (np.minimum((conf * 10).astype(int), 9) == b)
        if sel.any():
            ece += sel.mean() * abs(conf[sel].mean() - hit[sel].mean())
    assert cal['ece'] == pytest.approx(ece, abs=1e-6)
    assert cal['kept']['0.5']['share'] == pytest.approx((conf >= 0.5).mean(), abs=1e-9)
    assert (out / 'plots' / f'{key}_reliability.png').is_file()


def test_second_call_runs_nothing(table_run):
    out, proc = table_run
    assert proc.returncode == 0
    run, key = _run_json(out)
    again = _run(out, timeout=120)
    assert again.returncode == 0, again.stdout[-2000:] + again.stderr[-2000:]
    assert '1 runs cached, 0 to run' in again.stdout
    assert _run_json(out)[0] == run


def test_odometry_noise_is_two_percent_of_each_step_and_a_tenth_of_a_degree():
    from dpv_sensor.data.synthetic import render_sequence
    from dpv_sensor.evaluation.offline import relative_pose_error
    seq = render_sequence(50, 6, width=32, height=24, lazy=True)
    gt = SI.odometry_poses(seq, 'gt')
    noisy = SI.odometry_poses(seq, 'noisy1')
    assert np.allclose(noisy[0], gt[0]) and not np.allclose(noisy[3], gt[3])
    assert SI.odometry_poses(seq, 'noisy1')[5].tolist() == noisy[5].tolist()    # seeded
    for i in range(1, 6):
        rel_gt = np.linalg.inv(gt[i - 1]) @ gt[i]
        rel_n = np.linalg.inv(noisy[i - 1]) @ noisy[i]
        step = np.linalg.norm(rel_gt[:3, 3])
        assert np.linalg.norm(rel_n[:3, 3] - rel_gt[:3, 3]) == pytest.approx(0.02 * step, rel=1e-6)
        rot_err = relative_pose_error(_rot(rel_n) @ np.linalg.inv(_rot(rel_gt)), np.eye(4))[1]
        assert rot_err == pytest.approx(0.1, abs=1e-6)
    with pytest.raises(ValueError):
        SI.odometry_poses(seq, 'drift')


def test_time_offset_source_is_the_gt_pose_later_by_the_offset():
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(50, 6, width=32, height=24, lazy=True)
    gt = SI.odometry_poses(seq, 'gt')
    dt = seq.stamp(1) - seq.stamp(0)
    half = SI.odometry_poses(seq, f'offset{1000 * dt / 2:g}ms')
    # half a frame later: half way between the frames (linear translation), the last pose held
    np.testing.assert_allclose(half[2][:3, 3], 0.5 * (gt[2][:3, 3] + gt[3][:3, 3]), atol=1e-9)
    np.testing.assert_allclose(half[5], gt[5], atol=1e-12)
    assert SI.noise_description('offset10ms') == {'time_offset_ms': 10.0}


def _rot(T):
    R = np.eye(4)
    R[:3, :3] = T[:3, :3]
    return R


def test_consumer_odometry_on_gt_depth_is_ratio_one_and_a_constant_depth_is_worse():
    from dpv_sensor.data.synthetic import render_sequence
    from dpv_sensor.evaluation import offline as E
    seq = render_sequence(51, 9, width=160, height=120, lazy=True)
    recs = []
    for i in range(0, 9, 2):
        d = np.asarray(seq.depth(i), np.float32)
        recs.append(E.KeyframeRecord(index=i, stamp=seq.stamp(i), depth_hw=d.copy(), confidence_hw=None,
                                     K_33=np.asarray(seq.K), gt_depth_hw=d, gt_T_world_cam_44=seq.pose(i),
                                     image_hw3=seq.image(i)))
    same = E.consumer_odometry(recs)
    assert same['pairs'] == 4
    assert same['ratio_trans'] == pytest.approx(1.0) and same['ratio_rot'] == pytest.approx(1.0)
    # exact depth and poses of our renderer: the colour-term odometry recovers the motion to a few mm
    assert same['color']['gt_depth']['trans_m_median'] < 0.01
    flat = [E.KeyframeRecord(**{**r.__dict__, 'depth_hw': np.full_like(r.gt_depth_hw, np.median(r.gt_depth_hw))})
            for r in recs]
    worse = E.consumer_odometry(flat)
    assert worse['color']['ratio_trans'] > 1.0 or worse['color']['ratio_rot'] > 1.0
    assert math.isfinite(worse['ratio_trans'])


def test_corruption_variance_by_hand_and_against_the_noise_it_describes():
    from dpv_sensor.data.trajectory import corrupt_trajectory, corruption_variance
    # a straight line of 1 m steps: per step (0.02 m)^2 / 3 per axis, plus the heading error's tilt
    gt = [np.eye(4) for _ in range(4)]
    for i, T in enumerate(gt):
        T[2, 3] = float(i)
    var = corruption_variance(gt, trans_noise_rel=0.02, rot_noise_deg=0.1)
    r = math.radians(0.1) ** 2 / 3
    assert var[0].tolist() == [0.0, 0.0]
    assert var[1, 0] == pytest.approx(0.02 ** 2 / 3) and var[1, 1] == pytest.approx(r)
    assert var[2, 0] == pytest.approx(2 * 0.02 ** 2 / 3 + 2 * r / 3)
    assert var[3, 1] == pytest.approx(3 * r)
    # it is the variance of the error corrupt_trajectory makes (per axis, 400 seeds, 30 steps of 5 cm)
    for i, T in enumerate(gt := [np.eye(4) for _ in range(31)]):
        T[0, 3], T[2, 3] = 0.05 * i, 0.01 * i
    var = corruption_variance(gt, trans_noise_rel=0.05, rot_noise_deg=1.0)
    err = np.array([corrupt_trajectory(gt, trans_noise_rel=0.05, rot_noise_deg=1.0, seed=s)[-1][:3, 3] - gt[-1][:3, 3]
                    for s in range(400)])
    assert np.mean(err ** 2) == pytest.approx(var[-1, 0], rel=0.2)


def test_corruption_twist_variance_by_hand_integrates_to_the_noise_models_variance():
    from dpv_sensor.data.trajectory import corruption_twist_variance, corruption_variance
    # steps of 5, 10 and 0 cm after 0.04, 0.05 and 0.02 s
    gt = [np.eye(4) for _ in range(4)]
    for T, x in zip(gt, (0.0, 0.05, 0.15, 0.15)):
        T[0, 3] = x
    rates = corruption_twist_variance(gt, [1.0, 1.04, 1.09, 1.11], trans_noise_rel=0.02, rot_noise_deg=0.1)
    r = math.radians(0.1) ** 2 / 3
    np.testing.assert_allclose(rates[1:], [[(0.02 * 0.05) ** 2 / 3 / 0.04, r / 0.04],
                                           [(0.02 * 0.10) ** 2 / 3 / 0.05, r / 0.05], [0.0, r / 0.02]])
    np.testing.assert_array_equal(rates[0], rates[1])
    # integrated over the steps (rate x dt), the noise model's rotation variance, as the pose covariance grows
    dt = np.diff([1.0, 1.04, 1.09, 1.11])
    assert float(np.sum(rates[1:, 1] * dt)) == pytest.approx(corruption_variance(gt, 0.02, 0.1)[-1, 1])
    with pytest.raises(ValueError):
        corruption_twist_variance(gt, [1.0, 1.0, 1.1, 1.2])


def test_the_diff_drive_source_has_the_noisy_poses_a_constant_pose_and_a_twist_covariance():
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(50, 6, width=32, height=24, lazy=True)
    assert [T.tolist() for T in SI.odometry_poses(seq, 'noisy1twist')] == \
        [T.tolist() for T in SI.odometry_poses(seq, 'noisy1')]
    pose = SI.odometry_variance(seq, 'noisy1twist')
    assert pose.shape == (6, 2) and np.all(pose == SI.CONSTANT_POSE_VARIANCE)
    twist = SI.odometry_twist_variance(seq, 'noisy1twist')
    assert twist.shape == (6, 2) and np.all(twist > 0)
    assert SI.odometry_twist_variance(seq, 'noisy1cov') is None and SI.odometry_twist_variance(seq, 'noisy1') is None
    assert SI.noise_description('noisy1twist')['twist_covariance']
    assert not SI.noise_description('noisy1twist')['covariance']
    table = ST._Table(out=pathlib.Path('.'), params={}, folders={'a': None}, noise_seeds=[0, 1],
                      single_sources=('gt',), command='', covariance=True, twist=True)
    assert table.sources == ['gt', 'noisy0', 'noisy1', 'noisy0cov', 'noisy1cov', 'noisy0twist', 'noisy1twist']
    runs = [{'key': SI.run_key('a', src, {}), 'abs_rel': v, 'output_resets': 0}
            for src, v in (('noisy0cov', 0.2), ('noisy0twist', 0.3))]
    rows = SM.table_rows(runs, ['a'], [0], {}, single_sources=())
    assert [(r['poses'], r['abs_rel']) for r in rows] == [('noisy+cov ×1', 0.2), ('noisy+twist cov ×1', 0.3)]


def test_the_honest_odometry_source_has_the_noisy_poses_and_a_covariance():
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(50, 6, width=32, height=24, lazy=True)
    assert [T.tolist() for T in SI.odometry_poses(seq, 'noisy1cov')] == \
        [T.tolist() for T in SI.odometry_poses(seq, 'noisy1')]
    assert SI.odometry_variance(seq, 'noisy1') is None and SI.odometry_variance(seq, 'gt') is None
    var = SI.odometry_variance(seq, 'noisy1cov')
    assert var.shape == (6, 2) and np.all(np.diff(var[:, 1]) > 0)
    assert SI.noise_description('noisy1cov')['covariance'] and not SI.noise_description('noisy1')['covariance']
    table = ST._Table(out=pathlib.Path('.'), params={}, folders={'a': None}, noise_seeds=[0, 1],
                      single_sources=('gt',), command='', covariance=True)
    assert table.sources == ['gt', 'noisy0', 'noisy1', 'noisy0cov', 'noisy1cov']


def test_offline_runs_agree_with_the_node_and_carry_the_covariance(table_run):
    """--offline: the same pose source through the pipeline in this process gives the node run's depth; the honest
    source's covariance reaches the estimator (it widens the measurement: lower confidence, same poses)."""
    out, proc = table_run
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    node_run, _ = _run_json(out)
    folder = out / 'sequences' / 'synthetic_seed50'
    params = parse_params(NODE)
    plain = SR.run_one_offline('synthetic_seed50', folder, 'noisy0', params, out, progress=False)
    honest = SR.run_one_offline('synthetic_seed50', folder, 'noisy0cov', params, out, progress=False)
    assert plain['keyframes_scored'] == node_run['keyframes_scored']
    assert plain['abs_rel'] == pytest.approx(node_run['abs_rel'], abs=0.005)
    assert honest['calibration']['mean_confidence'] < plain['calibration']['mean_confidence']
    table = ST._Table(out=out, params=params, folders={'synthetic_seed50': folder}, noise_seeds=[0],
                      single_sources=(), command='', offline=True)
    assert 'offline=True' in table.run_file('synthetic_seed50', 'noisy0').name
    rows = SM.table_rows([plain, honest], table.sequences, [0], table.tag_params, single_sources=())
    assert [r['poses'] for r in rows] == ['noisy ×1', 'noisy+cov ×1']        # the offline table has its rows
    assert rows[0]['abs_rel'] == pytest.approx(plain['abs_rel'])
