"""The default keyframe as the node runs it: every stage of ``Pipeline.push``, median and p95, per variant.

    python -m dpv_sensor.benchmarks.keyframe                                # node defaults, float32 and bfloat16
    python -m dpv_sensor.benchmarks.keyframe --backends torch,onnxruntime --keyframes 30 --json out/keyframe.json
    python -m dpv_sensor.benchmarks.keyframe --precisions float32 --set pose_refinement=off
    python -m dpv_sensor.benchmarks.keyframe --variant default: --variant no-window:pose_refinement=off
    python -m dpv_sensor.benchmarks.keyframe --sequence DATA/tum_fr1_rpy --precisions float32 --keyframes 30

What is timed: ``Pipeline.push(frame)`` of the frames that become keyframes, with the node's defaults (the
settings table's: centred window, refinement window, K-Net, the readout, the edge filter, the output at the
input's size), on a rendered 30 Hz camera at ``--input`` size (default 640x480, as the node gets it), or on a
recorded sequence folder (``--sequence``: its images at their own size, its poses as the odometry). Variants
are every backend x precision asked for (``inference_backend`` x ``cpu_precision``); each has its own pipeline
and every frame is pushed into all of them in turn (the order rotating per frame), so on a shared machine each
variant sees the same load and the ratios between variants hold even where the absolute times are noisy.

The stages are the estimator's own timings (``DepthOutput.timings_ms``: resize, pose refinement, measurement,
pose uncertainty, filter, refine, metric anchors, output, and their parts such as ``filter.knet`` or
``refine.edge_filter``);
``push`` is the wall time of the whole call, measured here, ``push_cpu`` the process CPU time it took (all
threads: on a loaded machine the steadier figure; with ``--threads 1`` it is the one-core cost). A keyframe whose
push publishes an output is timed (in the centred window that output is the keyframe two keyframes back); the first
``--warmup`` of them are not (the window fills, the refiner warms up). Also reported per variant: the largest depth
difference from the ``torch`` variant of the same precision on the pixels both estimate (a runtime's check), and
the estimator's notes (e.g. a runtime that could not load).
"""
from __future__ import annotations

import argparse
import itertools
import json
import logging
import os
import statistics
import sys
import time
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from dpv_sensor import params as P
from dpv_sensor.benchmarks.nets import parse_size

__all__ = ['run', 'main', 'STAGES', 'markdown']

# (stage, label) in the order of a push; parts ('stage.part') are indented under their stage
STAGES = (
    ('push', 'Pipeline.push (wall)'),
    ('push_cpu', 'Pipeline.push (process CPU time)'),
    ('total', 'estimator total'),
    ('resize', 'resize'),
    ('pose_refinement', 'pose refinement'),
    ('pose_refinement.predict', 'predict + depth for the refiner'),
    ('pose_refinement.align', 'photometric alignments'),
    ('pose_refinement.keypoints', 'keypoints'),
    ('pose_refinement.optimize', 'gate, solve, marginals'),
    ('measurement', 'measurement (D-Net)'),
    ('measurement.features', 'features'),
    ('measurement.cost_volume', 'cost volume'),
    ('pose_uncertainty', 'pose uncertainty'),
    ('filter', 'filter'),
    ('filter.knet', 'K-Net'),
    ('refine', 'refine'),
    ('refine.rnet', 'R-Net'),
    ('refine.readout', 'readout'),
    ('refine.edge_filter', 'edge filter'),
    ('anchors', 'metric anchors'),
    ('anchors.classical', 'classical fallback'),
    ('output', 'output'),
)


# the settings that shape a keyframe, shown with the table (the variants' own settings are in each variant)
SHAPING = ('preset', 'processing_width', 'processing_height', 'window_mode', 'pose_refinement', 'filter_mode',
           'depth_readout', 'edge_filter_radius', 'depth_anchors', 'output_resolution')


def _frames(size: Tuple[int, int], seed: int, count: int, sequence: Optional[str] = None):
    """``count`` frames of a rendered 30 Hz camera (lazily rendered: only the frames pushed are drawn), or the
    first ``count`` of a sequence folder (read as pushed; its depth is not read)."""
    from dpv_sensor.stream.frame import Frame
    if sequence:
        from dpv_sensor.data.sequence import Sequence
        seq = Sequence(sequence, depth=False)
    else:
        from dpv_sensor.data.synthetic import render_sequence
        seq = render_sequence(seed=seed, num_frames=count, width=size[0], height=size[1], lazy=True, cache_frames=2)
    for i in range(min(count, len(seq))):
        yield Frame(stamp=seq.stamp(i), image=seq.image(i), K_33=seq.K, T_world_cam_44=seq.pose(i), frame_id='camera')


def _quiet_logger(notes: List[str]) -> logging.Logger:
    """A logger that keeps the warnings (the estimator's notes) instead of printing them."""
    log = logging.getLogger(f'dpv_sensor.benchmarks.keyframe.{id(notes)}')
    log.propagate = False
    log.setLevel(logging.INFO)

    class Keep(logging.Handler):
        def emit(self, record):
            if record.levelno >= logging.WARNING:
                notes.append(record.getMessage())
    log.handlers = [Keep()]
    return log


def _pipeline(settings: Dict, notes: List[str]):
    from dpv_sensor.evaluation.runner import build_config
    from dpv_sensor.stream.pipeline import Pipeline
    config, _ = build_config(settings)
    return Pipeline(config, logger=_quiet_logger(notes))


def variants(backends: Sequence[str] = ('torch',), precisions: Sequence[str] = ('float32', 'bfloat16'),
             extra: Optional[Dict[str, Dict]] = None) -> Dict[str, Dict]:
    """Variant name -> settings: every backend x precision (``torch/float32`` ...), times every ``extra`` variant
    (name -> settings, e.g. ``{'no-window': {'pose_refinement': 'off'}}``; the names then read
    ``torch/float32/no-window``)."""
    out = {}
    for b, p in itertools.product(backends, precisions):
        for name, settings in (extra or {'': {}}).items():
            out[f'{b}/{p}' + (f'/{name}' if name else '')] = dict(settings, inference_backend=b, cpu_precision=p)
    return out


def _reference(name: str, names: Sequence[str]) -> Optional[str]:
    """The variant a variant is compared with: the same name with the torch backend (itself for torch)."""
    ref = '/'.join(['torch'] + name.split('/')[1:])
    return ref if ref in names else None


def _summary(values: Sequence[float]) -> Dict[str, float]:
    return {'median': statistics.median(values), 'p95': float(np.percentile(values, 95)), 'n': len(values)}


def run(variant_settings: Optional[Dict[str, Dict]] = None, input_size: Tuple[int, int] = (640, 480),
        keyframes: int = 12, warmup: int = 4, seed: int = 3, max_frames: int = 600, settings: Optional[Dict] = None,
        threads: Optional[int] = None, progress: bool = False, sequence: Optional[str] = None) -> Dict:
    """Time ``keyframes`` keyframes per variant; returns a dict (see the module docstring).

    ``variant_settings``: name -> estimator settings (default :func:`variants`: torch in float32 and bfloat16);
    ``settings``: estimator settings over the node's defaults for every variant; ``sequence``: a sequence folder
    to push instead of the render (``input_size`` and ``seed`` then unused)."""
    import torch
    if threads:
        torch.set_num_threads(int(threads))
    settings = dict(settings or {})
    variant_settings = variant_settings or variants()
    names = list(variant_settings)
    notes = {n: [] for n in names}
    pipes = {n: _pipeline(dict(settings, **variant_settings[n]), notes[n]) for n in names}
    stages: Dict[str, Dict[str, List[float]]] = {n: {} for n in names}
    seen = {n: 0 for n in names}
    depth_diff: Dict[str, List[float]] = {n: [] for n in names}
    frames_pushed = 0
    t_start = time.perf_counter()
    for i, frame in enumerate(_frames(input_size, seed, max_frames, sequence)):
        frames_pushed += 1
        order = names[i % len(names):] + names[:i % len(names)]
        outputs = {}
        for n in order:
            c, t = time.process_time(), time.perf_counter()
            r = pipes[n].push(frame)
            ms, cpu_ms = (time.perf_counter() - t) * 1e3, (time.process_time() - c) * 1e3
            out = r.output
            if not (r.is_keyframe and out is not None and out.is_keyframe):
                continue
            seen[n] += 1
            outputs[n] = out
            if seen[n] <= warmup:
                continue
            for k, v in dict(out.timings_ms, push=ms, push_cpu=cpu_ms).items():
                stages[n].setdefault(k, []).append(float(v))
        for n, out in outputs.items():
            ref = outputs.get(_reference(n, names))
            if ref is not None and ref is not out and seen[n] > warmup:
                both = np.isfinite(out.depth_hw) & np.isfinite(ref.depth_hw)
                depth_diff[n].append(float(np.abs(out.depth_hw[both] - ref.depth_hw[both]).max()) if both.any()
                                     else 0.0)
        if progress and outputs:
            print(f'  frame {i}: ' + ', '.join(f'{n} {len(stages[n].get("push", []))}' for n in names), flush=True)
        if all(len(stages[n].get('push', [])) >= keyframes for n in names):
            break
    results = {}
    for n in names:
        status = pipes[n].status
        results[n] = {
            'settings': variant_settings[n], 'reference': _reference(n, names), 'precision': status.precision,
            'inference_backend': status.inference_backend,
            'keyframes_timed': len(stages[n].get('push', [])),
            'stages_ms': {k: _summary(v) for k, v in stages[n].items() if v},
            'depth_max_abs_diff_vs_torch': max(depth_diff[n]) if depth_diff[n] else None,
            'notes': list(dict.fromkeys(notes[n] + list(status.notes))),
        }
    defaults = {k: settings.get(k, P.default(k)) for k in SHAPING}
    source = {'sequence': os.path.basename(os.path.normpath(sequence))} if sequence else \
        {'input': f'{input_size[0]}x{input_size[1]}', 'seed': seed}
    return {**source, 'frames_pushed': frames_pushed,
            'warmup_keyframes': warmup, 'threads': torch.get_num_threads(), 'torch': torch.__version__,
            'cpu_count': os.cpu_count(), 'load_average': list(os.getloadavg()), 'settings': settings,
            'defaults': defaults, 'wall_s': round(time.perf_counter() - t_start, 1), 'variants': results}


def markdown(result: Dict) -> str:
    """The stage table: one row per stage, median / p95 per variant, and ratios of medians: each variant to its torch
    variant of the same precision (to the first variant when all are torch)."""
    names = list(result['variants'])
    pairs = [(n, v['reference']) for n, v in result['variants'].items() if v['reference'] not in (None, n)]
    pairs = pairs or [(n, names[0]) for n in names[1:]]
    d = result['defaults']
    shown = ', '.join(f'{k} {v}' for k, v in d.items() if k not in ('processing_width', 'processing_height'))
    source = f"sequence {result['sequence']}" if 'sequence' in result else f"input {result['input']}"
    lines = [f"Keyframe of `Pipeline.push`, {source} -> {d.get('processing_width')}x"
             f"{d.get('processing_height')}; settings {shown}; {result['threads']} torch threads, load average "
             f"{result['load_average'][0]:.1f}; the variants pushed the same frames in turn. ms, median / p95."
             + (f" malloc: {result['malloc']}." if result.get('malloc') else ''), '']
    hdr = ['stage'] + [f"{n} ({result['variants'][n]['keyframes_timed']} kf)" for n in names] + \
        [f'{a} / {b}' for a, b in pairs]
    rows = []
    for key, label in STAGES:
        stats = {n: result['variants'][n]['stages_ms'].get(key) for n in names}
        if all(v is None for v in stats.values()):
            continue
        cells = ['-' if v is None else f"{v['median']:.1f} / {v['p95']:.1f}" for v in stats.values()]
        for a, b in pairs:
            ok = stats[a] is not None and stats[b] is not None and stats[b]['median'] > 0
            cells.append(f"{stats[a]['median'] / stats[b]['median']:.2f}" if ok else '-')
        name = f'&nbsp;&nbsp;{label}' if '.' in key else (f'**{label}**' if key.startswith('push') or key == 'total'
                                                          else label)
        rows.append([name] + cells)
    lines += ['| ' + ' | '.join(hdr) + ' |', '|' + '|'.join('---' for _ in hdr) + '|']
    lines += ['| ' + ' | '.join(r) + ' |' for r in rows] + ['']
    for n in names:
        v = result['variants'][n]
        extra = [f"networks in {v['precision']}"]
        if v['depth_max_abs_diff_vs_torch'] is not None:
            extra.append(f"depth differs from {v['reference']} by at most {v['depth_max_abs_diff_vs_torch']:.2e} m")
        extra += v['notes']
        lines.append(f'- {n}: ' + '; '.join(extra))
    return '\n'.join(lines) + '\n'


def _csv(text: str) -> List[str]:
    return [x.strip() for x in text.split(',') if x.strip()]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='python -m dpv_sensor.benchmarks.keyframe', description=__doc__.split('\n')[0])
    ap.add_argument('--backends', type=_csv, default=['torch'],
                    help='comma list of inference backends (inference_backend), default torch')
    ap.add_argument('--precisions', type=_csv, default=['float32', 'bfloat16'],
                    help='comma list of cpu_precision values (default float32,bfloat16)')
    ap.add_argument('--input', type=parse_size, default=(640, 480), help='camera image size WxH (default 640x480)')
    ap.add_argument('--keyframes', type=int, default=12, help='timed keyframes per variant (default 12)')
    ap.add_argument('--warmup', type=int, default=4, help='keyframe outputs not timed at the start (default 4)')
    ap.add_argument('--seed', type=int, default=3, help='rendered scene (default 3)')
    ap.add_argument('--sequence', default=None, help='a sequence folder to push instead of the rendered camera (its '
                                                      'images at their size, its poses as the odometry)')
    ap.add_argument('--threads', type=int, default=None, help='torch.set_num_threads (default: torch default)')
    ap.add_argument('--set', nargs='*', default=[], metavar='KEY=VALUE', help='estimator settings over the defaults')
    ap.add_argument('--variant', action='append', default=[], metavar='NAME:KEY=VALUE,...',
                    help='a variant of settings, crossed with the backends and precisions (repeatable), e.g. '
                         'no-window:pose_refinement=off')
    ap.add_argument('--malloc', choices=('node', 'glibc'), default='node',
                    help="the C library's malloc settings: the node process's (default; process_memory) or glibc's "
                         'own (to measure them)')
    ap.add_argument('--json', default=None, help='also write the results here')
    ap.add_argument('--markdown', default=None, help='also write the table here')
    a = ap.parse_args(argv)
    malloc_note = "glibc's defaults"
    if a.malloc == 'node':       # before torch starts its threads, as the node does
        from dpv_sensor.ros.process_memory import configure_malloc
        malloc_note = configure_malloc()
    for b in a.backends:
        P.check_value(P.spec('inference_backend'), b)
    for p in a.precisions:
        P.check_value(P.spec('cpu_precision'), p)
    extra = {}
    for item in a.variant:
        name, _, assignments = item.partition(':')
        extra[name] = P.parse_assignments(_csv(assignments))
    result = run(variants(a.backends, a.precisions, extra or None), a.input, a.keyframes, a.warmup, a.seed,
                 settings=P.parse_assignments(a.set), threads=a.threads, progress=True, sequence=a.sequence)
    result['malloc'] = malloc_note
    md = markdown(result)
    print(md)
    for path, text in ((a.json, json.dumps(result, indent=1)), (a.markdown, md)):
        if path:
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
            with open(path, 'w') as f:
                f.write(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
