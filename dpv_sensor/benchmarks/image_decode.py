"""What compressed colour input costs the node: decode time per image (image_transport ``compressed``, JPEG and PNG).

    python -m dpv_sensor.benchmarks.image_decode [--size 640x480] [--quality 90] [--png-level 3] [--repeats 200]
                                                 [--sequence FOLDER] [--threads 1] [--json]

The image is a rendered synthetic frame (``data.synthetic``, seed 0) at ``--size``, or the first image of a
sequence folder (``--sequence``, resized to ``--size``): a noise-free render compresses better than a camera image,
so the folder gives the more realistic figure. It is encoded once per codec as image_transport's compressed plugin
publishes it (``ros.compressed_image.rgb_to_compressed``: JPEG at ``--quality``, PNG at ``--png-level``, the
plugin's defaults 95 and 3), then decoded ``--repeats`` times the two ways the node does: on receipt
(``decode_message``: the subscription callback's cost) and on to RGB for the estimator (``image_to_rgb``, the
worker's cost, the same as for a raw bgr8 image). Reported per codec: payload size, compression ratio against raw
rgb8, and the median and 95th percentile of each step in ms. OpenCV runs on ``--threads`` threads.

``run(...)`` returns a JSON-serialisable dict.
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from typing import Sequence

import numpy as np


def _image(width: int, height: int, sequence: str | None) -> tuple[np.ndarray, str]:
    import cv2
    if sequence:
        from dpv_sensor.data.sequence import Sequence as Folder
        seq = Folder(sequence)
        rgb = np.asarray(seq.image(0))
        source = f'{sequence} frame 0'
    else:
        from dpv_sensor.data.synthetic import render_sequence
        rgb = render_sequence(0, 1, width=width, height=height).image(0)
        source = 'synthetic seed 0 frame 0'
    if rgb.shape[:2] != (height, width):
        rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(rgb), source


def _times_ms(fn, repeats: int) -> np.ndarray:
    fn()                                    # warm-up
    out = np.empty(repeats)
    for k in range(repeats):
        t0 = time.perf_counter()
        fn()
        out[k] = (time.perf_counter() - t0) * 1000.0
    return out


def _stats(ms: np.ndarray) -> dict:
    return {'median_ms': round(float(np.median(ms)), 3), 'p95_ms': round(float(np.percentile(ms, 95)), 3)}


def run(width: int = 640, height: int = 480, quality: int = 90, png_level: int = 3, repeats: int = 200,
        sequence: str | None = None, threads: int = 1, codecs: Sequence[str] = ('jpeg', 'png')) -> dict:
    import cv2
    from dpv_sensor.ros import msgs as M
    from dpv_sensor.ros.compressed_image import decode_message, rgb_to_compressed
    cv2.setNumThreads(threads)
    rgb, source = _image(width, height, sequence)
    raw_bytes = rgb.size
    stamp = 1_700_000_000_000_000_000
    out = {'size': f'{width}x{height}', 'image': source, 'repeats': repeats, 'threads': threads,
           'machine': platform.processor() or platform.machine(), 'opencv': cv2.__version__, 'codecs': {}}
    raw = M.rgb_to_image(rgb, stamp, 'cam', encoding='bgr8')
    out['raw_bgr8_to_rgb'] = _stats(_times_ms(lambda: M.image_to_rgb(raw), repeats))
    for codec in codecs:
        msg = rgb_to_compressed(rgb, stamp, 'cam', codec=codec, jpeg_quality=quality, png_level=png_level)
        decoded = decode_message(msg)
        if decoded.error is not None:
            raise RuntimeError(f'{codec}: {decoded.error}')
        back = M.image_to_rgb(decoded)
        err = float(np.abs(back.astype(np.int16) - rgb.astype(np.int16)).mean())
        n = len(msg.data)
        out['codecs'][codec] = {
            'format': msg.format, 'setting': f'quality {quality}' if codec == 'jpeg' else f'level {png_level}',
            'bytes': n, 'ratio': round(raw_bytes / n, 2), 'mean_abs_error': round(err, 3),
            'decode': _stats(_times_ms(lambda m=msg: decode_message(m), repeats)),
            'to_rgb': _stats(_times_ms(lambda d=decoded: M.image_to_rgb(d), repeats))}
    return out


def table(res: dict) -> str:
    lines = [f"image decode, {res['size']} ({res['image']}), {res['repeats']} repeats, OpenCV {res['opencv']} on "
             f"{res['threads']} thread(s), {res['machine']}",
             '| codec | setting | bytes | ratio | mean abs error | decode ms (median / p95) '
             '| to RGB ms (median / p95) |',
             '|---|---|---|---|---|---|---|']
    for codec, c in res['codecs'].items():
        lines.append(f"| {codec} | {c['setting']} | {c['bytes']} | {c['ratio']:.1f} | {c['mean_abs_error']:.2f} | "
                     f"{c['decode']['median_ms']:.2f} / {c['decode']['p95_ms']:.2f} | "
                     f"{c['to_rgb']['median_ms']:.2f} / {c['to_rgb']['p95_ms']:.2f} |")
    r = res['raw_bgr8_to_rgb']
    lines.append(f"| raw bgr8 | - | {int(res['size'].split('x')[0]) * int(res['size'].split('x')[1]) * 3} | 1.0 | 0 | "
                 f"- | {r['median_ms']:.2f} / {r['p95_ms']:.2f} |")
    return '\n'.join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog='image_decode', description=__doc__.split('\n\n')[0],
                                epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--size', default='640x480', help='WIDTHxHEIGHT (default 640x480)')
    p.add_argument('--quality', type=int, default=90, help='JPEG quality 1-100 (default 90)')
    p.add_argument('--png-level', type=int, default=3, help='PNG compression level 0-9 (default 3)')
    p.add_argument('--repeats', type=int, default=200, help='decodes per codec (default 200)')
    p.add_argument('--sequence', default=None, help='take the first image of this sequence folder')
    p.add_argument('--threads', type=int, default=1, help='OpenCV threads (default 1)')
    p.add_argument('--json', action='store_true', help='print the result as JSON')
    a = p.parse_args(argv)
    w, h = (int(x) for x in a.size.lower().split('x'))
    res = run(w, h, a.quality, a.png_level, a.repeats, a.sequence, a.threads)
    print(json.dumps(res, indent=1) if a.json else table(res))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
