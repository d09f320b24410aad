"""`make bench` / `ros2 run dpv_sensor bench`: one speed and memory report of the virtual depth camera.

    python -m dpv_sensor.tools.bench                                    # lite + paper, 320x256 + 640x480, CPU (+ CUDA)
    python -m dpv_sensor.tools.bench --presets lite --sizes 320x256 --devices cpu --out out/bench

For every device (``cpu``; ``cuda`` only when ``torch.cuda.is_available()``), size (WxH, the processing size) and
network preset it aggregates the per-layer benchmark scripts of ``dpv_sensor.benchmarks`` and a short run of the
node, and writes OUT/bench.md (printed too) and OUT/bench.json:

1. **Per-stage latency** (median of ``--repeats`` after a warm-up, ms):
   ``benchmarks.nets.run_one``   feature extraction (one image), cost volume (4 cached source views), K-Net, R-Net
                                 and the whole network part of a keyframe (source features cached);
   ``benchmarks.core.run``       filter predict (``warp_volume``) and update (global damping) at the preset's volume
                                 (1/4 of the size, the preset's D planes), and the classical NCC cost volume at the
                                 classical model's default D = 64 (the no-weights fallback).
2. **Keyframes per second of the estimator** (``benchmarks.estimator.run``): steady-state ``Estimator.push()`` of a
   keyframe (causal window, 4 sources: resize, features, measurement, filter with K-Net, R-Net, output) for the
   classical model and each preset, with its stage split; peak memory of that run (growth of the process's peak
   RSS via /proc/self/clear_refs + VmHWM, and ``torch.cuda.max_memory_allocated`` on CUDA).
3. **The default keyframe** (``benchmarks.keyframe.run``): ``Pipeline.push`` of a keyframe at the node's defaults
   (640x480 camera, centred window, refinement window, K-Net, readout, edge filter, output), every stage's median
   and p95, in float32 and bfloat16 on the CPU, for each ``--backends`` entry (``inference_backend``), the variants
   pushed the same frames in turn; ``--keyframe-keyframes`` keyframes each after ``--keyframe-warmup`` untimed ones.
4. **End to end through the node**: the node is started as its own process (``python -m dpv_sensor.ros.node``) with
   the preset, the device and the size as its processing size; a rendered sequence at that size is played into it
   in a loop at ``--e2e-hz`` images/s (``BagPlayer``, stamps rebased to the wall clock) for ``--e2e-seconds`` (longer
   until ``--e2e-min-outputs`` depth images arrived, at most ``--e2e-max-seconds``). Reported: depth outputs per
   second, latency = receipt time of the depth image - its image stamp (median, p95), the node's own receipt ->
   publish time, images the node dropped (newest-wins mailbox: expected when it is slower than the camera) and the
   node process's peak RSS (VmHWM).

Weights: a preset whose packaged checkpoint (``dpv_sensor/weights/<preset>.safetensors``) does not load runs with
**randomly initialised** weights - the same cost, meaningless depth; the report says which. For the node such a
preset gets a random-init checkpoint written to OUT/weights/ (so the node runs the network, not the classical
fallback). The machine may be shared: the load average before and after is in the report, and every figure is a
median. No thresholds: this is a measurement, not a test.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import signal
import statistics
import subprocess
import sys
import threading
import time
from typing import Any, Dict, List, Optional, Tuple

from dpv_sensor.ros.process_memory import proc_status_kib
from dpv_sensor.client.node_process import ClientNode, node_command
from dpv_sensor.cli import tool_argv

REPO = pathlib.Path(__file__).resolve().parents[2]
PARTS = ('nets', 'core', 'estimator', 'keyframe', 'node')
CLASSICAL_PLANES = 64      # the node's default num_planes (the classical model's D)


# --------------------------------------------------------------------------------------------------------------
# memory helpers
# --------------------------------------------------------------------------------------------------------------



class PeakMemory:
    """Peak memory over a block: process peak RSS (VmHWM, reset through /proc/self/clear_refs when allowed) and
    its growth over the RSS at the start; CUDA max_memory_allocated (growth over the allocation at the start)."""

    def __init__(self, device: str):
        self.device = device
        self.rss_peak_mib = self.rss_growth_mib = self.cuda_peak_mib = None
        self.method = None

    def __enter__(self):
        import torch
        try:
            with open('/proc/self/clear_refs', 'w') as f:
                f.write('5')
            self._reset = True
        except OSError:
            self._reset = False
        self._rss0 = proc_status_kib('self', 'VmRSS')
        if self.device.startswith('cuda'):
            torch.cuda.synchronize()
            self._cuda0 = torch.cuda.memory_allocated()
            torch.cuda.reset_peak_memory_stats()
        return self

    def __exit__(self, *exc):
        import torch
        hwm = proc_status_kib('self', 'VmHWM')
        if hwm is not None:
            self.rss_peak_mib = hwm / 1024.0
            if self._rss0 is not None:
                self.rss_growth_mib = max(0, hwm - self._rss0) / 1024.0
            self.method = 'VmHWM (reset per run)' if self._reset else 'VmHWM (process lifetime peak)'
        if self.device.startswith('cuda'):
            torch.cuda.synchronize()
            self.cuda_peak_mib = (torch.cuda.max_memory_allocated() - self._cuda0) / 2 ** 20
        return False


# --------------------------------------------------------------------------------------------------------------
# the parts
# --------------------------------------------------------------------------------------------------------------
def bench_nets(presets, sizes, device, repeats, warmup) -> List[Dict]:
    from dpv_sensor.benchmarks import nets as NB
    out = []
    for preset in presets:
        for size in sizes:
            _say(f'nets: {preset} {size[0]}x{size[1]} on {device}')
            out.append(NB.run_one(preset, tuple(size), device, repeats=repeats, warmup=warmup))
    return out


def bench_core(presets, sizes, device, repeats) -> List[Dict]:
    """core.run once per distinct D: each preset's planes, plus the classical model's."""
    from dpv_sensor.benchmarks import core as CB
    from dpv_sensor.core.nets.presets import get_preset
    planes = {p: int(get_preset(p).num_planes) for p in presets}
    out = []
    for D in sorted(set(planes.values()) | {CLASSICAL_PLANES}):
        _say(f'core: D={D} on {device}')
        r = CB.run(sizes=[tuple(s) for s in sizes], num_planes=D, device=device, repeats=repeats)
        for row in r['results']:
            row = dict(row)
            row['num_planes'] = D
            row['presets'] = [p for p, d in planes.items() if d == D]
            row['classical'] = D == CLASSICAL_PLANES
            row['device'] = device
            out.append(row)
    return out


def bench_estimator(models, sizes, device, keyframes) -> List[Dict]:
    from dpv_sensor.benchmarks import estimator as EB
    out = []
    for size in sizes:
        for model in models:
            _say(f'estimator: {model} {size[0]}x{size[1]} on {device}')
            with PeakMemory(device) as mem:
                r = EB.run(models=(model,), width=size[0], height=size[1], keyframes=keyframes, device=device)
            m = r['models'][model]
            out.append({'model': model, 'width': size[0], 'height': size[1], 'device': device,
                        'threads': r['threads'], **m,
                        'keyframes_per_s': 1000.0 / m['push_ms_median'] if m['push_ms_median'] > 0 else None,
                        'rss_peak_mib': mem.rss_peak_mib, 'rss_growth_mib': mem.rss_growth_mib,
                        'cuda_peak_mib': mem.cuda_peak_mib, 'memory_method': mem.method})
    return out


def bench_keyframe(device: str, backends: List[str], keyframes: int, warmup: int,
                   input_size: Tuple[int, int] = (640, 480)) -> Dict:
    from dpv_sensor.benchmarks import keyframe as KB
    precisions = ['float32', 'bfloat16'] if device == 'cpu' else ['auto']
    _say(f'keyframe: node defaults on {device}, {input_size[0]}x{input_size[1]} camera, backends '
         f'{",".join(backends)}, {",".join(precisions)}')
    r = KB.run(KB.variants(backends, precisions), input_size=input_size, keyframes=keyframes, warmup=warmup,
               settings={'device': device})
    r['device'] = device
    return r


def _node_weights(preset: str, out: pathlib.Path) -> Tuple[str, str]:
    """(weights parameter, what) for a node run of `preset`: the packaged checkpoint when it loads, else a
    random-init checkpoint written under OUT/weights."""
    from dpv_sensor.stream.estimator import default_weights_path
    from dpv_sensor.core.nets.checkpoint import load_checkpoint, read_metadata, save_checkpoint
    path = default_weights_path(preset)
    try:
        load_checkpoint(str(path), preset=preset)
        steps = read_metadata(path).get('steps')
        return str(path), f'packaged weights ({steps} training steps)'
    except Exception:
        pass
    import torch
    from dpv_sensor.core.nets.model import DPVNet
    rnd = out / 'weights' / f'{preset}_random_init.safetensors'
    if not rnd.exists():
        torch.manual_seed(0)
        save_checkpoint(rnd, DPVNet(preset), {'training_data': 'none: random initialisation (bench: cost only)',
                                              'steps': 0})
    return str(rnd), 'RANDOM-INIT weights (no trained checkpoint): cost only'


def _bench_bag(out: pathlib.Path, size, frames: int, seed: int, cache: Dict) -> pathlib.Path:
    """A rendered sequence at `size` as a bag (rendered once at the largest size, resized for the others)."""
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.data.synthetic import render_sequence
    w, h = size
    bag = out / 'bags' / f'seed{seed}_{frames}f_{w}x{h}'
    if bag.exists():
        return bag
    if 'seq' not in cache:
        W, H = cache['largest']
        _say(f'node: rendering {frames} frames at {W}x{H} (seed {seed})')
        cache['seq'] = render_sequence(seed, frames, width=W, height=H).materialize()
    seq = cache['seq']
    if (w, h) != seq.size:
        seq = seq.resized(w, h)
    R.write_sequence_bag(bag, seq, odom_rate=100.0, progress=False)
    return bag


def bench_node(presets, sizes, device, out: pathlib.Path, *, hz: float, seconds: float, min_outputs: int,
               max_seconds: float, start_timeout: float, frames: int, seed: int, threads: Optional[int]) -> List[Dict]:
    """Start the node per preset x size, play a looped synthetic bag at `hz` with live stamps, measure."""
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.client.ros_io import BagPlayer, OutputCollector

    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([str(REPO)] + [p for p in env.get('PYTHONPATH', '').split(os.pathsep) if p])
    env.setdefault('PYTHONUNBUFFERED', '1')
    if threads:
        env['OMP_NUM_THREADS'] = str(threads)
    cache = {'largest': max(sizes, key=lambda s: s[0] * s[1])}
    results = []
    (out / 'logs').mkdir(parents=True, exist_ok=True)
    for size in sizes:
        bag = _bench_bag(out, size, frames, seed, cache)
        for preset in presets:
            w, h = size
            weights, what = _node_weights(preset, out)
            params = {'preset': preset, 'weights': weights, 'measurement': 'network', 'device': device,
                      'processing_width': w, 'processing_height': h, 'input_reliability': 'reliable',
                      'diagnostics_period': 0.5,
                      'extrinsic_source': 'parameter'}    # the bench's bags: odometry of the camera itself
            cmd = node_command(params, {'image': R.IMAGE_TOPIC, 'camera_info': R.CAMERA_INFO_TOPIC,
                                        'odom': R.ODOM_TOPIC})
            log_path = out / 'logs' / f'node_{preset}_{w}x{h}_{device.replace(":", "")}.log'
            _say(f'node: {preset} {w}x{h} on {device}: {hz:g} images/s for >= {seconds:g} s (log {log_path})')
            row: Dict[str, Any] = {'preset': preset, 'width': w, 'height': h, 'device': device, 'weights': what,
                                   'input_hz': hz, 'log': str(log_path)}
            client = ClientNode('dpv_bench')   # Ctrl-C: KeyboardInterrupt
            node, executor = client.node, client.executor
            collector = OutputCollector(node, keep_messages=False)
            player = BagPlayer(node, bag, rate=hz / 30.0, rebase_stamps=True, loop=True)
            with open(log_path, 'w') as log:
                proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, text=True)
                try:
                    t0 = time.monotonic()
                    while time.monotonic() - t0 < start_timeout and proc.poll() is None:
                        executor.spin_once(timeout_sec=0.1)
                        if collector.diagnostics.get('measurement_model') not in (None, 'starting'):
                            break
                    missing = player.wait_for_subscribers(timeout=max(10.0, start_timeout - (time.monotonic() - t0)),
                                                          spin=lambda t: executor.spin_once(timeout_sec=t))
                    if proc.poll() is not None or missing:
                        raise RuntimeError(f'the node did not start (exit code {proc.poll()}, unmatched {missing}); '
                                           f'see {log_path}')
                    row['start_s'] = round(time.monotonic() - t0, 1)
                    row['measurement'] = collector.diagnostics.get('measurement_model')
                    box = {}
                    thread = threading.Thread(target=lambda: box.setdefault('stats', player.play()), daemon=True)
                    t_play = time.monotonic()
                    thread.start()
                    peak = 0
                    while True:
                        executor.spin_once(timeout_sec=0.05)
                        peak = max(peak, proc_status_kib(proc.pid, 'VmRSS') or 0)
                        el = time.monotonic() - t_play
                        if el >= max_seconds or proc.poll() is not None:
                            break
                        if el >= seconds and collector.depth_count >= min_outputs:
                            break
                    player.stop()
                    thread.join(10.0)
                    end = time.monotonic() + 1.5      # last outputs and a fresh diagnostics message
                    while time.monotonic() < end:
                        executor.spin_once(timeout_sec=0.05)
                    wall = time.monotonic() - t_play
                    hwm = proc_status_kib(proc.pid, 'VmHWM')
                    d = dict(collector.diagnostics)
                    lat = collector.latency_ms
                    stats = box.get('stats')
                    row.update({
                        'seconds': round(wall, 1),
                        'images_offered': stats.per_topic.get(R.IMAGE_TOPIC, 0) if stats else None,
                        'outputs': collector.depth_count,
                        'outputs_per_s': collector.depth_count / wall if wall > 0 else None,
                        'latency_ms_median': statistics.median(lat) if lat else None,
                        'latency_ms_p95': _percentile(lat, 95) if lat else None,
                        'node_receipt_to_publish_ms_median': _num(d.get('latency_ms_median')),
                        'node_frames_received': _num(d.get('frames_received')),
                        'node_frames_processed': _num(d.get('frames_processed')),
                        'node_dropped': _num(d.get('dropped_total')),
                        'node_keyframes': _num(d.get('estimator_keyframes')),
                        'node_peak_rss_mib': (max(peak, hwm or 0) / 1024.0) if (peak or hwm) else None,
                    })
                except Exception as exc:
                    row['error'] = f'{type(exc).__name__}: {exc}'
                    _say(f'node: {row["error"]}')
                finally:
                    player.stop()
                    if proc.poll() is None:
                        proc.send_signal(signal.SIGINT)
                        try:
                            row['exit_code'] = proc.wait(timeout=30.0)
                        except subprocess.TimeoutExpired:
                            proc.kill()
                            row['exit_code'] = proc.wait()
                    else:
                        row['exit_code'] = proc.returncode
                    client.close()
            results.append(row)
    return results


# --------------------------------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------------------------------
def _say(text: str) -> None:
    print(f'  ... {text}', flush=True)


def _num(v):
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def _percentile(values, q):
    import numpy as np
    return float(np.percentile(values, q))


def _f(v, fmt='{:.1f}'):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return '-'
    return fmt.format(v)


def _table(header: List[str], rows: List[List[str]]) -> List[str]:
    return ['| ' + ' | '.join(header) + ' |', '|' + '|'.join('---' for _ in header) + '|'] + \
        ['| ' + ' | '.join(r) + ' |' for r in rows]


def markdown(report: Dict) -> str:
    m = report['machine']
    c = report['config']
    lines = ['# dpv_sensor bench', '',
             f"{m['cpu']} ({m['cpu_count']} cores), torch {m['torch']} with {m['torch_threads']} threads"
             + (f", GPU {m['cuda_device']}" if m.get('cuda_device') else ', no GPU') +
             f"; load average {m['load_before']} before, {m['load_after']} after; {report['wall_s']:.0f} s in all. "
             f"Devices: {', '.join(c['devices'])}" + (f" ({c['devices_note']})" if c.get('devices_note') else '') +
             f". Latencies are medians of {c['repeats']} timed run(s) after {c['warmup']} warm-up run(s) (estimator: "
             f"{c['keyframes']} steady-state keyframe(s) per model).",
             '']
    core = {(r['device'], r['input'], r['num_planes']): r for r in report.get('core', [])}
    nets = report.get('nets', [])
    if nets or core:
        lines += ['## Per-stage latency (ms)', '',
                  'Network stages per keyframe (4 source views, their features cached); filter predict/update at '
                  "the preset's volume (1/4 size, D planes); classical = the NCC cost volume of the no-weights "
                  f'fallback (D={CLASSICAL_PLANES}). Peak memory: growth of peak RSS (CPU) / CUDA max allocated over '
                  'the network stages.', '']
        hdr = ['device', 'model', 'size', 'D', 'feature extraction', 'cost volume', 'K-Net', 'R-Net',
               'filter predict', 'filter update', 'keyframe (nets)', 'peak mem MiB']
        rows = []
        for r in nets:
            size = f"{r['width']}x{r['height']}"
            cr = core.get((_dev(r['device']), size, r['num_planes']), {})
            ms = r['latency_ms']
            rows.append([_dev(r['device']), r['preset'], size, str(r['num_planes']), _f(ms['feature_extraction']),
                         _f(ms['cost_volume']), _f(ms['knet']), _f(ms['rnet']),
                         _f(_ms(cr.get('predict_warp_volume_s'))), _f(_ms(cr.get('update_global_s'))),
                         _f(ms['keyframe_streaming']), _f(r['peak_memory_mb'], '{:.0f}')])
        for (dev, size, D), cr in sorted(core.items()):
            if D == CLASSICAL_PLANES:
                rows.append([dev, 'classical', size, str(D), '-', _f(_ms(cr['classical_cost_volume_s'])), '-', '-',
                             _f(_ms(cr['predict_warp_volume_s'])), _f(_ms(cr['update_global_s'])), '-', '-'])
        lines += _table(hdr, rows) + ['']
    est = report.get('estimator', [])
    if est:
        lines += ['## Estimator: keyframes per second', '',
                  '`Estimator.push()` of a keyframe, steady state (causal window, 4 sources), end to end in the '
                  'process: resize, features, measurement, filter, R-Net/upsampling, output.', '']
        hdr = ['device', 'model', 'size', 'weights', 'ms / keyframe', 'keyframes/s', 'stages (ms)', 'peak RSS MiB',
               'CUDA peak MiB']
        rows = []
        for r in est:
            st = ', '.join(f'{k} {v:.0f}' for k, v in r['stages_ms_median'].items() if k != 'total' and '.' not in k)
            weights = 'none' if r['model'] == 'classical' else ('random init' if 'RANDOM' in r['what'] else 'packaged')
            rows.append([r['device'], r['model'], f"{r['width']}x{r['height']}", weights,
                         _f(r['push_ms_median'], '{:.0f}'),
                         _f(r['keyframes_per_s'], '{:.2f}'), st,
                         _f(r['rss_peak_mib'], '{:.0f}') + (f" (+{r['rss_growth_mib']:.0f})" if r.get('rss_growth_mib')
                                                           is not None else ''),
                         _f(r['cuda_peak_mib'], '{:.0f}')])
        lines += _table(hdr, rows) + ['']
    for r in report.get('keyframe', []):
        from dpv_sensor.benchmarks.keyframe import markdown as keyframe_markdown
        lines += [f"## The default keyframe, stage by stage ({r['device']})", '', keyframe_markdown(r)]
    node = report.get('node', [])
    if node:
        lines += ['## End to end through the node', '',
                  f"The node as its own process; a rendered sequence played into it at {c['e2e_hz']:g} images/s with "
                  'live stamps. Latency = receipt of the depth image - its image stamp. The node keeps only the newest '
                  'waiting image, so when a keyframe takes longer than the camera period it drops images (counted) '
                  'instead of falling behind.', '']
        hdr = ['device', 'preset', 'size', 'measurement', 'outputs/s', 'latency median ms', 'latency p95 ms',
               'node receipt->publish ms', 'images dropped / received', 'node peak RSS MiB']
        rows = []
        for r in node:
            if r.get('error'):
                rows.append([r['device'], r['preset'], f"{r['width']}x{r['height']}", 'error: ' + r['error'][:80]]
                            + ['-'] * 6)
                continue
            meas = f"{r.get('measurement')}" + (' (random init)' if 'RANDOM' in r['weights'] else '')
            rows.append([r['device'], r['preset'], f"{r['width']}x{r['height']}", meas,
                         _f(r['outputs_per_s'], '{:.2f}'),
                         _f(r['latency_ms_median'], '{:.0f}'), _f(r['latency_ms_p95'], '{:.0f}'),
                         _f(r['node_receipt_to_publish_ms_median'], '{:.0f}'),
                         f"{_f(r['node_dropped'], '{:.0f}')} / {_f(r['node_frames_received'], '{:.0f}')}",
                         _f(r['node_peak_rss_mib'], '{:.0f}')])
        lines += _table(hdr, rows) + ['']
    for w in report.get('warnings', []):
        lines.append(f'- {w}')
    return '\n'.join(lines).rstrip() + '\n'


def _ms(seconds):
    return None if seconds is None else 1000.0 * seconds


def _dev(device: str) -> str:
    return str(device)


def _parse_size(text: str) -> Tuple[int, int]:
    from dpv_sensor.benchmarks.nets import parse_size
    return parse_size(text)


def _parse_sizes(text: str) -> List[Tuple[int, int]]:
    return [_parse_size(part) for part in text.replace(' ', ',').split(',') if part]


def _csv(text: str) -> List[str]:
    return [x.strip() for x in text.split(',') if x.strip()]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='bench', description=__doc__.split('\n\n')[0],
                                epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--presets', type=_csv, default=['lite', 'paper'], help='comma list (default lite,paper)')
    p.add_argument('--devices', type=_csv, default=['cpu', 'cuda'],
                   help='comma list (default cpu,cuda; cuda is skipped when torch has no GPU)')
    p.add_argument('--sizes', type=_parse_sizes, default=[(320, 256), (640, 480)],
                   help='processing sizes WxH, comma list (default 320x256,640x480)')
    p.add_argument('--out', default='out/bench', help='output folder (default out/bench)')
    p.add_argument('--parts', type=_csv, default=list(PARTS), help=f'which parts (default {",".join(PARTS)})')
    p.add_argument('--repeats', type=int, default=3, help='timed runs per stage (default 3)')
    p.add_argument('--warmup', type=int, default=1, help='untimed runs per stage (default 1)')
    p.add_argument('--keyframes', type=int, default=3, help='timed estimator keyframes per model (default 3)')
    p.add_argument('--keyframe-keyframes', type=int, default=12,
                   help='timed keyframes per variant of the default-keyframe part (default 12)')
    p.add_argument('--keyframe-warmup', type=int, default=4,
                   help='untimed keyframes per variant before them (default 4)')
    p.add_argument('--keyframe-input', type=_parse_size, default=(640, 480),
                   help="the rendered camera's image size WxH of the default-keyframe part (default 640x480)")
    p.add_argument('--backends', type=_csv, default=['torch'],
                   help='inference_backend values of the default-keyframe part, comma list (default torch)')
    p.add_argument('--threads', type=int, default=None, help='torch threads (bench process and node; default torch)')
    p.add_argument('--e2e-hz', type=float, default=10.0, help='images per second into the node (default 10)')
    p.add_argument('--e2e-seconds', type=float, default=15.0, help='node run length (default 15 s)')
    p.add_argument('--e2e-min-outputs', type=int, default=3, help='run longer until this many outputs (default 3)')
    p.add_argument('--e2e-max-seconds', type=float, default=240.0, help='... but at most this long (default 240 s)')
    p.add_argument('--e2e-frames', type=int, default=30, help='frames of the looped synthetic sequence (default 30)')
    p.add_argument('--start-timeout', type=float, default=180.0, help='seconds for the node to start (default 180)')
    p.add_argument('--seed', type=int, default=42, help='synthetic scene of the node run (default 42)')
    p.add_argument('--domain-id', type=int, default=None, help='ROS_DOMAIN_ID of the node runs (default: private)')
    return p


def _argument_error(a) -> Optional[str]:
    """Why the parts, sizes or presets asked for cannot run (None: they can)."""
    unknown = [x for x in a.parts if x not in PARTS]
    if unknown:
        return f'unknown part(s) {unknown}; parts are {", ".join(PARTS)}'
    if not a.sizes or not a.presets:
        return 'give at least one size and one preset'
    from dpv_sensor.core.nets.presets import get_preset
    for preset in a.presets:
        try:
            get_preset(preset)
        except Exception as exc:
            return f'preset {preset!r}: {exc}'
    return None


def _available_devices(requested: List[str]) -> Tuple[List[str], List[str]]:
    """The devices asked for that torch has, and a note for each one skipped."""
    import torch
    devices, notes = [], []
    for d in requested:
        if d.startswith('cuda') and not torch.cuda.is_available():
            notes.append(f'{d} skipped: torch.cuda.is_available() is False')
            continue
        devices.append(d)
    return devices, notes


def _new_report(a, devices: List[str], notes: List[str]) -> Dict[str, Any]:
    """The report before any measurement: the machine (load before), the configuration, empty result lists."""
    import torch
    load_before = [round(x, 2) for x in os.getloadavg()]
    return {
        'machine': {'cpu': platform.processor() or platform.machine(), 'cpu_count': os.cpu_count(),
                    'torch': torch.__version__, 'torch_threads': torch.get_num_threads(),
                    'python': platform.python_version(),
                    'cuda_device': (torch.cuda.get_device_name(0) if any(d.startswith('cuda') for d in devices)
                                    else None),
                    'load_before': load_before},
        'config': {'presets': a.presets, 'devices': devices, 'devices_note': '; '.join(notes),
                   'sizes': [f'{w}x{h}' for w, h in a.sizes], 'parts': a.parts, 'repeats': a.repeats,
                   'warmup': a.warmup, 'keyframes': a.keyframes, 'backends': a.backends, 'e2e_hz': a.e2e_hz,
                   'e2e_seconds': a.e2e_seconds,
                   'e2e_min_outputs': a.e2e_min_outputs, 'threads': a.threads},
        'nets': [], 'core': [], 'estimator': [], 'keyframe': [], 'node': [], 'warnings': list(notes)}


def _run_parts(a, devices: List[str], out: pathlib.Path, report: Dict[str, Any]) -> None:
    """Every part asked for on every device, the results appended to the report's lists."""
    for device in devices:
        if 'nets' in a.parts:
            report['nets'] += bench_nets(a.presets, a.sizes, device, a.repeats, a.warmup)
        if 'core' in a.parts:
            report['core'] += bench_core(a.presets, a.sizes, device, a.repeats)
        if 'estimator' in a.parts:
            report['estimator'] += bench_estimator(['classical'] + list(a.presets), a.sizes, device, a.keyframes)
        if 'keyframe' in a.parts:
            report['keyframe'].append(bench_keyframe(device, a.backends, a.keyframe_keyframes, a.keyframe_warmup,
                                                        a.keyframe_input))
        if 'node' in a.parts:
            report['node'] += bench_node(a.presets, a.sizes, device, out, hz=a.e2e_hz, seconds=a.e2e_seconds,
                                         min_outputs=a.e2e_min_outputs, max_seconds=a.e2e_max_seconds,
                                         start_timeout=a.start_timeout, frames=a.e2e_frames, seed=a.seed,
                                         threads=a.threads)


def _result_warnings(report: Dict[str, Any], e2e_max_seconds: float) -> List[str]:
    """Warnings about the results: random-init estimator weights, node runs that failed or gave no output."""
    warnings = []
    for r in report['estimator']:
        if 'RANDOM' in r.get('what', ''):
            warnings.append(f"estimator {r['model']}: random-init weights (no trained checkpoint loads); "
                            'the cost is the same, the depth is meaningless')
            break
    for r in report['node']:
        run = f"node {r['preset']} {r['width']}x{r['height']} {r['device']}"
        if r.get('error'):
            warnings.append(f"{run}: {r['error']}")
        elif r.get('exit_code') not in (0, None):
            warnings.append(f"{run}: exit code {r['exit_code']} after SIGINT")
        if not r.get('error') and not r.get('outputs'):
            warnings.append(f'{run}: no depth output within {e2e_max_seconds:g} s')
    return warnings


def _write_report(out: pathlib.Path, report: Dict[str, Any]) -> None:
    """bench.json and bench.md in `out`; the markdown is printed too."""
    md = markdown(report)
    from dpv_sensor.evaluation.offline import to_jsonable
    (out / 'bench.json').write_text(json.dumps(to_jsonable(report), indent=1))
    (out / 'bench.md').write_text(md)
    print()
    print(md)
    print(f'written: {out / "bench.md"}, {out / "bench.json"}')


def main(argv: Optional[List[str]] = None) -> int:
    argv = tool_argv(argv)
    a = build_parser().parse_args(argv)
    error = _argument_error(a)
    if error:
        print(f'bench: {error}', file=sys.stderr)
        return 2
    out = pathlib.Path(a.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if 'node' in a.parts:   # a private DDS domain for the node runs, logs under OUT
        from dpv_sensor.client.ros_io import private_ros_env
        private_ros_env(out, a.domain_id)
    import torch
    if a.threads:
        torch.set_num_threads(a.threads)
    devices, notes = _available_devices(a.devices)
    t0 = time.perf_counter()
    report = _new_report(a, devices, notes)
    print(f'bench: presets {",".join(a.presets)}, sizes {",".join(report["config"]["sizes"])}, devices '
          f'{",".join(devices)}, parts {",".join(a.parts)} -> {out}', flush=True)
    _run_parts(a, devices, out, report)
    report['warnings'] += _result_warnings(report, a.e2e_max_seconds)
    report['machine']['load_after'] = [round(x, 2) for x in os.getloadavg()]
    report['wall_s'] = round(time.perf_counter() - t0, 1)
    _write_report(out, report)
    return 0


if __name__ == '__main__':
    sys.exit(main())
