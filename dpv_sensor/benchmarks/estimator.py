"""End-to-end time of ``Estimator.push()`` per keyframe: classical model and each network preset.

    python -m dpv_sensor.benchmarks.estimator                      # classical, lite, paper at 320x256, CPU
    python -m dpv_sensor.benchmarks.estimator --models classical,lite --keyframes 8 --threads 2
    python -m dpv_sensor.benchmarks.estimator --device cuda --json out/estimator.json

What is timed: ``push()`` of a keyframe, wall clock, from the uint8 input image to the finished
``DepthOutput`` (resize, feature extraction of the new frame - sources come from the cache -,
measurement, filter step incl. K-Net for ``knet``, R-Net / upsampling, resize back to the input size and
conversion to numpy). Every frame is a keyframe (``keyframe_max_interval=1``), the window is causal;
the first ``window_size`` keyframes fill the window and are not timed, so every timed keyframe has 4
source views and the filter is in steady state. Input frames come from the procedural renderer
(``data.synthetic.render_sequence``) at the processing size, so no resize happens on the way in.

Weights: a network preset uses ``dpv_sensor/weights/<preset>.safetensors`` when that loads; otherwise the
net is **randomly initialised** (same cost; outputs meaningless) and the report says so. Filter mode:
``knet`` for the networks, ``global`` for the classical model (K-Net needs a network).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from typing import Dict, List, Optional

import torch
from dpv_sensor import params as P
from dpv_sensor.cli import add_setting

__all__ = ['run', 'main']


def _frames(width: int, height: int, count: int, seed: int = 3):
    from dpv_sensor.data.synthetic import render_sequence
    from dpv_sensor.stream.frame import Frame
    seq = render_sequence(seed=seed, num_frames=count, width=width, height=height, lazy=True)
    K = seq.K
    return [Frame(stamp=seq.stamp(i), image=seq.image(i), K_33=K, T_world_cam_44=seq.pose(i), frame_id='camera')
            for i in range(count)]


def _estimator(model_name: str, width: int, height: int, device: str):
    from dpv_sensor.stream.estimator import Estimator, EstimatorConfig
    base = dict(processing_width=width, processing_height=height, device=device, keyframe_translation=0.0,
                keyframe_rotation_deg=0.0, keyframe_max_interval=1, window_mode='causal')
    if model_name == 'classical':
        cfg = EstimatorConfig(measurement='classical', filter_mode='global', **base)
        return Estimator(cfg), 'classical (NCC plane sweep, no weights)'
    cfg = EstimatorConfig(measurement='auto', preset=model_name, filter_mode='knet', **base)
    import logging
    quiet = logging.getLogger('dpv_sensor.benchmarks.quiet')
    quiet.addHandler(logging.NullHandler())
    quiet.propagate = False
    est = Estimator(cfg, logger=quiet)
    if est.measurement == 'network':
        status = est.status
        ck = status.checkpoint or {}
        return est, f'{model_name}: weights {status.weights} (training steps: {ck.get("steps")})'
    from dpv_sensor.core.nets.model import DPVNet
    torch.manual_seed(0)
    est = Estimator(cfg, model=DPVNet(model_name), logger=quiet)
    return est, f'{model_name}: RANDOM-INIT weights (no trained checkpoint loads); cost is the same'


def run(models=('classical', 'lite', 'paper'), width: int = P.default('processing_width'),
        height: int = P.default('processing_height'), keyframes: int = 6, device: str = P.default('device'),
        threads: Optional[int] = None) -> Dict:
    """Time ``keyframes`` steady-state keyframe pushes per model; returns a dict of results."""
    if threads:
        torch.set_num_threads(int(threads))
    frames = None
    results = {'width': width, 'height': height, 'device': device, 'threads': torch.get_num_threads(),
               'models': {}}
    for name in models:
        est, what = _estimator(name, width, height, device)
        warm = est.config.window_size
        if frames is None or len(frames) < warm + keyframes:
            frames = _frames(width, height, warm + keyframes)
        totals: List[float] = []
        stages: Dict[str, List[float]] = {}
        for i, f in enumerate(frames[:warm + keyframes]):
            if device.startswith('cuda'):
                torch.cuda.synchronize()
            t = time.perf_counter()
            out = est.push(f)
            if device.startswith('cuda'):
                torch.cuda.synchronize()
            ms = (time.perf_counter() - t) * 1000.0
            if i < warm:
                continue
            assert out is not None and out.is_keyframe
            totals.append(ms)
            for k, v in out.timings_ms.items():
                stages.setdefault(k, []).append(v)
        results['models'][name] = {
            'what': what, 'measurement': est.measurement, 'filter_mode': est.filter_mode,
            'keyframes_timed': len(totals),
            'push_ms_median': statistics.median(totals), 'push_ms_mean': statistics.fmean(totals),
            'push_ms_min': min(totals), 'push_ms_max': max(totals),
            'stages_ms_median': {k: statistics.median(v) for k, v in stages.items()},
        }
    return results


def _print(results: Dict) -> None:
    print(f"Estimator.push() per keyframe, {results['width']}x{results['height']}, device {results['device']}, "
          f"{results['threads']} torch threads, causal window of 5 (4 sources), steady state")
    for name, r in results['models'].items():
        print(f"\n{name:9s} {r['what']}")
        print(f"          filter {r['filter_mode']}; {r['keyframes_timed']} keyframes: median "
              f"{r['push_ms_median']:.0f} ms, mean {r['push_ms_mean']:.0f} ms "
              f"(min {r['push_ms_min']:.0f}, max {r['push_ms_max']:.0f})")
        st = ', '.join(f'{k} {v:.0f}' for k, v in r['stages_ms_median'].items() if k != 'total')
        print(f'          stages (median ms): {st}')


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog='python -m dpv_sensor.benchmarks.estimator', description=__doc__.split('\n')[0])
    ap.add_argument('--models', default='classical,lite,paper', help='comma list of classical, lite, paper')
    add_setting(ap, 'processing_width', '--width', dest='width')
    add_setting(ap, 'processing_height', '--height', dest='height')
    ap.add_argument('--keyframes', type=int, default=6, help='timed keyframes per model (after 5 warm-up)')
    add_setting(ap, 'device')
    ap.add_argument('--threads', type=int, default=None, help='torch.set_num_threads (default: torch default)')
    ap.add_argument('--json', default=None, help='also write the results here')
    args = ap.parse_args(argv)
    models = [m.strip() for m in args.models.split(',') if m.strip()]
    results = run(models, args.width, args.height, args.keyframes, args.device, args.threads)
    _print(results)
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
