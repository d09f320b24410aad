"""``ros2 run dpv_sensor export_onnx``: the networks as ONNX files, for a deployment runtime of your own.

    export_onnx --out onnx/                                   # packaged lite weights, 320x256
    export_onnx --weights adapted.safetensors --size 640x480 --out onnx/

Writes ``features.onnx`` (image, RGB in [0, 1], 1x3xHxW -> fusion 1xCxH/4xW/4 and half 1xSxH/2xW/2),
``knet.onnx`` (residual 1xDxH/4xW/4, image -> correction) and ``rnet.onnx`` (logp, fusion, half, image -> the
full-resolution log-DPV) at the processing size, and ``export.json`` (preset, planes, size, the weights' digest,
and each file's largest difference from PyTorch when ONNX Runtime is installed to check it). These are the files
the node's ``inference_backend: onnxruntime | openvino`` exports for itself (``core/nets/runtime.py``); on a GPU
feed them to TensorRT (``trtexec --onnx=knet.onnx --bf16 --saveEngine=knet.plan``) or to ONNX Runtime's CUDA
provider. The cost volume (a plane sweep in float32 geometry) and the filter stay in PyTorch.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
from typing import List, Optional

from dpv_sensor import params as P
from dpv_sensor.cli import add_setting, tool_argv

__all__ = ['main', 'export']


def export(weights: str, preset: str, size, out: pathlib.Path) -> dict:
    """Export the three parts of a checkpoint at ``size`` (W, H) into ``out``; returns what export.json holds."""
    from dpv_sensor.core.nets import runtime as RT
    from dpv_sensor.core.nets.checkpoint import default_weights_path, load_checkpoint
    path = weights or str(default_weights_path(preset))
    model, _ = load_checkpoint(path, preset=preset)
    hw = (int(size[1]), int(size[0]))
    report = {'weights': path, 'preset': model.preset.name, 'num_planes': model.num_planes,
              'd_min': model.d_min, 'd_max': model.d_max, 'processing_size': [int(size[0]), int(size[1])],
              'weights_sha256': RT.weights_digest(model), 'opset': RT.OPSET, 'format': RT.EXPORT_FORMAT, 'parts': {}}
    for part in RT.PARTS:
        file = RT.export_onnx(model, part, hw, out / f'{part}.onnx')
        entry = {'file': file.name}
        try:
            entry['max_diff_vs_torch'] = RT.check_part(model, part, RT._OrtSession(file, threads=1), hw)
        except ImportError:
            entry['max_diff_vs_torch'] = None          # no onnxruntime here to check with
        report['parts'][part] = entry
    (out / 'export.json').write_text(json.dumps(report, indent=1))
    return report


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog='export_onnx', description=__doc__.split('\n')[0],
                                 epilog=__doc__.split('\n\n', 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_setting(ap, 'preset')
    add_setting(ap, 'weights')
    ap.add_argument('--size', default=f"{P.default('processing_width')}x{P.default('processing_height')}",
                    help="processing size WxH (default the node's)")
    ap.add_argument('--out', required=True, type=pathlib.Path, help='folder for the files')
    a = ap.parse_args(tool_argv(argv))
    try:
        w, h = (int(v) for v in a.size.lower().split('x'))
    except ValueError:
        print(f'export_onnx: --size must look like 320x256, got {a.size!r}', file=sys.stderr)
        return 2
    from dpv_sensor.core.nets.runtime import RuntimeUnavailable
    try:
        report = export(a.weights, a.preset, (w, h), a.out)
    except RuntimeUnavailable as exc:
        print(f'export_onnx: {exc}', file=sys.stderr)
        return 2
    for entry in report['parts'].values():
        diff = entry['max_diff_vs_torch']
        print(f"{a.out / entry['file']}: " + ('not checked (no onnxruntime)' if diff is None
                                               else f'largest difference from PyTorch {diff:.2g}'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
