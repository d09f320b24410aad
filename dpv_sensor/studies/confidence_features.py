"""The confidence study: which per-pixel cues separate a right depth (within x1.25 of the truth) from a wrong one,
on every sequence, and which carry from one sequence to another.

    .venv/bin/python -m dpv_sensor.studies.confidence_features [--data DATA] [--seeds 50,51,60,61]
        [--sources gt,noisy1cov] [--pixels 3000] [--out out/confidence_features]

It runs every sequence folder under --data and the rendered held-out seeds through the node's pipeline in this
process (``evaluation.runner.run_sequence`` at the node's defaults; the stream table's pose sources: ``gt`` and
``noisy<seed>cov``, the drifting odometry with its accumulated covariance), with the estimator gathering each
keyframe's cues (``stream.confidence_features``). Of every keyframe it keeps up to --pixels scored pixels at random
(fixed seed): the cues, the per-frame medians of a few of them, the published depth, whether it is within x1.25,
its relative error and its log ratio to the truth. Samples are cached per run under OUT/samples (delete a file to
run it again); the analysis (``evaluation.confidence_study``) reads them and writes OUT/study.md and OUT/study.json.
Seeds 60 and 61 are fit-only renders of the analysis; pass them too (``--seeds 50,51,60,61``) for its tables.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time
from typing import Dict, List, Optional

import numpy as np

from dpv_sensor.stream.confidence_features import FEATURES

# cues whose per-frame median over the pixels with an estimate is a cue of every pixel of the frame
FRAME_FEATURES = ('confidence', 'parallax_px', 'texture', 'photometric')
DEFAULT_PIXELS = 3000
DEFAULT_SOURCES = ('gt', 'noisy1cov')
DEFAULT_SEEDS = (50, 51, 60, 61)


def sample_keyframe(record, rng: np.random.Generator, pixels: int, min_depth: float, max_depth: float
                    ) -> Optional[Dict[str, np.ndarray]]:
    """Up to ``pixels`` scored pixels of one keyframe record (with features): each cue, the frame medians
    (``frame_<cue>``), ``hit`` (within x1.25) and ``rel_err`` (|d - gt| / gt); None when no pixel is scored."""
    from dpv_sensor.evaluation import metrics as M
    if record.features is None:
        raise RuntimeError('the keyframe has no confidence cues: the estimator gathers them with the network '
                           'measurement only (measurement: network or auto with weights)')
    pred, gt = record.depth_hw, record.gt_depth_hw
    m = M.evaluation_mask(pred, gt, min_depth, max_depth)
    idx = np.flatnonzero(m)
    if idx.size == 0:
        return None
    if idx.size > pixels:
        idx = np.sort(rng.choice(idx, pixels, replace=False))
    p = np.clip(pred.ravel()[idx].astype(np.float64), min_depth, max_depth)
    g = gt.ravel()[idx].astype(np.float64)
    out = {k: record.features[k].ravel()[idx].astype(np.float32) for k in FEATURES}
    has_depth = np.isfinite(pred)
    for k in FRAME_FEATURES:
        v = record.features[k][has_depth]
        v = v[np.isfinite(v)]
        out['frame_' + k] = np.full(idx.size, float(np.median(v)) if v.size else np.nan, np.float32)
    out['hit'] = M.within_ratio(p, g)
    out['rel_err'] = (np.abs(p - g) / g).astype(np.float32)
    out['depth'] = p.astype(np.float32)
    out['log_ratio'] = np.log(p / g).astype(np.float32)
    out['keyframe'] = np.full(idx.size, record.index, np.int32)
    return out


def collect(seq_name: str, seq_dir: pathlib.Path, pose_source: str, out: pathlib.Path, pixels: int,
            progress: bool) -> pathlib.Path:
    """Run one sequence with one pose source and write its samples (npz); cached."""
    from dpv_sensor.benchmarks import stream_table_inputs as ST
    from dpv_sensor.data.sequence import Sequence
    from dpv_sensor.evaluation import runner as RN
    path = out / 'samples' / f'{seq_name}__{pose_source}.npz'
    if path.is_file():
        return path
    seq = Sequence(seq_dir)
    config, _ = RN.build_config({})
    t = time.perf_counter()
    records, status = RN.run_sequence(seq, config, RN.EvalOptions(progress=progress), keep_images=False,
                                      poses=ST.odometry_poses(seq, pose_source),
                                      pose_variance=ST.odometry_variance(seq, pose_source), features=True)
    lo, hi = RN.depth_limits(RN.EvalOptions(), status)
    rng = np.random.default_rng(0)
    parts = [s for s in (sample_keyframe(r, rng, pixels, lo, hi) for r in records) if s is not None]
    if not parts:
        raise RuntimeError(f'{seq_name} {pose_source}: no scored pixel')
    merged = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix('.tmp.npz')
    np.savez_compressed(tmp, **merged)
    tmp.replace(path)
    print(f'{seq_name} {pose_source}: {len(records)} keyframes, {merged["hit"].size} pixels, '
          f'{time.perf_counter() - t:.0f} s', flush=True)
    return path


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0], epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--data', default=None, help='folder of sequence folders (none: the rendered seeds only)')
    p.add_argument('--seeds', default=','.join(map(str, DEFAULT_SEEDS)),
                   help='rendered seeds ("" = none; 60 and 61 are fit-only in the analysis)')
    p.add_argument('--sources', default=','.join(DEFAULT_SOURCES), help='pose sources (stream table names)')
    p.add_argument('--pixels', type=int, default=DEFAULT_PIXELS, help='scored pixels kept per keyframe')
    p.add_argument('--out', default='out/confidence_features')
    p.add_argument('--threads', type=int, default=2)
    p.add_argument('--collect-only', action='store_true', help='run and sample, no analysis')
    p.add_argument('--quiet', action='store_true')
    return p


def main(argv: Optional[List[str]] = None) -> int:
    a = build_parser().parse_args(argv)
    import torch
    torch.set_num_threads(a.threads)
    from dpv_sensor.benchmarks import stream_table_inputs as ST
    out = pathlib.Path(a.out)
    sequences: Dict[str, pathlib.Path] = {}
    if a.data is not None:
        if not pathlib.Path(a.data).is_dir():
            raise SystemExit(f'--data {a.data}: not a folder')
        sequences.update({p.name: p for p in ST.sequence_folders(pathlib.Path(a.data))})
    for s in [int(x) for x in a.seeds.split(',') if x.strip()]:
        sequences[f'synthetic_seed{s}'] = ST.rendered_sequence(out, s, ST.RENDER_FRAMES, not a.quiet)
    sources = [s for s in a.sources.split(',') if s]
    for name, folder in sequences.items():
        for source in sources:
            collect(name, folder, source, out, a.pixels, not a.quiet)
    if a.collect_only:
        return 0
    from dpv_sensor.evaluation import confidence_study as S
    study = S.run_study(out / 'samples', list(sequences), sources)
    (out / 'study.json').write_text(json.dumps(study['json'], indent=1))
    (out / 'study.md').write_text(study['markdown'])
    print(study['markdown'])
    return 0


if __name__ == '__main__':
    sys.exit(main())
