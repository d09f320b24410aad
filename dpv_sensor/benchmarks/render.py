"""Speed of the procedural scene renderer (dpv_sensor.data.synthetic) on one CPU core.

    python -m dpv_sensor.benchmarks.render [--size 320x240] [--seeds 0 1 2 3] [--frames 20]
                                           [--threads 1] [--json]

For each configuration — default (no motion blur), motion blur (``blur_samples`` sub-frames), rolling
shutter, and both — every seed builds its scene (timed separately: textures, furniture, shadow maps,
auto-exposure), renders one warm-up frame, then ``--frames`` frames. Reported: frames/s from wall-clock
time and from process CPU time (the CPU figure is what one core sustains; on a shared machine the
wall-clock figure also contains waiting for the core). OpenCV and BLAS are limited to ``--threads``.

``run(...)`` returns a JSON-serialisable dict so the ``bench`` tool can aggregate it.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from typing import Dict, Sequence


def _limit_threads(threads: int) -> None:
    for var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
        os.environ.setdefault(var, str(threads))
    import cv2
    cv2.setNumThreads(threads)


CONFIGS: Dict[str, dict] = {
    'default': {},
    'motion_blur': {'motion_blur': True},
    'rolling_shutter': {'rolling_shutter': True},
    'blur+rolling_shutter': {'motion_blur': True, 'rolling_shutter': True},
}


def run(width: int = 320, height: int = 240, seeds: Sequence[int] = (0, 1, 2, 3), frames: int = 20,
        configs: Sequence[str] = ('default', 'motion_blur'), threads: int = 1) -> dict:
    _limit_threads(threads)
    from dpv_sensor.data.synthetic import SceneConfig, SyntheticScene

    results = {'size': f'{width}x{height}', 'seeds': list(seeds), 'frames_per_seed': frames,
               'threads': threads, 'machine': platform.processor() or platform.machine(),
               'blur_samples': SceneConfig().blur_samples, 'configs': {}}
    for name in configs:
        options = CONFIGS[name]
        build_wall = build_cpu = wall = cpu = 0.0
        n = 0
        for seed in seeds:
            w0, c0 = time.perf_counter(), time.process_time()
            scene = SyntheticScene(seed, width, height, **options)
            build_wall += time.perf_counter() - w0
            build_cpu += time.process_time() - c0
            scene.render_frame(0)                       # warm-up
            w0, c0 = time.perf_counter(), time.process_time()
            for i in range(1, frames + 1):
                scene.render_frame(i)
            wall += time.perf_counter() - w0
            cpu += time.process_time() - c0
            n += frames
        results['configs'][name] = {
            'fps_wall': n / wall, 'fps_cpu': n / cpu, 'ms_per_frame_cpu': 1e3 * cpu / n,
            'scene_build_s_wall': build_wall / len(seeds), 'scene_build_s_cpu': build_cpu / len(seeds)}
    try:
        results['load_average'] = os.getloadavg()
    except OSError:
        pass
    return results


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='python -m dpv_sensor.benchmarks.render', description=__doc__.split('\n')[0])
    parser.add_argument('--size', default='320x240')
    parser.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2, 3])
    parser.add_argument('--frames', type=int, default=20)
    parser.add_argument('--configs', nargs='+', default=['default', 'motion_blur'], choices=sorted(CONFIGS))
    parser.add_argument('--threads', type=int, default=1)
    parser.add_argument('--json', action='store_true', help='print the result dict as JSON')
    args = parser.parse_args(argv)
    w, h = (int(x) for x in args.size.lower().split('x'))
    res = run(w, h, args.seeds, args.frames, args.configs, args.threads)
    if args.json:
        print(json.dumps(res, indent=1))
        return 0
    print(f"renderer at {res['size']}, {args.threads} thread(s), seeds {res['seeds']}, "
          f"{res['frames_per_seed']} frames each (motion blur = {res['blur_samples']} sub-frames)")
    print(f"{'config':<22}{'frames/s (cpu)':>16}{'frames/s (wall)':>17}{'ms/frame (cpu)':>16}{'scene build s':>15}")
    for name, r in res['configs'].items():
        print(f"{name:<22}{r['fps_cpu']:>16.1f}{r['fps_wall']:>17.1f}{r['ms_per_frame_cpu']:>16.1f}"
              f"{r['scene_build_s_cpu']:>15.2f}")
    if 'load_average' in res:
        print('load average: ' + ' '.join(f'{x:.2f}' for x in res['load_average']))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
