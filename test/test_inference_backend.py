"""inference_backend: the networks exported to ONNX and run in ONNX Runtime / OpenVINO against PyTorch, the file
cache, and the fallback to PyTorch where a runtime cannot be used (core/nets/runtime.py, the estimator)."""
from __future__ import annotations

import logging
import sys

import numpy as np
import pytest
import torch

from dpv_sensor.core.nets import runtime as RT
from dpv_sensor.core.nets.checkpoint import default_weights_path, load_checkpoint
from dpv_sensor.core.nets.dnet import ImageFeatures

HW = (64, 96)      # a small processing size (H, W): every part at 1/4, 1/2 and full size


@pytest.fixture(scope='module')
def lite():
    model, _ = load_checkpoint(str(default_weights_path('lite')), preset='lite')
    return model.eval()


@pytest.fixture(autouse=True)
def onnx_cache(tmp_path, monkeypatch):
    """A fresh ONNX cache per test (the runtime reads XDG_CACHE_HOME)."""
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'cache'))
    return tmp_path / 'cache' / 'dpv_sensor' / 'onnx'


def _ort():
    return pytest.importorskip('onnxruntime')


def _collect():
    """A logger whose warnings are kept in a list (what the node's logger would print)."""
    kept = []
    log = logging.getLogger(f'test_inference_backend.{len(kept)}.{id(kept)}')
    log.propagate = False

    class Keep(logging.Handler):
        def emit(self, record):
            if record.levelno >= logging.WARNING:
                kept.append(record.getMessage())
    log.handlers = [Keep()]
    return log, kept


# ---------------------------------------------------------------------------------------------------------------
# export and check
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize('part', RT.PARTS)
def test_export_matches_torch_to_1e4_and_a_changed_weight_fails_the_check(lite, part, tmp_path):
    _ort()
    path = RT.export_onnx(lite, part, HW, tmp_path / f'{part}.onnx')
    session = RT._OrtSession(path, threads=1)
    diff = RT.check_part(lite, part, session, HW)
    assert diff <= RT.CHECK_TOLERANCE
    # the same file against the weights with one output channel of the part's last layer shifted by 0.5: the check
    # must see it (a check that compared nothing, or only shapes, would pass)
    changed = RT._float_model(lite)
    module = {'features': changed.features.fusion[1].conv, 'knet': changed.knet.conv2_b,
              'rnet': changed.rnet.conv2[-1]}[part]
    with torch.no_grad():
        module.bias[0] += 0.5
    assert RT.check_part(changed, part, session, HW) > RT.CHECK_TOLERANCE


def test_runner_outputs_match_the_model_in_shape_and_value(lite):
    _ort()
    runner = RT.OnnxRunner(lite, 'onnxruntime', HW, threads=1)
    x = RT.example_inputs(lite, 'rnet', HW, seed=5)
    logp, fusion, half, image = x
    residual = torch.randn(1, lite.num_planes, *fusion.shape[-2:], generator=torch.Generator().manual_seed(7))
    with torch.no_grad():
        want_f = lite.extract_features(image)
        want_k = lite.knet(residual, image)
        want_r = lite.refine(logp, ImageFeatures(fusion, half), image)
    got_f = runner.extract_features(image)
    assert got_f.fusion.shape == want_f.fusion.shape and got_f.half.shape == want_f.half.shape
    assert torch.allclose(got_f.fusion, want_f.fusion, atol=1e-4) and torch.allclose(got_f.half, want_f.half, atol=1e-4)
    # inputs other than the check's: the graph is no constant of the example inputs
    assert torch.allclose(runner.knet(residual, image), want_k, atol=1e-4)
    assert torch.allclose(runner.refine(logp, ImageFeatures(fusion, half), image), want_r, atol=1e-4)


def test_files_are_cached_by_weights_and_a_damaged_file_is_exported_again(lite, onnx_cache):
    _ort()
    RT.OnnxRunner(lite, 'onnxruntime', HW, threads=1)
    files = sorted(onnx_cache.glob('*.onnx'))
    assert len(files) == 3 and all(f.name.startswith('lite_') for f in files)
    stamps = {f: f.stat().st_mtime_ns for f in files}
    RT.OnnxRunner(lite, 'onnxruntime', HW, threads=1)          # the same weights: the same files, not rewritten
    assert {f: f.stat().st_mtime_ns for f in sorted(onnx_cache.glob('*.onnx'))} == stamps
    other = RT._float_model(lite)
    with torch.no_grad():
        other.knet.gain.add_(0.1)
    RT.OnnxRunner(other, 'onnxruntime', HW, threads=1)         # other weights: three more files
    assert len(list(onnx_cache.glob('*.onnx'))) == 6
    files[0].write_bytes(b'not an onnx file')
    runner = RT.OnnxRunner(lite, 'onnxruntime', HW, threads=1)
    assert max(runner.check.values()) <= RT.CHECK_TOLERANCE and files[0].stat().st_size > 1000


# ---------------------------------------------------------------------------------------------------------------
# through the estimator
# ---------------------------------------------------------------------------------------------------------------
def _run(settings, frames, logger=None):
    from dpv_sensor.evaluation.runner import build_config
    from dpv_sensor.stream.pipeline import Pipeline
    config, _ = build_config(dict({'processing_width': HW[1], 'processing_height': HW[0], 'cpu_precision': 'float32'},
                                  **settings))
    pipe = Pipeline(config, logger=logger)
    outs = [r.output for r in (pipe.push(f) for f in frames) if r.output is not None and r.output.is_keyframe]
    return pipe, outs


@pytest.fixture(scope='module')
def frames():
    from dpv_sensor.data.synthetic import render_sequence
    from dpv_sensor.stream.frame import Frame
    seq = render_sequence(seed=5, num_frames=36, width=2 * HW[1], height=2 * HW[0])
    return [Frame(stamp=seq.stamp(i), image=seq.image(i), K_33=seq.K, T_world_cam_44=seq.pose(i))
            for i in range(len(seq))]


def test_onnxruntime_depth_matches_torch_within_1e3_on_a_rendered_sequence(frames):
    _ort()
    torch_pipe, want = _run({}, frames)
    ort_pipe, got = _run({'inference_backend': 'onnxruntime'}, frames)
    assert ort_pipe.status.inference_backend == 'onnxruntime' and 'onnxruntime' in ort_pipe.status.precision
    assert torch_pipe.status.inference_backend == 'torch'
    assert len(got) == len(want) >= 4           # the default centred window with the refiner: several keyframes
    for a, b in zip(got, want):
        assert a.stamp == b.stamp
        assert np.array_equal(np.isfinite(a.depth_hw), np.isfinite(b.depth_hw))
        ok = np.isfinite(b.depth_hw)
        assert ok.mean() > 0.5
        assert np.abs(a.depth_hw[ok] - b.depth_hw[ok]).max() <= 1e-3
        assert np.abs(a.confidence_hw - b.confidence_hw).max() <= 1e-3


def test_openvino_float32_depth_matches_torch_within_1e3(frames):
    pytest.importorskip('openvino')
    _, want = _run({}, frames[:20])
    pipe, got = _run({'inference_backend': 'openvino'}, frames[:20])
    assert pipe.status.inference_backend == 'openvino' and pipe.status.precision == 'float32 (openvino)'
    assert len(got) == len(want) >= 2
    for a, b in zip(got, want):
        ok = np.isfinite(b.depth_hw)
        assert np.array_equal(np.isfinite(a.depth_hw), ok)
        assert np.abs(a.depth_hw[ok] - b.depth_hw[ok]).max() <= 1e-3


def test_a_runtime_that_cannot_load_warns_once_and_torch_runs_identically(frames, monkeypatch):
    monkeypatch.setitem(sys.modules, 'onnxruntime', None)      # how Python marks a module that is not there
    log, warnings = _collect()
    pipe, got = _run({'inference_backend': 'onnxruntime'}, frames[:20], logger=log)
    mentions = [w for w in warnings if 'onnxruntime' in w]
    assert len(mentions) == 1 and 'cannot be used' in mentions[0] and 'running PyTorch' in mentions[0]
    assert pipe.status.inference_backend == 'torch' and pipe.status.precision == 'float32'
    assert any('onnxruntime' in n for n in pipe.status.notes)
    _, want = _run({}, frames[:20])
    assert len(got) == len(want) >= 2
    for a, b in zip(got, want):
        assert a.depth_hw.tobytes() == b.depth_hw.tobytes()
        assert a.confidence_hw.tobytes() == b.confidence_hw.tobytes()


def test_a_runtime_failing_while_running_is_reported_once_and_torch_takes_over(lite):
    _ort()
    notes = []
    runner = RT.build_runner(lite, 'onnxruntime', HW, note=notes.append, threads=1)
    assert isinstance(runner, RT.FallbackRunner) and runner.backend == 'onnxruntime' and notes == []
    small = torch.rand(1, 3, HW[0] // 2, HW[1] // 2)            # not the size the files were made for
    with torch.no_grad():
        want = lite.extract_features(small)
    for _ in range(2):
        got = runner.extract_features(small)
        assert torch.equal(got.fusion, want.fusion)             # PyTorch's result, the failed call included
    assert len(notes) == 1 and 'onnxruntime' in notes[0] and 'PyTorch' in notes[0]
    assert runner.backend == 'torch'


def test_torch_backend_builds_no_runtime_and_other_devices_fall_back(lite):
    notes = []
    assert isinstance(RT.build_runner(lite, 'torch', HW, note=notes.append), RT.TorchRunner) and notes == []
    runner = RT.build_runner(lite, 'openvino', HW, device='meta', note=notes.append)
    assert isinstance(runner, RT.TorchRunner) and len(notes) == 1 and 'CPU only' in notes[0]
    with pytest.raises(ValueError, match='inference_backend'):
        RT.build_runner(lite, 'tensorrt', HW)


def test_export_tool_writes_the_three_files_and_their_check(tmp_path, capsys):
    import importlib.util
    from dpv_sensor.tools.export_onnx import main
    assert main(['--size', '96', '--out', str(tmp_path)]) == 2
    if importlib.util.find_spec('onnx') is None:               # PyTorch's exporter needs it: said, not a traceback
        assert main(['--size', '96x64', '--out', str(tmp_path)]) == 2
        assert 'onnx package' in capsys.readouterr().err and not list(tmp_path.iterdir())
        return
    assert main(['--size', '96x64', '--out', str(tmp_path)]) == 0
    import json
    report = json.loads((tmp_path / 'export.json').read_text())
    assert report['processing_size'] == [96, 64] and report['preset'] == 'lite' and report['num_planes'] == 32
    for part in RT.PARTS:
        assert (tmp_path / f'{part}.onnx').stat().st_size > 1000
        diff = report['parts'][part]['max_diff_vs_torch']
        try:
            import onnxruntime  # noqa: F401
        except ImportError:
            assert diff is None
        else:
            assert diff <= RT.CHECK_TOLERANCE
