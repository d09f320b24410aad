"""Calibration of the depth probability volumes: NLL of the GT depth before / after the filter, and
whether the confidence ranks the errors.

    .venv/bin/python -m dpv_sensor.benchmarks.calibration --threads 1 [--data DATA] \
        [--weights dpv_sensor/weights/lite.safetensors] [--synthetic-seeds 0-5] [--sun3d-windows 2] \
        [--width 320 --height 256] [--json out/calibration/calibration.json] [--out out/calibration] [--skip-sun3d]

What is scored (per dataset x source x filter mode):

* **NLL of the GT depth** (:func:`dpv_sensor.core.dpv.nll`, nats, mean over frames) of the quarter-resolution
  *measurement* (before the filter), of the quarter-resolution *filtered* belief (after the filter) and,
  for the network, of R-Net's full-resolution output. All on the network's planes (D, d_min, d_max of
  the checkpoint), so network and classical NLLs are comparable.
* abs_rel, delta1 (metric, frame means), the **confident-half ratio** (abs_rel of the most confident half
  of the pixels / abs_rel of all, frame mean; target <= 0.6; and pooled over all frames, where it also ranks
  whole frames against each other), AUSE and AURG of the sparsification curves
  (:mod:`dpv_sensor.evaluation.metrics`), and whether the mean sparsification curve lies below the random one
  (at every removed fraction > 0).

Everything is computed by :func:`dpv_sensor.training.validation.evaluate_batches` (the training loop's
validation: D-Net / classical measurement of every unrolled step, ``DPVFilter`` in mode none / global /
knet, R-Net), on windows laid out like the training validation (``TrainConfig``: 8 keyframes, causal
5-keyframe windows, i.e. 4 filter steps per window):

* **synthetic**: held-out seeds (0..99, never trained on) rendered by
  :func:`~dpv_sensor.training.validation.render_validation_batches`, keyframes ``val_gap`` frames apart;
* **SUN3D** (``sun3d_3dmatch_frag1`` and ``frag2`` of the shared development data folder, when present;
  never trained on): keyframes chosen by the estimator's own
  :class:`dpv_sensor.stream.keyframes.KeyframeSelector` (its default 5 cm / 5 deg / every 5th
  frame thresholds), ``--sun3d-windows`` runs of consecutive keyframes spread along each sequence, frames
  resized (stretched, like the estimator) to the evaluation size.

Sources: the learned model (``--weights``), and the classical plane-sweep ZNCC model
(:class:`dpv_sensor.core.classical.ClassicalMeasurement`) with its softmax **temperature tuned on training
data only**: the temperature in ``--temperatures`` that minimises the mean measurement NLL on synthetic
scenes with *training* seeds (``--tune-seeds``, >= ``TRAIN_SEED_BASE``; held-out seeds are refused and
SUN3D is never used). The classical model at its default temperature (0.07) is reported as well
(when the tuned one differs; the grid contains 0.07, so tuning can only keep or beat it on training data).

Default size 320x256 is the product's processing size (``EstimatorConfig``); the default run (6
synthetic windows, 2 windows per SUN3D fragment, 12 temperatures x 6 tuning scenes) takes about 1.5
minutes on one core (``--threads 1``). Outputs: the printed table, ``--json`` (everything, including the tuning curve
and the plotted sparsification curves), and ``--out``/sparsification_<dataset>.png (the network's best
mode and the tuned classical model's best mode: sparsification vs oracle vs random).
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time
from typing import Dict, List, Optional, Sequence as Seq, Tuple

import numpy as np
import torch

from dpv_sensor.core import dpv as dpvops
from dpv_sensor.core.classical import ClassicalMeasurement
from dpv_sensor.training.dataset import (TRAIN_SEED_BASE, VAL_SEEDS, WindowLayout, check_heldout_seeds,
                                sample_from_sequence)
from dpv_sensor.training.config import TrainConfig
from dpv_sensor.training.validation import evaluate_batches, render_validation_batches
from dpv_sensor import params as P
from dpv_sensor.cli import add_setting
from dpv_sensor.common import to_jsonable

__all__ = ['run', 'main', 'sun3d_batches', 'tune_temperature', 'format_table', 'DEFAULT_TEMPERATURES',
           'SUN3D_SEQUENCES', 'CONFIDENT_HALF_TARGET']

SUN3D_SEQUENCES = ('sun3d_3dmatch_frag1', 'sun3d_3dmatch_frag2')
DEFAULT_TEMPERATURE = ClassicalMeasurement().temperature              # 0.07
# 0.02 .. 0.3 log-spaced, plus the default, so the tuned value is never worse than it on training data
DEFAULT_TEMPERATURES = tuple(sorted(set(np.round(np.geomspace(0.02, 0.3, 11), 4).tolist()) | {DEFAULT_TEMPERATURE}))
DEFAULT_TUNE_SEEDS = tuple(range(TRAIN_SEED_BASE, TRAIN_SEED_BASE + 6))
CONFIDENT_HALF_TARGET = 0.6                                           # issue: most confident half <= 0.6 x all


# ----------------------------------------------------------------------------------------------
# data
# ----------------------------------------------------------------------------------------------

def _layout(num_keyframes: int) -> WindowLayout:
    """The training validation's window layout (window, reference position) unrolled over all complete
    windows of ``num_keyframes`` keyframes (as :func:`render_validation_batches` does)."""
    d = TrainConfig()
    return WindowLayout(steps=num_keyframes - d.window + 1, window=d.window, ref_position=d.ref_position)


def estimator_keyframes(seq) -> List[int]:
    """Frame indices the streaming estimator would take as keyframes (its default thresholds, GT poses)."""
    from dpv_sensor.stream.estimator import EstimatorConfig
    from dpv_sensor.stream.keyframes import KeyframeSelector
    cfg = EstimatorConfig()
    sel = KeyframeSelector(cfg.keyframe_translation, cfg.keyframe_rotation_deg, cfg.keyframe_max_interval)
    return [i for i in range(len(seq)) if sel.decide(np.asarray(seq.pose(i))).is_keyframe]


def sun3d_batches(folders: Seq[str], windows_per_seq: int, num_keyframes: int, width: int,
                  height: int) -> Tuple[List[Dict[str, torch.Tensor]], List[Dict]]:
    """Batches (B = 1) of ``num_keyframes`` consecutive estimator keyframes, ``windows_per_seq`` runs
    spread evenly along each sequence (they overlap when the sequence is short), frames resized to
    width x height. Returns (batches, [{'sequence', 'frames'}] describing each)."""
    from dpv_sensor.data.sequence import Sequence
    lay = _layout(num_keyframes)
    batches, info = [], []
    for folder in folders:
        seq = Sequence(folder)
        kf = estimator_keyframes(seq)
        if len(kf) < num_keyframes:
            print(f'{folder}: only {len(kf)} keyframes (< {num_keyframes}); skipped', file=sys.stderr)
            continue
        rs = seq.resized(width, height)
        n_start = len(kf) - num_keyframes + 1
        starts = sorted(set(int(round(x)) for x in np.linspace(0, n_start - 1, max(1, windows_per_seq))))
        for st in starts:
            ids = kf[st:st + num_keyframes]
            smp = sample_from_sequence(rs, ids, lay, np.random.default_rng(0), augment=None, seed=-1 - ids[0])
            batches.append({k: v[None] for k, v in smp.items()})
            info.append({'sequence': pathlib.Path(folder).name, 'frames': ids})
    return batches, info


class _Ticking:
    """Iterate a list of batches and advance a progress bar per batch (evaluate_batches enumerates it)."""

    def __init__(self, items, bar):
        self.items, self.bar = items, bar

    def __len__(self):
        return len(self.items)

    def __iter__(self):
        for x in self.items:
            yield x
            if self.bar is not None:
                self.bar.update(1)


# ----------------------------------------------------------------------------------------------
# temperature tuning (training seeds only)
# ----------------------------------------------------------------------------------------------

def check_tune_seeds(seeds: Seq[int]) -> None:
    """Refuse anything that is not a training seed (held-out seeds are what we report on)."""
    if not seeds:
        raise ValueError('need at least one tuning seed')
    for s in seeds:
        if s in VAL_SEEDS or s < TRAIN_SEED_BASE:
            raise ValueError(f'tuning seed {s} is not a training seed: the temperature is tuned on training '
                             f'data only (seeds >= {TRAIN_SEED_BASE}); seeds {VAL_SEEDS.start}..'
                             f'{VAL_SEEDS.stop - 1} are held out for reporting')


def tune_temperature(batches, depths_d: torch.Tensor, temperatures: Seq[float], bar=None,
                     **classical_kw) -> Tuple[float, Dict[float, float]]:
    """The temperature of ``temperatures`` with the lowest mean measurement NLL (``nll_meas_q``, before
    the filter) of the classical model on ``batches``; returns (best, {temperature: nll})."""
    if not temperatures:
        raise ValueError('need at least one temperature')
    d_min, d_max, D = float(depths_d[0]), float(depths_d[-1]), int(depths_d.numel())
    curve = {}
    for t in temperatures:
        cm = ClassicalMeasurement(d_min, d_max, D, temperature=float(t), **classical_kw)
        r = evaluate_batches(None, _Ticking(batches, bar), depths_d, 'cpu', modes=('none',), classical=cm,
                             keep_last=False)
        curve[float(t)] = float(r['classical_none']['nll_meas_q'])
    finite = {t: v for t, v in curve.items() if math.isfinite(v)}
    if not finite:
        raise RuntimeError('temperature tuning: no finite NLL')
    best = min(finite, key=finite.get)
    return best, curve


# ----------------------------------------------------------------------------------------------
# the benchmark
# ----------------------------------------------------------------------------------------------

def _below_random(c: Optional[Dict[str, np.ndarray]]) -> Tuple[Optional[bool], float]:
    """(sparsification <= random at every removed fraction > 0, share of those fractions where it is)."""
    if c is None:
        return None, float('nan')
    s, r = np.asarray(c['sparsification'])[1:], np.asarray(c['random'])[1:]
    ok = np.isfinite(s) & np.isfinite(r)
    if not ok.any():
        return None, float('nan')
    below = s[ok] <= r[ok] + 1e-12
    return bool(below.all()), float(below.mean())


def _evaluate_dataset(name: str, batches, model, depths_d, classicals: Dict[str, ClassicalMeasurement],
                      bar, readout: str = dpvops.DEFAULT_READOUT, confidence: str = dpvops.DEFAULT_CONFIDENCE
                      ) -> Tuple[List[Dict], Dict[str, Dict]]:
    """Rows of one dataset (net modes, then every classical source) and the curves per row key."""
    rows, curves = [], {}
    jobs = [('net', model, None)] + [(label, None, cm) for label, cm in classicals.items()]
    for label, net, cm in jobs:
        if label == 'net' and net is None:
            continue
        modes = ('none', 'global', 'knet') if net is not None else ('none', 'global')
        res = evaluate_batches(net, _Ticking(batches, bar), depths_d, 'cpu', modes=modes, classical=cm,
                               keep_last=False, curves=True, readout=readout, confidence=confidence)
        res.pop('examples', None)
        src = 'net' if net is not None else 'classical'
        for mode in modes:
            e = dict(res[f'{src}_{mode}'])
            c = e.pop('sparsification_curves', None)
            below, share = _below_random(c)
            row = {'dataset': name, 'source': label, 'mode': mode, **e, 'below_random': below,
                   'below_random_share': share,
                   'confident_half_ok': bool(e['confident_half_ratio'] <= CONFIDENT_HALF_TARGET)
                   if math.isfinite(e['confident_half_ratio']) else None}
            if cm is not None:
                row['temperature'] = cm.temperature
            rows.append(row)
            curves[f'{label} {mode}'] = c
    return rows, curves


def _best(rows: List[Dict], source: str) -> Optional[Dict]:
    cand = [r for r in rows if r['source'] == source and math.isfinite(r['abs_rel'])]
    return min(cand, key=lambda r: r['abs_rel']) if cand else None


def run(model, *, synthetic_seeds: Seq[int] = tuple(range(6)), sun3d_windows: int = 2,
        width: int = P.default('processing_width'), height: int = P.default('processing_height'),
        tune_seeds: Seq[int] = DEFAULT_TUNE_SEEDS,
        temperatures: Seq[float] = DEFAULT_TEMPERATURES, num_keyframes: Optional[int] = None,
        gap: Optional[int] = None, skip_sun3d: bool = False, data_dir=None, out: Optional[str] = None,
        progress: bool = True, quiet: bool = False, readout: str = dpvops.DEFAULT_READOUT,
        confidence: str = dpvops.DEFAULT_CONFIDENCE) -> Dict:
    """Run the whole benchmark (see the module docstring); returns a JSON-ready dict with ``rows``,
    ``temperature`` (tuned, default, grid, tuning NLL per temperature), ``datasets`` and ``plots``.

    ``model``: a :class:`dpv_sensor.core.nets.model.DPVNet` (its preset gives the planes). ``num_keyframes``
    and ``gap`` default to the training validation's (``TrainConfig.val_keyframes`` / ``val_gap``).
    ``readout``: how depth and confidence are read from the DPVs (the node's ``depth_readout``);
    ``confidence``: which confidence is ranked (the node's ``confidence``, ratio band 1.25).
    """
    from tqdm import tqdm
    t_start = time.time()
    check_tune_seeds(tune_seeds)
    check_heldout_seeds(synthetic_seeds)
    if width % 4 or height % 4:
        raise ValueError(f'width and height must be multiples of 4, got {width}x{height}')
    tc = TrainConfig()
    num_keyframes = int(num_keyframes or tc.val_keyframes)
    gap = int(gap or tc.val_gap)
    lay = _layout(num_keyframes)
    p = model.preset
    depths_d = dpvops.depth_planes(p.d_min, p.d_max, p.num_planes)
    model.eval()

    datasets: Dict[str, Dict] = {}
    tune = render_validation_batches(tune_seeds, num_keyframes, gap, width, height, lay, split='train')
    if synthetic_seeds:
        datasets['synthetic'] = {'batches': render_validation_batches(synthetic_seeds, num_keyframes, gap, width,
                                                                      height, lay),
                                 'what': f'held-out synthetic seeds {list(synthetic_seeds)}, '
                                         f'keyframes {gap} frames apart'}
    if not skip_sun3d and data_dir is None:
        print('no --data folder given: the SUN3D part is skipped', file=sys.stderr)
    elif not skip_sun3d:
        folders = [pathlib.Path(data_dir) / n for n in SUN3D_SEQUENCES
                   if (pathlib.Path(data_dir) / n / 'poses.txt').is_file()]
        if not folders:
            print(f'SUN3D not found under {data_dir}; skipped', file=sys.stderr)
        else:
            b, info = sun3d_batches([str(f) for f in folders], sun3d_windows, num_keyframes, width, height)
            if b:
                datasets['sun3d'] = {'batches': b, 'what': 'SUN3D (3DMatch fragments), estimator keyframes',
                                     'windows': info}

    n_win = sum(len(d['batches']) for d in datasets.values())
    # progress: tuning (temperatures x tuning windows) + per dataset: net, tuned and default classical
    bar = tqdm(total=len(temperatures) * len(tune) + n_win * 3, desc='calibration', unit='window',
               disable=not progress, dynamic_ncols=True, mininterval=1.0 if sys.stderr.isatty() else 30.0)
    try:
        t0 = time.time()
        best_t, tune_curve = tune_temperature(tune, depths_d, temperatures, bar=bar)
        tune_s = time.time() - t0
        classicals = {f'classical T={best_t:g} (tuned)': ClassicalMeasurement(p.d_min, p.d_max, p.num_planes,
                                                                                temperature=best_t)}
        if abs(best_t - DEFAULT_TEMPERATURE) > 1e-12:
            classicals[f'classical T={DEFAULT_TEMPERATURE:g} (default)'] = ClassicalMeasurement(
                p.d_min, p.d_max, p.num_planes, temperature=DEFAULT_TEMPERATURE)
        else:
            bar.total -= n_win
        rows, plots, curves_out = [], {}, {}
        for name, d in datasets.items():
            r, curves = _evaluate_dataset(name, d['batches'], model, depths_d, classicals, bar, readout, confidence)
            rows += r
            best_net = _best(r, 'net')
            tuned_label = next(iter(classicals))
            best_cls = _best(r, tuned_label)
            sel = {}
            for b in (best_net, best_cls):
                if b is not None and curves.get(f"{b['source']} {b['mode']}") is not None:
                    sel[f"{b['source'].split(' (')[0]} {b['mode']}"] = curves[f"{b['source']} {b['mode']}"]
            curves_out[name] = {k: {kk: np.asarray(vv).tolist() for kk, vv in c.items()} for k, c in sel.items()}
            if out and sel:
                from dpv_sensor.evaluation.plots import sparsification_plot
                path = pathlib.Path(out) / f'sparsification_{name}.png'
                sparsification_plot(sel, path, title=f'{name}: sparsification ({len(d["batches"])} windows, '
                                                     f'{width}x{height})')
                plots[name] = str(path)
    finally:
        bar.close()
    result = {
        'settings': {'width': width, 'height': height, 'num_keyframes': num_keyframes, 'synthetic_gap': gap,
                     'window': lay.window, 'ref_position': lay.ref_position, 'filter_steps_per_window': lay.steps,
                     'planes': {'D': p.num_planes, 'd_min': p.d_min, 'd_max': p.d_max},
                     'synthetic_seeds': list(synthetic_seeds), 'sun3d_windows_per_sequence': sun3d_windows,
                     'threads': torch.get_num_threads()},
        'temperature': {'tuned': best_t, 'default': DEFAULT_TEMPERATURE, 'grid': [float(t) for t in temperatures],
                        'tuning_nll_meas_q': {f'{t:g}': v for t, v in tune_curve.items()},
                        'tuning_seeds': list(tune_seeds), 'tuning_windows': len(tune),
                        'objective': 'mean NLL of the GT under the classical measurement DPV (1/4 res, before '
                                     'the filter) on synthetic training seeds', 'seconds': tune_s},
        'datasets': {n: {k: v for k, v in d.items() if k != 'batches'} | {'num_windows': len(d['batches'])}
                     for n, d in datasets.items()},
        'rows': rows,
        'sparsification_curves': curves_out,
        'plots': plots,
        'confident_half_target': CONFIDENT_HALF_TARGET,
        'seconds': time.time() - t_start,
    }
    if not quiet:
        print(format_table(result))
    return result


def _f(x, fmt='{:.3f}') -> str:
    return '-' if x is None or (isinstance(x, float) and not math.isfinite(x)) else fmt.format(x)


def format_table(result: Dict) -> str:
    """The printed table: rows dataset x source x filter mode."""
    hdr = ['dataset', 'source', 'mode', 'NLL meas 1/4', 'NLL filt 1/4', 'NLL full', 'abs_rel', 'delta1',
           f'conf-half (<={CONFIDENT_HALF_TARGET:g})', 'pooled', 'AUSE', 'AURG', 'below random']
    lines = []
    for r in result['rows']:
        below = '-' if r['below_random'] is None else ('yes' if r['below_random'] else
                                                       f"no ({r['below_random_share']:.0%} of points)")
        ch = _f(r['confident_half_ratio'], '{:.2f}')
        if r.get('confident_half_ok') is not None:
            ch += ' ok' if r['confident_half_ok'] else ' NO'
        lines.append([r['dataset'], r['source'], r['mode'], _f(r['nll_meas_q']), _f(r['nll_filtered_q']),
                      _f(r['nll_full']), _f(r['abs_rel'], '{:.4f}'), _f(r['delta1']), ch,
                      _f(r.get('confident_half_ratio_pooled'), '{:.2f}'), _f(r['ause'], '{:.4f}'),
                      _f(r['aurg'], '{:.4f}'), below])
    w = [max(len(h), *(len(row[i]) for row in lines)) if lines else len(h) for i, h in enumerate(hdr)]

    def fmt(cells):
        return '  '.join(c.ljust(w[i]) if i < 3 else c.rjust(w[i]) for i, c in enumerate(cells))

    t = result['temperature']
    s = result['settings']
    head = (f"calibration at {s['width']}x{s['height']}, {s['num_keyframes']} keyframes/window "
            f"({s['filter_steps_per_window']} filter steps), D={s['planes']['D']} planes "
            f"{s['planes']['d_min']:g}..{s['planes']['d_max']:g} m; windows: "
            + ', '.join(f"{n} {d['num_windows']}" for n, d in result['datasets'].items()) + '\n'
            f"classical temperature: tuned {t['tuned']:g} (default {t['default']:g}) on {t['tuning_windows']} "
            f"synthetic training-seed windows; tuning NLL: "
            + ' '.join(f'{k}:{v:.3f}' for k, v in t['tuning_nll_meas_q'].items()))
    return '\n'.join([head, fmt(hdr), fmt(['-' * x for x in w])] + [fmt(row) for row in lines])


def main(argv: Optional[List[str]] = None) -> Dict:
    from dpv_sensor.training.dataset import parse_seeds
    ap = argparse.ArgumentParser(prog='python -m dpv_sensor.benchmarks.calibration',
                                 description=__doc__.split('\n\n')[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument('--weights', default=None, help='checkpoint (default: dpv_sensor/weights/lite.safetensors)')
    ap.add_argument('--synthetic-seeds', default='0-5', help="held-out seeds, e.g. '0-5' or '0,3,7' ('' = none)")
    ap.add_argument('--sun3d-windows', type=int, default=2, help='windows per SUN3D fragment')
    ap.add_argument('--skip-sun3d', action='store_true')
    ap.add_argument('--data', default=None, help='folder holding the SUN3D sequences (none: SUN3D skipped)')
    add_setting(ap, 'processing_width', '--width', dest='width')
    add_setting(ap, 'processing_height', '--height', dest='height')
    ap.add_argument('--keyframes', type=int, default=None,
                    help='keyframes per window (default: TrainConfig.val_keyframes)')
    ap.add_argument('--tune-seeds', default=f'{DEFAULT_TUNE_SEEDS[0]}-{DEFAULT_TUNE_SEEDS[-1]}',
                    help=f'training seeds (>= {TRAIN_SEED_BASE}) the classical temperature is tuned on')
    ap.add_argument('--temperatures', default=','.join(f'{t:g}' for t in DEFAULT_TEMPERATURES),
                    help='comma-separated temperature grid')
    ap.add_argument('--json', default=None, help='write all results here')
    ap.add_argument('--out', default='out/calibration', help='folder for the sparsification PNGs')
    ap.add_argument('--threads', type=int, default=1)
    add_setting(ap, 'depth_readout', '--readout', dest='readout')
    add_setting(ap, 'confidence')
    ap.add_argument('--no-progress', action='store_true')
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    from dpv_sensor.core.nets.checkpoint import default_weights_path
    from dpv_sensor.benchmarks.heldout import load_model
    weights = a.weights or str(default_weights_path('lite'))
    model, meta = load_model(weights)
    res = run(model, synthetic_seeds=parse_seeds(a.synthetic_seeds), sun3d_windows=a.sun3d_windows,
              width=a.width, height=a.height, tune_seeds=parse_seeds(a.tune_seeds),
              temperatures=[float(x) for x in a.temperatures.split(',') if x.strip()],
              num_keyframes=a.keyframes, skip_sun3d=a.skip_sun3d, data_dir=a.data, out=a.out,
              progress=not a.no_progress, readout=a.readout, confidence=a.confidence)
    res['weights'] = {'path': weights, 'steps': meta.get('steps'), 'preset': model.preset.name}
    res['command'] = ' '.join(['python -m dpv_sensor.benchmarks.calibration']
                              + list(argv if argv is not None else sys.argv[1:]))
    print(f"total {res['seconds']:.0f} s; plots: {', '.join(res['plots'].values()) or '-'}")
    if a.json:
        pathlib.Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        with open(a.json, 'w') as f:
            json.dump(to_jsonable(res), f, indent=1)
    return res


if __name__ == '__main__':
    main()
