"""Per-step timings of the DPV core: plane-sweep warp, classical cost volume, predict, update.

    python -m dpv_sensor.benchmarks.core [--sizes 320x240 640x480] [--planes 64] [--views 4]
                                         [--downscale 4] [--threads N] [--device cpu|cuda] [--json]

For each input size W x H the volume is at (W/downscale) x (H/downscale) with D planes (1/4
resolution, like the networks). Steps timed (median over ``--repeats`` after one warm-up):

- ``plane_sweep_warp``: one source's 3-channel feature map warped onto the D planes of the reference
  (grid_sample on the volume grid) - what D-Net does per source view and feature channel group;
- ``classical_cost_volume``: :class:`ClassicalMeasurement` on one reference + ``views`` sources,
  including grey/box-downscale/gradients, all warps, ZNCC and the softmax (the whole measurement);
- ``predict_warp_volume``: :func:`warp_volume` of a DPV with a small camera motion (filter predict);
- ``update_global``: the energy-space update of mode 'global' + clamping and renormalisation
  (timed as :meth:`DPVFilter.step` minus its predict, i.e. a step with an identity pose, which skips
  the resampling).

``run(...)`` returns a dict (JSON-serialisable) so the ``bench`` tool can aggregate it.
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from typing import Dict, Iterable, Sequence, Tuple

import torch

from dpv_sensor.core.classical import ClassicalMeasurement
from dpv_sensor.core.dpv import depth_planes
from dpv_sensor.core.filter import DPVFilter
from dpv_sensor.core.geometry import make_se3, plane_sweep_warp, scale_intrinsics, so3_exp, warp_volume
from dpv_sensor import params as P
from dpv_sensor.cli import add_setting


def _sync(device: torch.device) -> None:
    if device.type == 'cuda':
        torch.cuda.synchronize(device)


def _time(fn, repeats: int, device: torch.device) -> float:
    fn()  # warm-up
    _sync(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _pose(i: int, dtype, device) -> torch.Tensor:
    """A small, non-trivial camera motion (a few cm, ~1 deg) - like consecutive keyframes."""
    w = torch.tensor([[0.004 * i, -0.012 * i, 0.003 * i]], dtype=dtype, device=device)
    t = torch.tensor([[0.03 * i, -0.01 * i, 0.015 * i]], dtype=dtype, device=device)
    return make_se3(so3_exp(w), t)


def run(sizes: Sequence[Tuple[int, int]] = ((320, 240), (640, 480)), num_planes: int = P.default('num_planes'),
        views: int = 4,
        downscale: int = 4, device: str = P.default('device'), repeats: int = 5, threads: int | None = None,
        d_min: float = P.default('d_min'), d_max: float = P.default('d_max')) -> Dict:
    """Time the core steps; returns {'config': ..., 'results': [{size, volume, step timings (s)}]}."""
    if threads is not None:
        torch.set_num_threads(int(threads))
    dev = torch.device(device)
    dt = torch.float32
    gen = torch.Generator().manual_seed(0)
    results = []
    for (W, H) in sizes:
        K = torch.tensor([[[0.9 * W, 0.0, (W - 1) / 2], [0.0, 0.9 * W, (H - 1) / 2], [0.0, 0.0, 1.0]]],
                         dtype=dt, device=dev)
        Kv = scale_intrinsics(K, 1.0 / downscale, 1.0 / downscale)
        h, w = H // downscale, W // downscale
        planes = depth_planes(d_min, d_max, num_planes, dtype=dt, device=dev)
        ref = torch.rand(1, 3, H, W, generator=gen).to(dev)
        srcs = torch.rand(1, views, 3, H, W, generator=gen).to(dev)
        T_src_ref = torch.stack([_pose(i + 1, dt, dev)[0] for i in range(views)])[None]
        feat = torch.rand(1, 3, h, w, generator=gen).to(dev)
        logp = torch.log_softmax(torch.randn(1, num_planes, h, w, generator=gen).to(dev), 1)
        cm = ClassicalMeasurement(d_min, d_max, num_planes, downscale=downscale)
        T1 = _pose(1, dt, dev)
        flt = DPVFilter(mode='global', max_time_gap=1e9, max_translation=1e9, max_rotation_deg=180.)
        eye = torch.eye(4, dtype=dt, device=dev)[None]
        flt.step(logp, Kv, eye, 0.0, planes)
        stamp = [0.0]

        def update():
            stamp[0] += 0.1
            flt.step(logp, Kv, eye, stamp[0], planes)

        with torch.no_grad():
            r = {
                'input': f'{W}x{H}', 'volume': f'{w}x{h}x{num_planes}', 'views': views,
                'plane_sweep_warp_s': _time(lambda: plane_sweep_warp(feat, Kv, Kv, T1, planes), repeats, dev),
                'classical_cost_volume_s': _time(lambda: cm(ref, srcs, K, T_src_ref), repeats, dev),
                'predict_warp_volume_s': _time(lambda: warp_volume(logp, Kv, T1, planes), repeats, dev),
                'update_global_s': _time(update, repeats, dev),
            }
        results.append(r)
    return {
        'config': {'num_planes': num_planes, 'views': views, 'downscale': downscale, 'device': str(dev),
                   'threads': torch.get_num_threads(), 'torch': torch.__version__, 'repeats': repeats,
                   'machine': platform.processor() or platform.machine()},
        'results': results,
    }


def _parse_size(s: str) -> Tuple[int, int]:
    w, h = s.lower().split('x')
    return int(w), int(h)


def main(argv: Iterable[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--sizes', nargs='+', default=['320x240', '640x480'])
    ap.add_argument('--planes', type=int, default=P.default('num_planes'))
    ap.add_argument('--views', type=int, default=4)
    ap.add_argument('--downscale', type=int, default=4)
    add_setting(ap, 'device')
    ap.add_argument('--repeats', type=int, default=5)
    ap.add_argument('--threads', type=int, default=None)
    ap.add_argument('--json', action='store_true', help='print the result dict as JSON')
    a = ap.parse_args(argv)
    out = run([_parse_size(s) for s in a.sizes], a.planes, a.views, a.downscale, a.device, a.repeats, a.threads)
    if a.json:
        print(json.dumps(out, indent=2))
        return
    c = out['config']
    print(f"dpv_sensor core benchmark: device={c['device']} threads={c['threads']} torch={c['torch']} "
          f"D={c['num_planes']} views={c['views']} volume=1/{c['downscale']} input, median of {c['repeats']}")
    print(f"{'input':>9} {'volume':>12} {'sweep warp':>11} {'classical':>10} {'predict':>9} {'update':>9}   (ms)")
    for r in out['results']:
        print(f"{r['input']:>9} {r['volume']:>12} {1e3 * r['plane_sweep_warp_s']:11.1f} "
              f"{1e3 * r['classical_cost_volume_s']:10.1f} {1e3 * r['predict_warp_volume_s']:9.1f} "
              f"{1e3 * r['update_global_s']:9.1f}")


if __name__ == '__main__':
    main()
