"""Offline evaluation of the virtual depth camera (ROS-free): the front door of ``evaluate``.

Two ways in, one way out:

1. **Run the estimator** over a posed RGB-D sequence (a sequence folder, or an in-memory
   :class:`~dpv_sensor.data.sequence.Sequence`, e.g. from the synthetic renderer) with the one offline runner,
   :func:`dpv_sensor.evaluation.runner.run_sequence`: frames are pushed in order into the node's
   :class:`~dpv_sensor.stream.pipeline.Pipeline` with poses from the chosen *pose source* (``gt``: the
   sequence's poses; ``noisy``: the GT trajectory with odometry-like drift from
   :func:`dpv_sensor.data.trajectory.corrupt_trajectory`). Every keyframe output is matched to its frame by stamp
   and kept as a :class:`KeyframeRecord` (prediction, confidence, K, poses, GT depth, image).
   :func:`evaluate_sequence` runs, scores and reports one configuration, :func:`compare` several.
2. **Score recorded outputs** (:mod:`dpv_sensor.evaluation.recorded`): a rosbag2 of the node's outputs or a
   folder written by ``bag_export.export_depth_bag``, each depth image matched by stamp to a GT frame;
   :func:`evaluate_records` scores and reports them.

Scoring is :func:`dpv_sensor.evaluation.scoring.score_records` (metrics of :mod:`dpv_sensor.evaluation.metrics`),
the files and tables come from :mod:`dpv_sensor.evaluation.report`; their names are re-exported here.

Depth range and resizing (documented for the ``evaluate`` tool too):

- GT pixels outside ``[min_depth, max_depth]`` are not scored and predictions are clipped to that range.
  By default the range is the estimator's depth planes ``[d_min, d_max]`` (the network checkpoint's, or the
  ``d_min`` / ``d_max`` parameters for the classical model), since no prediction can lie outside it.
- ``width`` / ``height`` resize the *input* sequence before anything else (images with area averaging, GT
  depth with centre-aligned nearest neighbour, K scaled with the project convention). The estimator then
  resizes to its ``processing_width x processing_height``; with ``output_resolution=input`` (default) the
  output and the scoring are at the (resized) input size, with ``processing`` at the processing size, the GT
  being resized to it with centre-aligned nearest neighbour (no depth interpolated across edges).

Outputs of :func:`~dpv_sensor.evaluation.report.write_report`: ``frames.csv`` (one row per keyframe),
``summary.json`` (metrics, temporal consistency, AUSE, confident-half ratio, configuration, estimator status,
timing), ``montage.png`` (image | GT | prediction | confidence | abs-rel error for a few frames, shared colour
scale) and ``sparsification.png``. :func:`compare` writes ``compare.md`` / ``compare.json`` (and an overlaid
sparsification plot).
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import pathlib
import time
from typing import Any, Dict, Iterable, List, Optional, Sequence as SequenceT

import numpy as np

from dpv_sensor.common import to_jsonable
from dpv_sensor.evaluation.consumer_odometry import (  # noqa: F401
    CONSUMER_ODOMETRY_DEPTH_MAX, add_consumer_odometry, consumer_odometry, consumer_odometry_text)
from dpv_sensor.evaluation.recorded import (  # noqa: F401
    first_image_stamp, gt_stamp_offset, records_from_bag, records_from_export)
from dpv_sensor.evaluation.report import (  # noqa: F401
    get_path, markdown_table, table_row, write_frames_csv, write_report)
from dpv_sensor.evaluation.runner import (  # noqa: F401
    EVAL_KEYS, POSE_SOURCES, EvalOptions, KeyframeRecord, build_config, depth_limits, input_poses, known_keys,
    load_sequence, load_source, parse_overrides, prepare_sequence, run_sequence, status_json)
from dpv_sensor.evaluation.scoring import pose_rpe, relative_pose_error, score_records, summarize  # noqa: F401
from dpv_sensor import params as P

LOG = logging.getLogger('dpv_sensor.evaluation.offline')

__all__ = ['POSE_SOURCES', 'EVAL_KEYS', 'EvalOptions', 'KeyframeRecord', 'parse_value', 'parse_overrides',
           'build_config', 'load_sequence', 'load_source', 'prepare_sequence', 'run_sequence', 'score_records',
           'summarize', 'write_report', 'evaluate_sequence', 'compare', 'variants_from_specs',
           'markdown_table', 'records_from_bag', 'records_from_export', 'evaluate_records', 'to_jsonable',
           'relative_pose_error', 'consumer_odometry']

# compare() keeps the decoded frames in memory for all variants when they take less than this (RGB + depth).
MATERIALIZE_BYTES = 256 * 2 ** 20

parse_value = P.parse_value


def evaluate_sequence(seq, overrides: Optional[Dict[str, Any]] = None, out_dir=None,
                      options: Optional[EvalOptions] = None, *, model=None, name: Optional[str] = None,
                      return_records: bool = False):
    """Run the estimator over ``seq`` with the node defaults plus ``overrides``, score, and (with
    ``out_dir``) write the report. ``overrides['pose_source']`` overrides ``options.pose_source``.

    Returns the summary dict (and the records with ``return_records=True``).
    """
    options = dataclasses.replace(options or EvalOptions())
    overrides = dict(overrides or {})
    if 'pose_source' in overrides:
        options.pose_source = overrides['pose_source']
    options.validate()
    config, values = build_config(overrides)
    t0 = time.perf_counter()
    records, status = run_sequence(seq, config, options, model=model)
    wall = time.perf_counter() - t0
    lo, hi = depth_limits(options, status)
    acc = score_records(records, min_depth=lo, max_depth=hi, occlusion_tol=options.occlusion_tol,
                        progress=options.progress)
    seq_name = str(seq) if isinstance(seq, (str, pathlib.Path)) else getattr(seq, 'name', 'in-memory')
    configuration = {'overrides': overrides, 'parameters': values,
                     'options': dataclasses.asdict(options), 'depth_limits': [lo, hi]}
    summary = summarize(acc, records, configuration=configuration, status=status, source=seq_name)
    summary['wall_time_s'] = wall
    add_consumer_odometry(summary, records, options)
    if out_dir is not None:
        write_report(out_dir, acc, records, summary, montage_frames=options.montage_frames, title=name)
    return (summary, records) if return_records else summary


# ----------------------------------------------------------------------------------------------
# Comparing configurations
# ----------------------------------------------------------------------------------------------

def variants_from_specs(specs: Iterable[str]) -> List[Dict[str, Any]]:
    """``['filter_mode=none,global', 'measurement=classical']`` -> the cartesian product as typed dicts."""
    known = known_keys()
    axes = []
    for spec in specs:
        if '=' not in spec:
            raise ValueError(f'expected key=v1,v2,..., got {spec!r}')
        key, values = spec.split('=', 1)
        key = key.strip()
        if key not in known:
            raise ValueError(f'unknown configuration key {key!r}; known: {", ".join(sorted(known))}')
        vals = [v.strip() for v in values.split(',') if v.strip()]
        if isinstance(known[key], list):
            raise ValueError(f'{key} is a list parameter and cannot be compared with --compare')
        axes.append([(key, parse_value(v, known[key], key)) for v in vals])
    return [dict(combo) for combo in itertools.product(*axes)] if axes else [{}]


def _variant_name(variant: Dict[str, Any]) -> str:
    return ' '.join(f'{k}={v}' for k, v in variant.items()) or 'default'


def compare(seq, base_overrides: Optional[Dict[str, Any]], variants: SequenceT[Dict[str, Any]], out_dir=None,
            options: Optional[EvalOptions] = None, *, model=None) -> Dict[str, Any]:
    """Evaluate every variant (``base_overrides`` updated with the variant) on the same frames.

    With ``out_dir``: one report per variant in ``out_dir/<nn>_<name>/``, plus ``compare.md``,
    ``compare.json`` and ``compare_sparsification.png``. Returns ``{'rows', 'markdown', 'summaries'}``.
    """
    from dpv_sensor.evaluation import plots
    options = options or EvalOptions()
    seq = prepare_sequence(seq, options)
    if hasattr(seq, 'materialize') and len(variants) > 1 and len(seq):
        w, h = seq.size
        if len(seq) * w * h * 7 < MATERIALIZE_BYTES:
            seq = seq.materialize()      # decode/resize the frames once for all variants
    inner = dataclasses.replace(options, start=0, max_frames=None, width=None, height=None)
    rows, summaries, curves = [], {}, {}
    out = pathlib.Path(out_dir) if out_dir is not None else None
    for k, variant in enumerate(variants):
        name = _variant_name(variant)
        ov = dict(base_overrides or {})
        ov.update(variant)
        sub = None
        if out is not None:
            safe = ''.join(ch if ch.isalnum() or ch in '-_.' else '_' for ch in name)
            sub = out / f'{k:02d}_{safe}'
        LOG.info('evaluating %s', name)
        summary = evaluate_sequence(seq, ov, sub, inner, model=model, name=name)
        summaries[name] = summary
        rows.append(table_row(name, summary))
        mc = get_path(summary, ('confidence', 'mean_curves'))
        if mc is not None:
            curves[name] = {kk: np.asarray(v, np.float64) for kk, v in mc.items()}
    md = markdown_table(rows)
    result = {'rows': rows, 'markdown': md, 'summaries': summaries}
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / 'compare.md').write_text(md + '\n\nFrame means over keyframes; ms = per-frame median-scaled; '
                                        'temporal = mean abs relative disagreement of consecutive keyframes; '
                                        'conf½/all = abs_rel of the most confident half / abs_rel of all '
                                        '(per frame, mean over frames); conf½ pooled = the same over the pixels of '
                                        "all frames together; const = every pixel at the frame's median GT depth "
                                        '(an oracle constant) on the same keyframes and pixels.\n')
        with open(out / 'compare.json', 'w') as f:
            json.dump(to_jsonable({'rows': rows, 'base_overrides': base_overrides or {},
                                   'variants': list(variants), 'options': dataclasses.asdict(options)}), f, indent=1)
        if curves:
            plots.sparsification_plot(curves, out / 'compare_sparsification.png')
    return result


def evaluate_records(records: SequenceT[KeyframeRecord], out_dir=None, options: Optional[EvalOptions] = None,
                     *, source: Optional[str] = None, extra: Optional[Dict[str, Any]] = None,
                     name: Optional[str] = None) -> Dict[str, Any]:
    """Score already produced records (from a bag or an export) and write the report to ``out_dir``.

    The GT range is ``options.min_depth / max_depth`` (no estimator to take it from: None = every valid
    GT pixel).
    """
    options = options or EvalOptions()
    acc = score_records(records, min_depth=options.min_depth, max_depth=options.max_depth,
                        occlusion_tol=options.occlusion_tol, progress=options.progress)
    summary = summarize(acc, records, configuration={'options': dataclasses.asdict(options), **(extra or {})},
                        source=source)
    add_consumer_odometry(summary, records, options)
    if out_dir is not None:
        write_report(out_dir, acc, records, summary, montage_frames=options.montage_frames, title=name)
    return summary

