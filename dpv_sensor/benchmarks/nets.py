"""Per-stage latency, peak memory, parameters and MACs of the D-Net / K-Net / R-Net presets.

    python -m dpv_sensor.benchmarks.nets                       # lite + paper at 320x256 and 640x480, CPU
    python -m dpv_sensor.benchmarks.nets --presets lite --sizes 320x256 --repeats 10
    python -m dpv_sensor.benchmarks.nets --device cuda --amp bf16 --json out/nets.json
    python -m dpv_sensor.benchmarks.nets --presets lite --amp bf16    # CPU bfloat16 autocast (cpu_precision)

One "keyframe" is what the streaming estimator does per keyframe with a window of 1 reference + N
(default 4) source views: feature extraction of the new frame (sources come from the feature cache),
cost volume over the N views, K-Net on the filter residual, R-Net to full resolution. Stages:

* ``feature_extraction`` - one image through the PSM-Net extractor;
* ``cost_volume``        - plane-sweep warps of the N cached source features + L1 + softmax;
* ``knet``               - K-Net on a (D, H/4, W/4) residual and the image;
* ``rnet``               - R-Net to (D, H, W);
* ``keyframe_streaming`` - all four in sequence, timed end to end (features of the sources cached);
* ``keyframe_cold``      - same but all 1 + N images go through the extractor (no cache).

The filter's own predict/update arithmetic is not part of these nets and is not included.

Latency is the median (and the minimum, the least-contended figure on a shared machine) over
``repeats`` timed runs after ``warmup`` runs, plus the median process CPU time (``cpu``: robust to
other processes competing for the cores; with ``--threads 1`` it is the uncontended one-core latency)
(``torch.no_grad``; CUDA is synchronised around each stage). Peak memory on the CPU is the growth of the
process's peak resident set (``VmHWM`` in /proc/self/status, reset before each configuration through
/proc/self/clear_refs; falls back to ``resource.getrusage`` ``ru_maxrss`` growth, which only sees new
highs) over the resident size before the configuration; on CUDA it is
``torch.cuda.max_memory_allocated`` growth. ``run(...)`` returns everything as a dict.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time
from contextlib import nullcontext
from typing import Dict, Iterable, Optional, Sequence, Tuple

import torch

from dpv_sensor.core.nets.model import DPVNet, count_macs, count_parameters
from dpv_sensor.ros.process_memory import proc_status_kib
from dpv_sensor import params as P
from dpv_sensor.cli import add_setting

__all__ = ['run', 'main', 'parse_size']

DEFAULT_SIZES = ((320, 256), (640, 480))


def parse_size(text: str) -> Tuple[int, int]:
    """'320x256' -> (320, 256) (width x height)."""
    try:
        w, h = text.lower().split('x')
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f'size must look like 320x256, got {text!r}') from None


def _reset_peak_rss() -> bool:
    try:
        with open('/proc/self/clear_refs', 'w') as f:
            f.write('5')
        return True
    except OSError:
        return False


class _CpuPeak:
    """Peak resident-set growth (MiB) over a block."""

    def __enter__(self):
        self.clear_ok = _reset_peak_rss() and proc_status_kib('self', 'VmHWM') is not None
        self.rss0 = proc_status_kib('self', 'VmRSS') if self.clear_ok else None
        self.maxrss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return self

    def __exit__(self, *exc):
        if self.clear_ok:
            self.peak_mb = max(0, proc_status_kib('self', 'VmHWM') - self.rss0) / 1024.0
            self.method = 'VmHWM-VmRSS'
        else:
            self.peak_mb = max(0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - self.maxrss0) / 1024.0
            self.method = 'ru_maxrss growth'
        return False


class _CudaPeak:
    def __init__(self, device):
        self.device = device

    def __enter__(self):
        torch.cuda.synchronize(self.device)
        self.base = torch.cuda.memory_allocated(self.device)
        torch.cuda.reset_peak_memory_stats(self.device)
        return self

    def __exit__(self, *exc):
        torch.cuda.synchronize(self.device)
        self.peak_mb = (torch.cuda.max_memory_allocated(self.device) - self.base) / 2 ** 20
        self.method = 'cuda max_memory_allocated'
        return False


def _timed(fn, device, repeats: int, warmup: int) -> Tuple[float, float, float]:
    """(median wall ms, min wall ms, median process-CPU ms) of fn().

    The CPU time (all threads of the process) is what the work costs regardless of how long other
    processes kept it off the cores: with ``--threads 1`` it is the uncontended single-core latency.
    """
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == 'cuda' else (lambda: None)
    for _ in range(warmup):
        fn()
    sync()
    times, cpu = [], []
    for _ in range(repeats):
        c0 = time.process_time()
        t0 = time.perf_counter()
        fn()
        sync()
        times.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return statistics.median(times), min(times), statistics.median(cpu)


def _window(width: int, height: int, num_sources: int, device):
    """A synthetic window: random images, a plausible K, sources translated sideways/forwards."""
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(1, 3, height, width, generator=g)
    srcs = torch.rand(1, num_sources, 3, height, width, generator=g)
    f = 0.9 * width
    K = torch.tensor([[[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]]])
    T = torch.eye(4).repeat(1, num_sources, 1, 1)
    for n in range(num_sources):
        T[0, n, 0, 3] = 0.05 * (n + 1) * (-1) ** n
        T[0, n, 2, 3] = 0.02 * n
    return ref.to(device), srcs.to(device), K.to(device), T.to(device)


@torch.no_grad()
def run_one(preset: str, size: Tuple[int, int], device=P.default('device'), num_sources: int = 4, repeats: int = 5,
            warmup: int = 1, amp: Optional[str] = None, channels_last: Optional[bool] = None,
            channels_last_3d: Optional[bool] = None) -> Dict:
    """Benchmark one preset at one size; see the module docstring for the fields."""
    device = torch.device(device)
    width, height = size
    model = DPVNet(preset, channels_last=channels_last, channels_last_3d=channels_last_3d).eval()
    params = count_parameters(model)
    macs = count_macs(model, height, width, num_sources)
    model = model.to(device)
    ref, srcs, K, T = _window(width, height, num_sources, device)
    if amp:
        if device.type != 'cuda' and amp != 'bf16':
            raise ValueError('--amp fp16 is CUDA only (the CPU autocasts to bf16)')
        dtype = {'bf16': torch.bfloat16, 'fp16': torch.float16}[amp]
        ctx = lambda: torch.autocast(device.type, dtype=dtype)  # noqa: E731
    else:
        ctx = nullcontext
    peak = _CudaPeak(device) if device.type == 'cuda' else _CpuPeak()
    with peak, ctx():
        src_feats = [model.extract_features(srcs[:, n]) for n in range(num_sources)]
        feats = model.extract_features(ref)
        K_vol = model.volume_intrinsics(K)
        depths = model.depths_d
        src = torch.stack([f.fusion for f in src_feats], 1)
        logp = model.cost_volume(feats.fusion, src, K_vol, T, depths)
        residual = torch.randn_like(logp)

        def keyframe_streaming():
            lp, _, fe = model.measure(ref, None, K, T, src_features=src_feats)
            model.knet(residual, ref)
            return model.refine(lp, fe, ref)

        def keyframe_cold():
            lp, _, fe = model.measure(ref, srcs, K, T)
            model.knet(residual, ref)
            return model.refine(lp, fe, ref)

        load0 = os.getloadavg()[0] if hasattr(os, 'getloadavg') else None
        timed = {
            'feature_extraction': _timed(lambda: model.extract_features(ref), device, repeats, warmup),
            'cost_volume': _timed(lambda: model.cost_volume(feats.fusion, src, K_vol, T, depths), device, repeats,
                                  warmup),
            'knet': _timed(lambda: model.knet(residual, ref), device, repeats, warmup),
            'rnet': _timed(lambda: model.refine(logp, feats, ref), device, repeats, warmup),
            'keyframe_streaming': _timed(keyframe_streaming, device, repeats, warmup),
            'keyframe_cold': _timed(keyframe_cold, device, repeats, warmup),
        }
        ms = {k: v[0] for k, v in timed.items()}
        ms_min = {k: v[1] for k, v in timed.items()}
        ms_cpu = {k: v[2] for k, v in timed.items()}
    return {
        'preset': preset, 'width': width, 'height': height, 'num_sources': num_sources,
        'num_planes': model.num_planes, 'device': str(device), 'amp': amp or 'fp32',
        'threads': torch.get_num_threads(), 'repeats': repeats,
        'latency_ms': ms, 'latency_min_ms': ms_min, 'cpu_time_ms': ms_cpu, 'load_average': load0,
        'peak_memory_mb': peak.peak_mb, 'memory_method': peak.method,
        'params': dict(params), 'macs': dict(macs),
    }


def run(presets: Sequence[str] = ('lite', 'paper'), sizes: Iterable[Tuple[int, int]] = DEFAULT_SIZES,
        device: str = P.default('device'), num_sources: int = 4, repeats: int = 5, warmup: int = 1,
        amp: Optional[str] = None, threads: Optional[int] = None, channels_last: Optional[bool] = None,
        channels_last_3d: Optional[bool] = None, verbose: bool = False) -> Dict:
    """Benchmark every preset x size; returns ``{'results': [run_one(...) dicts], 'torch': ..., ...}``."""
    if threads:
        torch.set_num_threads(int(threads))
    results = []
    for preset in presets:
        for size in sizes:
            r = run_one(preset, tuple(size), device, num_sources, repeats, warmup, amp, channels_last,
                        channels_last_3d)
            results.append(r)
            if verbose:
                print(format_result(r), flush=True)
    return {'results': results, 'torch': torch.__version__, 'cpu_count': os.cpu_count(),
            'threads': torch.get_num_threads(),
            'cuda_device': torch.cuda.get_device_name(0) if device.startswith('cuda') else None}


def format_result(r: Dict) -> str:
    ms, mn, cpu, macs = r['latency_ms'], r['latency_min_ms'], r['cpu_time_ms'], r['macs']
    load = f"  load avg {r['load_average']:.1f}" if r.get('load_average') is not None else ''
    lines = [f"{r['preset']:>6} {r['width']}x{r['height']}  D={r['num_planes']}  N={r['num_sources']}  "
             f"{r['device']} {r['amp']} threads={r['threads']}{load}  params={r['params']['total'] / 1e6:.3f} M  "
             f"peak mem +{r['peak_memory_mb']:.0f} MiB",
             f"    {'stage':<20} {'median':>9}    {'min':>7}    {'cpu':>8}      {'MACs':>8}"]
    for stage in ('feature_extraction', 'cost_volume', 'knet', 'rnet'):
        lines.append(f"    {stage:<20} {ms[stage]:9.1f} ms {mn[stage]:7.1f} ms {cpu[stage]:8.1f} ms "
                     f"{macs[stage] / 1e9:8.3f} GMAC   {r['params'][stage] / 1e6:7.3f} M params")
    lines.append(f"    {'keyframe_streaming':<20} {ms['keyframe_streaming']:9.1f} ms "
                 f"{mn['keyframe_streaming']:7.1f} ms {cpu['keyframe_streaming']:8.1f} ms "
                 f"{macs['total_streaming'] / 1e9:8.3f} GMAC   (source features cached)")
    lines.append(f"    {'keyframe_cold':<20} {ms['keyframe_cold']:9.1f} ms {mn['keyframe_cold']:7.1f} ms "
                 f"{cpu['keyframe_cold']:8.1f} ms "
                 f"{macs['total_window'] / 1e9:8.3f} GMAC   (all {1 + r['num_sources']} images extracted)")
    return '\n'.join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--presets', nargs='+', default=['lite', 'paper'])
    ap.add_argument('--sizes', nargs='+', type=parse_size, default=list(DEFAULT_SIZES), help='WxH ...')
    add_setting(ap, 'device')
    ap.add_argument('--amp', choices=['bf16', 'fp16'], default=None, help='autocast dtype (bf16 also on the CPU)')
    ap.add_argument('--sources', type=int, default=4, help='source views per keyframe')
    ap.add_argument('--repeats', type=int, default=5)
    ap.add_argument('--warmup', type=int, default=1)
    ap.add_argument('--threads', type=int, default=None, help='torch.set_num_threads')
    ap.add_argument('--no-channels-last', action='store_true', help='NCHW instead of NHWC for the 2-D nets')
    ap.add_argument('--no-channels-last-3d', action='store_true', help='NCDHW instead of NDHWC for the K-Net 3-D convs')
    ap.add_argument('--json', default=None, help='also write the results to this file')
    a = ap.parse_args(argv)
    if a.device.startswith('cuda') and not torch.cuda.is_available():
        print('CUDA is not available', file=sys.stderr)
        return 2
    out = run(a.presets, a.sizes, a.device, a.sources, a.repeats, a.warmup, a.amp, a.threads,
              channels_last=False if a.no_channels_last else None,
              channels_last_3d=False if a.no_channels_last_3d else None,
              verbose=True)
    if a.json:
        os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
        with open(a.json, 'w') as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
