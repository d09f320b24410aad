"""Pose-refinement experiments (sliding-window pose refinement, odometry-free mode).

    python -m dpv_sensor.studies.poses                        # everything, CPU, prints tables
    python -m dpv_sensor.studies.poses --parts synthetic sun3d --seeds 0 1 --frames 90
    python -m dpv_sensor.studies.poses --parts timing --measurement lite
    python -m dpv_sensor.studies.poses --json out/poses.json

Parts:

* ``synthetic`` - rendered sequences (``data.synthetic.render_sequence``), keyframes every ``--every`` frames,
  odometry corrupted per keyframe (``data.trajectory.corrupt_trajectory``: ``--trans-noise`` (3 %) of each
  keyframe step in a random direction, ``--rot-noise`` (0.5 deg) about a random axis, optional
  ``--scale-bias``). Runs the
  estimator (``estimator.Estimator``, causal window of 5 keyframes) three times - GT poses, noisy poses, noisy
  poses with the :class:`~dpv_sensor.stream.window_refiner.WindowPoseRefiner` hook - and reports the keyframe
  relative pose error
  (RPE between consecutive output keyframes, of the poses the outputs were computed with) and depth abs_rel
  (metric and median-scaled), and the fraction of the noisy-to-GT abs_rel gap the refinement recovers. A
  ``refiner on GT depth`` row shows the RPE the window reaches when it aligns against the true depth (an upper
  bound for what the filter's predicted depth allows).
* ``sun3d`` - the same on ``sun3d_3dmatch_frag1`` and ``frag2`` of the shared development data folder
  (skipped when absent).
* ``vo`` - odometry-free mode (``visual_odometry.VisualOdometry``, bootstrapped from a fronto-parallel plane,
  refined by the same window) on rendered sequences and SUN3D: metric and median-scaled abs_rel next to the
  GT-pose figures; a second run replaces the middle keyframe's image by noise (must lose tracking and publish
  nothing for it);
  keyframes lost, and the worst rotation RPE among the published keyframes (a published diverged pose would show
  there). Frames whose tracking is lost are never pushed / their output is discarded.
* ``gtcheck`` - how far the ground-truth poses themselves are from photometric consistency: every pair of
  consecutive keyframes is aligned against the sensor's (GT) depth at full processing resolution, starting from
  the GT relative pose; prints the mean photometric error (|I_ref - I_src(warp)|, intensities in [0, 1]) at the GT
  pose and at the aligned pose, and how far the alignment moved (rotation deg, translation mm). On rendered
  sequences the alignment stays on the GT pose (the aligner's own accuracy); where it moves by more than the
  injected odometry noise, RPE against that GT cannot show an improvement of the size the acceptance asks for.
  The ``synthetic``/``sun3d`` tables therefore also give the RPE against these sensor-depth alignments
  ("photo-ref" columns): a reference that does not inherit the GT poses' errors, though it shares the photometric
  model with the refiner (it aligns against the depth sensor, at full resolution, the refiner against the
  filter's predicted depth at half resolution).
* ``timing`` - the added time per keyframe of the refinement relative to a keyframe without it
  (``--measurement lite``: the lite network with random weights, the per-keyframe cost of a deployed lite
  model; ``classical``: the NCC fallback).

Tracking loss is handled the way the estimator should: when the refiner (or the VO)
flags it, the estimator is reset and that keyframe's output is discarded.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import statistics
import sys
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence as Seq

import numpy as np
import torch

from dpv_sensor import params as P
from dpv_sensor.common import to_jsonable
from dpv_sensor.data.trajectory import corrupt_trajectory
from dpv_sensor.stream.estimator import Estimator, EstimatorConfig
from dpv_sensor.stream.frame import Frame
from dpv_sensor.evaluation.metrics import MetricAccumulator
from dpv_sensor.core.photometric import pose_error
from dpv_sensor.stream.visual_odometry import VisualOdometry, VisualOdometryConfig
from dpv_sensor.stream.window_refiner import PoseRefinerConfig, WindowKeyframe, WindowPoseRefiner

# the filter of these runs: the classical model's default measurement cannot drive knet (it needs a network)
FILTER_MODE = 'global'

REPO = pathlib.Path(__file__).resolve().parents[2]
SHARED_DATA = REPO.parent / 'shared' / 'data'


# ------------------------------------------------------------------------------------------------------------------
# data

def synthetic_keyframes(seed: int, frames: int, every: int, width: int, height: int):
    """Rendered sequence subsampled to its keyframes (every ``every``-th frame), in memory."""
    from dpv_sensor.data.synthetic import render_sequence
    seq = render_sequence(seed, frames, width=width, height=height, lazy=True)
    return seq.subset(list(range(0, frames, every))).materialize()


def folder_keyframes(path: pathlib.Path, every: int, width: int, height: int):
    from dpv_sensor.data.sequence import Sequence
    seq = Sequence(path)
    return seq.subset(list(range(0, len(seq), every))).resized(width, height).materialize()


# ------------------------------------------------------------------------------------------------------------------
# pipeline runs

def estimator_config(seq, measurement: str, filter_mode: str = FILTER_MODE) -> EstimatorConfig:
    """Every pushed frame is a keyframe (the sequences are already subsampled), output at processing size."""
    W, H = seq.size
    return EstimatorConfig(measurement='classical' if measurement == 'classical' else 'network',
                           preset='lite', processing_width=W, processing_height=H, filter_mode=filter_mode,
                           keyframe_translation=0.0, keyframe_rotation_deg=0.0, keyframe_max_interval=1,
                           output_resolution='processing', odom_max_speed=0.0, odom_max_rate_deg=0.0,
                           reset_time_gap=0.0, pose_refinement='window')


def make_model(measurement: str, weights: Optional[str] = None):
    """None for the classical model; the network of ``measurement``'s preset with ``weights`` (a checkpoint), or
    with random weights when none are given (what the timing needs: the cost does not depend on the values)."""
    if measurement == 'classical':
        return None
    if weights:
        from dpv_sensor.core.nets.checkpoint import load_checkpoint
        return load_checkpoint(weights, preset=measurement)[0].eval()
    from dpv_sensor.core.nets.model import DPVNet
    torch.manual_seed(0)
    return DPVNet(measurement).eval()


@dataclass
class RunResult:
    name: str
    summary: Dict
    rows: List[Dict]
    used_poses: Dict[int, np.ndarray]          # frame index -> pose the output was computed with
    keyframe_ms: List[float] = field(default_factory=list)
    keyframe_cpu_ms: List[float] = field(default_factory=list)
    refine_ms: List[float] = field(default_factory=list)
    refine_cpu_ms: List[float] = field(default_factory=list)
    lost: int = 0
    lost_reasons: List[str] = field(default_factory=list)
    published_garbage: int = 0                  # outputs for frames whose image was replaced by noise


def run_pipeline(name: str, seq, poses: Optional[Seq[np.ndarray]], measurement: str, *,
                 refiner: Optional[WindowPoseRefiner] = None, vo: Optional[VisualOdometry] = None,
                 model=None, max_depth: Optional[float] = None, garbage_frames: Seq[int] = (),
                 filter_mode: str = FILTER_MODE) -> RunResult:
    """Push the keyframes through an Estimator (with the refiner hook / VO when given) and score the outputs.

    ``garbage_frames``: indices whose image is replaced by uniform noise (bad input: tracking must be lost and no
    depth published for them)."""
    cfg = estimator_config(seq, measurement, filter_mode)
    est = Estimator(cfg, model=model, pose_refiner=refiner)
    acc = MetricAccumulator(min_depth=est.d_min, max_depth=max_depth or est.d_max)
    K = np.asarray(seq.K, dtype=np.float64)
    res = RunResult(name, {}, [], {})
    rng = np.random.default_rng(0)
    for i in range(len(seq)):
        image = seq.image(i)
        if i in garbage_frames:
            image = rng.integers(0, 256, size=image.shape, dtype=np.uint8)
        stamp = float(seq.stamp(i))
        lost_now = None
        if vo is not None:
            tr = vo.track(image, K, stamp)
            if not tr.tracking_ok:
                lost_now = f'VO: {tr.reason}'
            T = tr.T_world_cam_44
        else:
            T = poses[i]
        if lost_now is not None:
            res.lost += 1
            res.lost_reasons.append(lost_now)
            est.reset(f'tracking lost: {lost_now}')
            if refiner is not None:
                refiner.reset()
            continue
        calls = refiner.calls if refiner is not None else 0
        cpu0 = time.process_time()
        out = est.push(Frame(stamp=stamp, image=image, K_33=K, T_world_cam_44=T))
        cpu_ms = 1e3 * (time.process_time() - cpu0)
        if refiner is not None and refiner.calls != calls:
            res.refine_ms.append(refiner.last_result.timings_ms['total'])
            res.refine_cpu_ms.append(refiner.last_result.timings_ms['cpu'])
            if refiner.tracking_lost:
                # The estimator has restarted its filter and returned no output for this keyframe.
                assert out is None, 'the estimator published a keyframe whose pose refinement lost tracking'
                res.lost += 1
                res.lost_reasons.append(f'refiner: {refiner.last_result.reason}')
                if vo is not None:
                    vo.reset()
                continue
        if out is None:
            continue
        res.keyframe_ms.append(out.timings_ms.get('total', float('nan')))
        res.keyframe_cpu_ms.append(cpu_ms)
        if i in garbage_frames:
            res.published_garbage += 1
        gt = seq.depth(i)
        acc.add(out.depth_hw, gt, out.confidence_hw, index=i)
        res.used_poses[i] = np.asarray(out.T_world_cam_44, dtype=np.float64)
        if vo is not None:
            depth = np.nan_to_num(out.depth_hw, nan=0.0)
            vo.set_keyframe(image, out.K_33, out.T_world_cam_44, depth, out.confidence_hw, stamp=stamp)
    res.summary = acc.summary()
    res.rows = acc.rows
    return res


def rpe_of(used: Dict[int, np.ndarray], gt: Seq[np.ndarray], worst: bool = False):
    """Mean (or with ``worst`` the largest) RPE (translation m, rotation deg) over consecutive scored keyframes
    (pairs across a gap are skipped)."""
    relative = {a: np.linalg.inv(gt[a]) @ gt[a + 1] for a in range(len(gt) - 1)}
    return rpe_against(used, relative, np.max if worst else np.mean)


def reprojection_rpe(used: Dict[int, np.ndarray], seq, step: int = 8) -> float:
    """Mean image-space pose error (pixels) over consecutive scored keyframes: the GT-depth points of the later
    keyframe projected into the earlier one with the estimated vs the GT relative pose (one number that weighs
    rotation and translation errors by what they do to the plane sweep)."""
    K = np.asarray(seq.K, dtype=np.float64)
    Kinv = np.linalg.inv(K)
    idx = sorted(used)
    errs = []
    for a, b in zip(idx[:-1], idx[1:]):
        if b != a + 1:
            continue
        depth = np.asarray(seq.depth(b), dtype=np.float64)[::step, ::step]
        vv, uu = np.mgrid[0:depth.shape[0], 0:depth.shape[1]]
        ok = np.isfinite(depth) & (depth > 0)
        pix = np.stack([uu[ok] * step, vv[ok] * step, np.ones(ok.sum())])
        X = (Kinv @ pix) * depth[ok]
        T_gt = np.linalg.inv(seq.pose(a)) @ seq.pose(b)
        T_est = np.linalg.inv(used[a]) @ used[b]

        def proj(T):
            Y = T[:3, :3] @ X + T[:3, 3:]
            p = K @ Y
            return p[:2] / p[2:], Y[2]
        p_gt, z_gt = proj(T_gt)
        p_est, z_est = proj(T_est)
        front = (z_gt > 1e-3) & (z_est > 1e-3)
        if front.any():
            errs.append(float(np.linalg.norm(p_gt[:, front] - p_est[:, front], axis=0).mean()))
    return float(np.mean(errs)) if errs else float('nan')


def refiner_gt_depth_rpe(seq, noisy, config: PoseRefinerConfig, window: int = 5):
    """RPE of the window refiner aligning against the exact depth of each reference (no estimator)."""
    ref = WindowPoseRefiner(config)
    used = {0: noisy[0]}
    K = np.asarray(seq.K, dtype=np.float64)
    for i in range(len(seq)):
        kfs = [WindowKeyframe(j, seq.image(j), K, noisy[j]) for j in range(max(0, i - window + 1), i + 1)]
        r = ref.refine(kfs[-1], kfs[:-1], seq.depth(i) if i > 0 else None)
        if i > 0 and r.tracking_ok:
            used[i] = r.T_world_ref_44
        elif not r.tracking_ok:
            ref.reset()
    t, rot = rpe_of(used, [seq.pose(j) for j in range(len(seq))])
    return t, rot, reprojection_rpe(used, seq)


def gt_consistency(label: str, seq) -> Dict:
    """Align each keyframe's successor to it against the GT depth from the GT relative pose (see ``gtcheck``)."""
    from dpv_sensor.core.geometry import warp_image_with_depth
    from dpv_sensor.core.photometric import AlignmentConfig, align_photometric, to_gray
    K = np.asarray(seq.K, dtype=np.float64)
    K_t = torch.as_tensor(K, dtype=torch.float32)[None]
    cfg = AlignmentConfig(finest_level=0, num_levels=4, max_pixels=3000)

    def photo_error(ref: int, src: int, T_src_ref: np.ndarray) -> float:
        depth = torch.as_tensor(np.asarray(seq.depth(ref), dtype=np.float32))[None]
        warped, valid = warp_image_with_depth(to_gray(seq.image(src))[None, None], depth, K_t, K_t,
                                              torch.as_tensor(T_src_ref, dtype=torch.float32)[None])
        return float((warped[0, 0] - to_gray(seq.image(ref))).abs()[valid[0]].mean())

    rows = []
    relative = {}                  # ref -> aligned T_ref_src (= T_a_b of rpe_of) of the pair (ref, ref + 1)
    for ref in range(len(seq) - 1):
        src = ref + 1
        T_gt = np.linalg.inv(seq.pose(src)) @ seq.pose(ref)
        res = align_photometric(seq.image(ref), seq.image(src), seq.depth(ref), K, T_src_ref_init=T_gt, config=cfg)
        if not res.converged:
            continue
        relative[ref] = np.linalg.inv(res.T_src_ref_44)
        dt, dr = pose_error(T_gt, res.T_src_ref_44)
        rows.append((photo_error(ref, src, T_gt), photo_error(ref, src, res.T_src_ref_44), dr, 1e3 * dt,
                     1e3 * float(np.linalg.norm(T_gt[:3, 3]))))
    a = np.asarray(rows, dtype=np.float64).reshape(-1, 5)
    return {'sequence': label, 'pairs': len(rows), 'photo_gt': float(a[:, 0].mean()),
            'photo_aligned': float(a[:, 1].mean()), 'moved_deg': float(a[:, 2].mean()),
            'moved_deg_max': float(a[:, 2].max()), 'moved_mm': float(a[:, 3].mean()),
            'baseline_mm': float(a[:, 4].mean()), 'relative': relative}


def rpe_against(used: Dict[int, np.ndarray], relative: Dict[int, np.ndarray], agg=np.mean):
    """RPE (translation m, rotation deg; mean, or ``agg``) of consecutive scored keyframes against reference
    relative poses ``relative[a] = T_a_(a+1)`` (the GT's, or :func:`gt_consistency`'s sensor-depth alignments)."""
    te, re = [], []
    for a in sorted(used):
        if a + 1 in used and a in relative:
            t, r = pose_error(relative[a], np.linalg.inv(used[a]) @ used[a + 1])
            te.append(t)
            re.append(r)
    return (float(agg(te)), float(agg(re))) if te else (float('nan'), float('nan'))


def _abs_rel(r: RunResult, kind: str = 'metric') -> float:
    return float(r.summary[kind]['frame_mean']['abs_rel'])


# ------------------------------------------------------------------------------------------------------------------
# experiments

def odometry_experiment(label: str, seq, args, measurement: str, consistency: Dict) -> Dict:
    """``consistency``: :func:`gt_consistency` of ``seq`` (its sensor-depth alignments are the photo-ref)."""
    gt = [seq.pose(j) for j in range(len(seq))]
    noisy = corrupt_trajectory(gt, args.trans_noise, args.rot_noise, args.scale_bias, seed=args.noise_seed)
    model = make_model(measurement, args.weights)
    cfg = refiner_config(args)
    fm = args.filter_mode
    r_gt = run_pipeline('GT poses', seq, gt, measurement, model=model, filter_mode=fm)
    r_noisy = run_pipeline('noisy odometry', seq, noisy, measurement, model=model, filter_mode=fm)
    refiner = WindowPoseRefiner(cfg)
    r_ref = run_pipeline('noisy + refinement', seq, noisy, measurement, refiner=refiner, model=model, filter_mode=fm)
    ub = refiner_gt_depth_rpe(seq, noisy, cfg)
    out = {'sequence': label, 'keyframes': len(seq), 'runs': {}}
    for r in (r_gt, r_noisy, r_ref):
        t, rot = rpe_of(r.used_poses, gt)
        out['runs'][r.name] = {'rpe_t_mm': 1e3 * t, 'rpe_r_deg': rot, 'rpe_px': reprojection_rpe(r.used_poses, seq),
                               'abs_rel': _abs_rel(r),
                               'ms_abs_rel': _abs_rel(r, 'median_scaled'), 'outputs': len(r.rows),
                               'lost': r.lost, 'lost_reasons': r.lost_reasons[:5]}
    out['runs']['refiner on GT depth'] = {'rpe_t_mm': 1e3 * ub[0], 'rpe_r_deg': ub[1], 'rpe_px': ub[2]}
    # RPE against the sensor-depth alignment of consecutive keyframes (a reference that does not inherit the GT
    # poses' own errors; see gtcheck)
    photo_ref = consistency['relative']
    for r in (r_gt, r_noisy, r_ref):
        t, rot = rpe_against(r.used_poses, photo_ref)
        out['runs'][r.name].update(photo_rpe_t_mm=1e3 * t, photo_rpe_r_deg=rot)
    a_gt, a_no, a_re = (out['runs'][k]['abs_rel'] for k in ('GT poses', 'noisy odometry', 'noisy + refinement'))
    out['gap_recovered'] = (a_no - a_re) / (a_no - a_gt) if a_no != a_gt else float('nan')
    n, f = out['runs']['noisy odometry'], out['runs']['noisy + refinement']
    out['rpe_ratio_t'] = f['rpe_t_mm'] / n['rpe_t_mm']
    out['rpe_ratio_r'] = f['rpe_r_deg'] / n['rpe_r_deg']
    out['rpe_ratio_px'] = f['rpe_px'] / n['rpe_px']
    out['photo_rpe_ratio_r'] = f['photo_rpe_r_deg'] / n['photo_rpe_r_deg']
    out['photo_rpe_ratio_t'] = f['photo_rpe_t_mm'] / n['photo_rpe_t_mm']
    out['refine_ms_mean'] = float(np.mean(r_ref.refine_ms)) if r_ref.refine_ms else float('nan')
    return out


def vo_experiment(label: str, seq, args, measurement: str) -> Dict:
    gt = [seq.pose(j) for j in range(len(seq))]
    model = make_model(measurement, args.weights)
    r_gt = run_pipeline('GT poses', seq, gt, measurement, model=model, filter_mode=args.filter_mode)
    vo = VisualOdometry(VisualOdometryConfig(bootstrap_depth=args.bootstrap_depth))
    refiner = WindowPoseRefiner(refiner_config(args, vo_mode=True))
    r_vo = run_pipeline('odometry-free', seq, None, measurement, refiner=refiner, vo=vo, model=model,
                        filter_mode=args.filter_mode)
    garbage = [len(seq) // 2]
    r_bad = run_pipeline('+ noise frame', seq, None, measurement, model=model, garbage_frames=garbage,
                         refiner=WindowPoseRefiner(refiner_config(args, vo_mode=True)),
                         vo=VisualOdometry(VisualOdometryConfig(bootstrap_depth=args.bootstrap_depth)),
                         filter_mode=args.filter_mode)
    out = {'sequence': label, 'keyframes': len(seq), 'runs': {}}
    for r in (r_gt, r_vo, r_bad):
        t, rot = rpe_of(r.used_poses, gt)
        out['runs'][r.name] = {'abs_rel': _abs_rel(r), 'ms_abs_rel': _abs_rel(r, 'median_scaled'),
                               'rpe_r_deg': rot, 'max_rpe_r_deg': rpe_of(r.used_poses, gt, worst=True)[1],
                               'outputs': len(r.rows), 'lost': r.lost, 'lost_reasons': r.lost_reasons[:5],
                               'published_garbage': r.published_garbage}
    out['ms_ratio'] = out['runs']['odometry-free']['ms_abs_rel'] / out['runs']['GT poses']['ms_abs_rel']
    return out


def timing_experiment(seq, args) -> Dict:
    """Added time per keyframe of the refinement: the same keyframes with refinement off and on, interleaved
    ``--timing-repeats`` times (other jobs on a shared CPU drift over minutes), first 3 keyframes of each run
    skipped (window filling); medians. Wall and process CPU time (one torch thread: CPU time is the cost)."""
    gt = [seq.pose(j) for j in range(len(seq))]
    noisy = corrupt_trajectory(gt, args.trans_noise, args.rot_noise, seed=args.noise_seed)
    model = make_model(args.timing_measurement)
    run_pipeline('warm-up', seq.subset([0, 1, 2]), noisy[:3], args.timing_measurement, model=model)
    off, on, off_cpu, on_cpu, ref_wall, ref_cpu = [], [], [], [], [], []
    for _ in range(args.timing_repeats):
        r_off = run_pipeline('off', seq, noisy, args.timing_measurement, model=model)
        r_on = run_pipeline('window', seq, noisy, args.timing_measurement, model=model,
                            refiner=WindowPoseRefiner(refiner_config(args)))
        off += r_off.keyframe_ms[3:]
        on += r_on.keyframe_ms[3:]
        off_cpu += r_off.keyframe_cpu_ms[3:]
        on_cpu += r_on.keyframe_cpu_ms[3:]
        ref_wall += r_on.refine_ms[3:]
        ref_cpu += r_on.refine_cpu_ms[3:]
    med = statistics.median
    return {'measurement': args.timing_measurement, 'size': seq.size, 'keyframes': len(seq),
            'repeats': args.timing_repeats, 'keyframe_ms_off': med(off), 'keyframe_ms_window': med(on),
            'refine_ms': med(ref_wall), 'added_fraction': (med(on) - med(off)) / med(off),
            'keyframe_cpu_ms_off': med(off_cpu), 'keyframe_cpu_ms_window': med(on_cpu), 'refine_cpu_ms': med(ref_cpu),
            'added_fraction_cpu': (med(on_cpu) - med(off_cpu)) / med(off_cpu),
            'refine_fraction_cpu': med(ref_cpu) / med(off_cpu), 'threads': torch.get_num_threads()}


def refiner_config(args, vo_mode: bool = False) -> PoseRefinerConfig:
    al = dataclasses.replace(PoseRefinerConfig().alignment, finest_level=args.finest_level)
    cfg = PoseRefinerConfig.photometric(alignment=al, odom_sigma_rot_deg=args.rot_noise if not vo_mode else 1.0,
                                        odom_sigma_trans_m=5e-4,
                                        odom_sigma_trans_rel=max(args.trans_noise, 1e-3) if not vo_mode else 0.1,
                                        max_sources=args.max_sources or None, depth_scale_sigma=args.depth_scale_sigma,
                                        translation_sigma_rel=args.translation_sigma_rel,
                                        use_depth_uncertainty=args.depth_uncertainty, warmup_keyframes=args.warmup,
                                        inv_depth_offset_sigma=args.offset_sigma)
    return cfg


# ------------------------------------------------------------------------------------------------------------------
# printing

def print_odometry_table(results: List[Dict]) -> None:
    print('\nKeyframe relative pose error and depth with corrupted odometry')
    hdr = (f'{"sequence":<22} {"run":<22} {"RPE t mm":>9} {"RPE deg":>8} {"RPE px":>7} {"abs_rel":>8} '
           f'{"ms_abs_rel":>10} {"out":>4} {"lost":>4} {"photo-ref mm":>12} {"photo-ref deg":>13}')
    print(hdr)
    print('-' * len(hdr))
    for res in results:
        for name, r in res['runs'].items():
            print(f'{res["sequence"]:<22} {name:<22} {r["rpe_t_mm"]:>9.2f} {r["rpe_r_deg"]:>8.3f} {r["rpe_px"]:>7.2f} '
                  f'{r.get("abs_rel", float("nan")):>8.4f} {r.get("ms_abs_rel", float("nan")):>10.4f} '
                  f'{r.get("outputs", ""):>4} {r.get("lost", ""):>4} {r.get("photo_rpe_t_mm", float("nan")):>12.2f} '
                  f'{r.get("photo_rpe_r_deg", float("nan")):>13.3f}')
        print(f'{"":<22} => RPE after/before: t {res["rpe_ratio_t"]:.2f}, rot {res["rpe_ratio_r"]:.2f}, '
              f'px {res["rpe_ratio_px"]:.2f} '
              f'(target <= 0.5); abs_rel gap recovered {res["gap_recovered"]:.2f} (target >= 0.5); '
              f'refinement {res["refine_ms_mean"]:.0f} ms/keyframe')
        print(f'{"":<22}    against the sensor-depth photometric reference: RPE after/before t '
              f'{res["photo_rpe_ratio_t"]:.2f}, rot {res["photo_rpe_ratio_r"]:.2f}')


def print_vo_table(results: List[Dict]) -> None:
    print('\nOdometry-free mode (VO bootstrapped from a plane, window refinement)')
    hdr = (f'{"sequence":<22} {"run":<14} {"abs_rel":>8} {"ms_abs_rel":>10} {"RPE deg":>8} {"max RPE deg":>11} '
           f'{"out":>4} {"lost":>4} {"published noise frames":>22}')
    print(hdr)
    print('-' * len(hdr))
    for res in results:
        for name, r in res['runs'].items():
            print(f'{res["sequence"]:<22} {name:<14} {r["abs_rel"]:>8.4f} {r["ms_abs_rel"]:>10.4f} '
                  f'{r["rpe_r_deg"]:>8.3f} {r["max_rpe_r_deg"]:>11.3f} {r["outputs"]:>4} {r["lost"]:>4} '
                  f'{r["published_garbage"]:>22}')
        print(f'{"":<22} => median-scaled abs_rel / GT-pose: {res["ms_ratio"]:.2f} (target <= 1.5)')
        for name in ('odometry-free', '+ noise frame'):
            reasons = res['runs'][name]['lost_reasons']
            if reasons:
                print(f'{"":<22}    {name}: first loss reasons: {reasons[:2]}')


def print_gt_consistency(results: List[Dict]) -> None:
    print('\nPhotometric consistency of the GT poses (consecutive keyframes aligned against the GT depth from the GT '
          'pose)')
    hdr = (f'{"sequence":<22} {"pairs":>5} {"baseline mm":>11} {"photo err GT":>12} {"aligned":>8} {"moved deg":>9} '
           f'{"max deg":>8} {"moved mm":>8}')
    print(hdr)
    print('-' * len(hdr))
    for r in results:
        print(f'{r["sequence"]:<22} {r["pairs"]:>5} {r["baseline_mm"]:>11.1f} {r["photo_gt"]:>12.4f} '
              f'{r["photo_aligned"]:>8.4f} {r["moved_deg"]:>9.3f} {r["moved_deg_max"]:>8.3f} {r["moved_mm"]:>8.2f}')


def print_timing(t: Dict) -> None:
    print('\nAdded time per keyframe of pose refinement (this CPU)')
    print(f'  measurement {t["measurement"]}, {t["size"][0]}x{t["size"][1]}, {t["keyframes"]} keyframes x '
          f'{t["repeats"]} interleaved repeats, {t["threads"]} torch threads, medians')
    print(f'  wall time: keyframe without refinement {t["keyframe_ms_off"]:.0f} ms, with {t["keyframe_ms_window"]:.0f} '
          f'ms (refiner itself {t["refine_ms"]:.0f} ms): added {100 * t["added_fraction"]:.0f} % (target < 50 %)')
    print(f'  CPU time:  keyframe without refinement {t["keyframe_cpu_ms_off"]:.0f} ms, with '
          f'{t["keyframe_cpu_ms_window"]:.0f} ms (refiner itself {t["refine_cpu_ms"]:.0f} ms = '
          f'{100 * t["refine_fraction_cpu"]:.0f} %): added {100 * t["added_fraction_cpu"]:.0f} % '
          f'(CPU time is what the job costs when other jobs share the cores)')


# ------------------------------------------------------------------------------------------------------------------

def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--parts', nargs='+', default=['synthetic', 'sun3d', 'vo', 'gtcheck', 'timing'],
                   choices=['synthetic', 'sun3d', 'vo', 'gtcheck', 'timing'])
    p.add_argument('--seeds', type=int, nargs='+', default=[0, 1])
    p.add_argument('--frames', type=int, default=90, help='rendered frames per synthetic sequence')
    p.add_argument('--every', type=int, default=3, help='keyframe spacing in frames (synthetic)')
    p.add_argument('--sun3d-every', type=int, default=3, help='keyframe spacing in frames (SUN3D)')
    p.add_argument('--size', default='320x240', help='processing size WxH')
    p.add_argument('--measurement', default='classical', choices=['classical', 'lite', 'paper'],
                   help='measurement model for the accuracy parts (network presets use random weights)')
    p.add_argument('--weights', default=None,
                   help='checkpoint for --measurement lite/paper (default: random weights, enough for timing)')
    p.add_argument('--filter-mode', default=FILTER_MODE, choices=P.choices('filter_mode'),
                   help='filter of the estimator runs (knet needs a network)')
    p.add_argument('--timing-measurement', default='lite', choices=['classical', 'lite', 'paper'])
    p.add_argument('--timing-repeats', type=int, default=3)
    p.add_argument('--trans-noise', type=float, default=0.03)
    p.add_argument('--rot-noise', type=float, default=0.5)
    p.add_argument('--scale-bias', type=float, default=0.0)
    p.add_argument('--noise-seed', type=int, default=0)
    p.add_argument('--finest-level', type=int, default=1)
    p.add_argument('--max-sources', type=int, default=PoseRefinerConfig.max_sources,
                   help='sources aligned per keyframe (0 = all)')
    p.add_argument('--bootstrap-depth', type=float, default=2.0)
    p.add_argument('--depth-scale-sigma', type=float, default=PoseRefinerConfig.depth_scale_sigma)
    p.add_argument('--translation-sigma-rel', type=float, default=PoseRefinerConfig.translation_sigma_rel)
    p.add_argument('--offset-sigma', type=float, default=None,
                   help='inverse-depth offset sigma (1/m) of the predicted depth (default: automatic)')
    p.add_argument('--warmup', type=int, default=PoseRefinerConfig.warmup_keyframes,
                   help='references with a predicted depth that are not aligned after a (re)start')
    p.add_argument('--no-depth-uncertainty', dest='depth_uncertainty', action='store_false',
                   help='do not weigh pixels by the DPV depth uncertainty')
    p.add_argument('--threads', type=int, default=None)
    p.add_argument('--json', default=None)
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    W, H = (int(v) for v in args.size.lower().split('x'))
    report: Dict = {'args': vars(args)}

    seqs = []
    if {'synthetic', 'vo', 'timing', 'gtcheck'} & set(args.parts):
        for s in args.seeds:
            t = time.perf_counter()
            seqs.append((f'synthetic seed {s}', synthetic_keyframes(s, args.frames, args.every, W, H)))
            print(f'rendered seed {s} in {time.perf_counter() - t:.0f} s', file=sys.stderr)
    sun = []
    if {'sun3d', 'vo', 'gtcheck'} & set(args.parts):
        for name in ('sun3d_3dmatch_frag1', 'sun3d_3dmatch_frag2'):
            path = SHARED_DATA / name
            if (path / 'poses.txt').is_file():
                sun.append((name, folder_keyframes(path, args.sun3d_every, W, H)))
            else:
                print(f'{path} is absent: skipped', file=sys.stderr)

    consistency: Dict[str, Dict] = {}

    def consistency_of(label, seq) -> Dict:      # once per sequence: the odometry tables and gtcheck share it
        if label not in consistency:
            consistency[label] = gt_consistency(label, seq)
        return consistency[label]

    if 'synthetic' in args.parts or 'sun3d' in args.parts:
        todo = (seqs if 'synthetic' in args.parts else []) + (sun if 'sun3d' in args.parts else [])
        results = []
        for label, seq in todo:
            t = time.perf_counter()
            results.append(odometry_experiment(label, seq, args, args.measurement, consistency_of(label, seq)))
            print(f'{label}: {time.perf_counter() - t:.0f} s', file=sys.stderr)
        report['odometry'] = results
        print_odometry_table(results)
    if 'vo' in args.parts:
        results = [vo_experiment(label, seq, args, args.measurement) for label, seq in seqs + sun]
        report['vo'] = results
        print_vo_table(results)
    if 'gtcheck' in args.parts:
        report['gtcheck'] = [{k: v for k, v in consistency_of(label, seq).items() if k != 'relative'}
                             for label, seq in seqs + sun]
        print_gt_consistency(report['gtcheck'])
    if 'timing' in args.parts and seqs:
        report['timing'] = timing_experiment(seqs[0][1], args)
        print_timing(report['timing'])
    if args.json:
        pathlib.Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        with open(args.json, 'w') as f:
            json.dump(to_jsonable(report), f, indent=1, default=str)
    return 0


if __name__ == '__main__':
    sys.exit(main())
