"""Where the networks run: PyTorch (the reference), or a deployment runtime on ONNX files exported from the same
weights (ONNX Runtime's CPU provider, OpenVINO). The ``inference_backend`` setting chooses.

    nets = build_runner(model, 'onnxruntime', image_hw=(256, 320), device='cpu', bfloat16=False, note=log.warning)
    feats = nets.extract_features(image_b3hw)            # ImageFeatures(fusion, half)
    correction = nets.knet(residual_bdhw, image_b3hw)    # float32, as DPVNet.knet
    logp_full = nets.refine(logp_q_bdhw, feats, image_b3hw)   # float32, as DPVNet.refine

Three parts are exported (:data:`PARTS`): ``features`` (D-Net's feature extractor, image normalisation included),
``knet`` and ``rnet``. The cost volume stays in PyTorch: it is float32 geometry (a plane sweep by ``grid_sample``
over however many sources the window has), and on the CPU PyTorch's is as fast as the runtimes'.

The files: each part is exported from the loaded weights with ``torch.onnx.export`` (the TorchScript exporter,
opset 17, static shapes at the processing size, batch 1) the first time a node starts with those weights, and kept
in a cache folder (``$XDG_CACHE_HOME/dpv_sensor/onnx``, else ``~/.cache/dpv_sensor/onnx``; a temporary folder when
that cannot be written) under a key made of the weights' digest, the preset, the part, the input shapes, the torch
version and :data:`EXPORT_FORMAT`: adapted weights get their own files without a tool step, and a restart finds
them. The same files feed TensorRT or ONNX Runtime's CUDA provider on a GPU (:func:`export_onnx` writes them to any
folder). Every time a runtime session is made, its outputs are checked against PyTorch's in float32 on fixed inputs
(:func:`check_part`): the largest difference, relative to the largest magnitude of the output (at least 1), must be
at most :data:`CHECK_TOLERANCE` (1e-4), else the part is refused.

Precision: ONNX Runtime's CPU provider runs float32 (it has no bfloat16 convolutions); OpenVINO runs bfloat16
where ``bfloat16`` is asked (``cpu_precision``, as PyTorch's autocast) and float32 otherwise. A runtime that cannot
be imported, cannot export or compile a part, fails the check, or raises while running, is reported once through
``note`` and PyTorch runs from then on (:class:`FallbackRunner`).

Threads: the runtimes use as many threads as torch (``torch.get_num_threads()``), without spin-waiting after a run
(ONNX Runtime's spinning threads took the cores from the PyTorch work between two runs: 3-8x slower stages).
"""
from __future__ import annotations

import contextlib
import copy
import hashlib
import importlib.util
import json
import os
import pathlib
import tempfile
import warnings
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from dpv_sensor.core.nets.dnet import ImageFeatures, feature_size

__all__ = ['BACKENDS', 'PARTS', 'CHECK_TOLERANCE', 'EXPORT_FORMAT', 'RuntimeUnavailable', 'TorchRunner',
           'OnnxRunner', 'FallbackRunner', 'build_runner', 'export_onnx', 'example_inputs', 'check_part',
           'cache_dir', 'weights_digest', 'part_module']

BACKENDS = ('torch', 'onnxruntime', 'openvino')
PARTS = ('features', 'knet', 'rnet')
CHECK_TOLERANCE = 1e-4
EXPORT_FORMAT = 'dpv_sensor.onnx/1'    # bump when the exported graphs change meaning
OPSET = 17


class RuntimeUnavailable(RuntimeError):
    """A runtime could not be used (not installed, export or compile failed, outputs differ from PyTorch's)."""


# --------------------------------------------------------------------------------------------------------------
# the parts as modules with tensor inputs and outputs (what is exported)
# --------------------------------------------------------------------------------------------------------------
class _Features(torch.nn.Module):
    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, image_b3hw):
        f = self.model.extract_features(image_b3hw)
        return f.fusion, f.half


class _KNet(torch.nn.Module):
    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, residual_bdhw, image_b3hw):
        return self.model.knet(residual_bdhw, image_b3hw)


class _RNet(torch.nn.Module):
    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, logp_bdhw, fusion_bchw, half_bchw, image_b3hw):
        return self.model.refine(logp_bdhw, ImageFeatures(fusion_bchw, half_bchw), image_b3hw)


_PART_MODULES = {'features': _Features, 'knet': _KNet, 'rnet': _RNet}


def part_module(model, part: str) -> torch.nn.Module:
    """The part of a DPVNet as a module of tensors (``features``: image -> (fusion, half); ``knet``: residual,
    image -> correction; ``rnet``: logp, fusion, half, image -> full-resolution logp)."""
    if part not in _PART_MODULES:
        raise ValueError(f'part must be one of {PARTS}, not {part!r}')
    return _PART_MODULES[part](model).eval()


def example_inputs(model, part: str, image_hw: Tuple[int, int], seed: int = 0) -> Tuple[torch.Tensor, ...]:
    """Fixed inputs of a part at an image size (float32, CPU, batch 1): a random image in [0, 1], a residual of a
    few nats, a normalised log-DPV, and for R-Net the features of that image."""
    H, W = int(image_hw[0]), int(image_hw[1])
    h, w = feature_size(H, W)
    D = int(model.num_planes)
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(1, 3, H, W, generator=g)
    if part == 'features':
        return (image,)
    if part == 'knet':
        return (3.0 * torch.randn(1, D, h, w, generator=g), image)
    logp = torch.log_softmax(2.0 * torch.randn(1, D, h, w, generator=g), 1)
    with torch.no_grad():
        f = _float_model(model).extract_features(image)
    return (logp, f.fusion.contiguous(), f.half.contiguous(), image)


def _float_model(model):
    """A float32 CPU copy of a DPVNet in the plain (NCHW) layout: what is exported and what a check compares with."""
    m = copy.deepcopy(model).to('cpu').float().eval()
    m.set_channels_last(False, False)
    return m


def weights_digest(model) -> str:
    """SHA-256 over the model's state (names, dtypes, shapes, bytes; as the checkpoint's ``tensors_sha256``)."""
    from dpv_sensor.core.nets.checkpoint import _tensors_digest
    return _tensors_digest({k: v.detach().to('cpu') for k, v in model.state_dict().items()})


def cache_dir() -> pathlib.Path:
    """``$XDG_CACHE_HOME/dpv_sensor/onnx`` (``~/.cache/dpv_sensor/onnx`` without it)."""
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return pathlib.Path(base) / 'dpv_sensor' / 'onnx'


def _cache_key(digest: str, model, part: str, inputs: Sequence[torch.Tensor]) -> str:
    shapes = 'x'.join('_'.join(str(int(s)) for s in t.shape) for t in inputs)
    text = json.dumps([EXPORT_FORMAT, OPSET, torch.__version__, model.preset.name, digest, part, shapes])
    return f'{model.preset.name}_{part}_{shapes}_{hashlib.sha256(text.encode()).hexdigest()[:16]}'


def export_onnx(model, part: str, image_hw: Tuple[int, int], path) -> pathlib.Path:
    """Export one part of ``model`` at an image size (H, W) to ``path`` (written atomically); returns the path.
    Raises RuntimeUnavailable where the onnx package PyTorch's exporter writes with is not installed."""
    if importlib.util.find_spec('onnx') is None:
        raise RuntimeUnavailable('exporting ONNX files needs the onnx package, which this environment does not '
                                 'have (pip install onnx)')
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    m = _float_model(model)
    inputs = example_inputs(m, part, image_hw)
    names = {'features': (['image'], ['fusion', 'half']), 'knet': (['residual', 'image'], ['correction']),
             'rnet': (['logp', 'fusion', 'half', 'image'], ['logp_full'])}[part]
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', dir=str(path.parent))
    os.close(fd)
    try:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter('ignore')
            torch.onnx.export(part_module(m, part), inputs, tmp, dynamo=False, opset_version=OPSET,
                              input_names=names[0], output_names=names[1], do_constant_folding=True)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def _cached_onnx(model, part: str, image_hw: Tuple[int, int], digest: str, fresh: bool = False) -> pathlib.Path:
    """The part's ONNX file from the cache, exported there first when missing (or always with ``fresh``)."""
    inputs = example_inputs(model, part, image_hw)
    name = _cache_key(digest, model, part, inputs) + '.onnx'
    for folder in (cache_dir(), pathlib.Path(tempfile.gettempdir()) / f'dpv_sensor_onnx_{os.getuid()}'):
        path = folder / name
        if path.exists() and not fresh:
            return path
        try:
            return export_onnx(model, part, image_hw, path)
        except OSError:
            continue                      # the folder cannot be written: the next one
    raise RuntimeUnavailable(f'no writable folder for the ONNX files (tried {cache_dir()} and the temp folder)')


def check_part(model, part: str, run: Callable[[List[np.ndarray]], List[np.ndarray]],
               image_hw: Tuple[int, int]) -> float:
    """The largest difference between ``run``'s outputs and PyTorch's (float32) on :func:`example_inputs`, each
    relative to the largest magnitude of PyTorch's output (at least 1)."""
    m = _float_model(model)
    inputs = example_inputs(m, part, image_hw)
    with torch.no_grad():
        want = part_module(m, part)(*inputs)
    want = want if isinstance(want, tuple) else (want,)
    got = run([t.numpy() for t in inputs])
    worst = 0.0
    for g, w in zip(got, want):
        w = w.numpy()
        if g.shape != w.shape:
            return float('inf')
        worst = max(worst, float(np.abs(g - w).max()) / max(1.0, float(np.abs(w).max())))
    return worst


# --------------------------------------------------------------------------------------------------------------
# runners
# --------------------------------------------------------------------------------------------------------------
class TorchRunner:
    """The networks in PyTorch, under the caller's autocast (``autocast()`` gives the context)."""

    backend = 'torch'

    def __init__(self, model, autocast: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext):
        self.model = model
        self.autocast = autocast

    def extract_features(self, image_b3hw: torch.Tensor) -> ImageFeatures:
        with self.autocast():
            return self.model.extract_features(image_b3hw)

    def knet(self, residual_bdhw: torch.Tensor, image_b3hw: torch.Tensor) -> torch.Tensor:
        with self.autocast():
            return self.model.knet(residual_bdhw, image_b3hw).float()

    def refine(self, logp_bdhw: torch.Tensor, feats: ImageFeatures, image_b3hw: torch.Tensor) -> torch.Tensor:
        with self.autocast():
            out = self.model.refine(logp_bdhw, feats, image_b3hw)
        return out.float()


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().to('cpu', torch.float32).contiguous().numpy()


class _OrtSession:
    def __init__(self, path: pathlib.Path, threads: int):
        import onnxruntime as ort
        so = ort.SessionOptions()
        so.intra_op_num_threads = int(threads)
        so.inter_op_num_threads = 1
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        so.add_session_config_entry('session.intra_op.allow_spinning', '0')
        so.log_severity_level = 3
        self.session = ort.InferenceSession(str(path), so, providers=['CPUExecutionProvider'])
        self.inputs = [i.name for i in self.session.get_inputs()]

    def __call__(self, arrays: List[np.ndarray]) -> List[np.ndarray]:
        return self.session.run(None, dict(zip(self.inputs, arrays)))


class _OpenVinoSession:
    def __init__(self, path: pathlib.Path, threads: int, bfloat16: bool):
        import openvino as ov
        core = ov.Core()
        config = {'INFERENCE_PRECISION_HINT': 'bf16' if bfloat16 else 'f32', 'INFERENCE_NUM_THREADS': int(threads),
                  'PERFORMANCE_HINT': 'LATENCY', 'NUM_STREAMS': 1, 'ENABLE_CPU_PINNING': False}
        self.compiled = core.compile_model(core.read_model(str(path)), 'CPU', config)
        self.request = self.compiled.create_infer_request()

    def __call__(self, arrays: List[np.ndarray]) -> List[np.ndarray]:
        result = self.request.infer(arrays)
        return [np.array(result[o]) for o in self.compiled.outputs]


def _import(backend: str) -> str:
    """The runtime's version; raises RuntimeUnavailable when it cannot be imported."""
    try:
        if backend == 'onnxruntime':
            import onnxruntime as mod
        else:
            import openvino as mod
    except Exception as exc:            # ImportError, or a broken install failing in its own import
        raise RuntimeUnavailable(f'{backend} cannot be imported ({type(exc).__name__}: {exc})') from None
    return str(getattr(mod, '__version__', '?'))


class OnnxRunner:
    """The networks on ONNX files in ONNX Runtime (float32) or OpenVINO (float32 or bfloat16). Every part is
    exported (or found in the cache), loaded and checked in the constructor; raises RuntimeUnavailable."""

    def __init__(self, model, backend: str, image_hw: Tuple[int, int], bfloat16: bool = False,
                 threads: Optional[int] = None):
        if backend not in ('onnxruntime', 'openvino'):
            raise ValueError(f'backend must be onnxruntime or openvino, not {backend!r}')
        self.backend = backend
        self.version = _import(backend)
        self.image_hw = (int(image_hw[0]), int(image_hw[1]))
        self.bfloat16 = bool(bfloat16) and backend == 'openvino'
        threads = int(threads or torch.get_num_threads())
        digest = weights_digest(model)
        self.device = next(model.parameters()).device
        self.paths: Dict[str, pathlib.Path] = {}
        self.sessions: Dict[str, Callable] = {}
        self.check: Dict[str, float] = {}
        for part in PARTS:
            try:
                path = _cached_onnx(model, part, self.image_hw, digest)
                try:
                    f32 = self._session(path, threads, False)
                except Exception:          # a cached file the runtime refuses (damaged, or from another version)
                    path = _cached_onnx(model, part, self.image_hw, digest, fresh=True)
                    f32 = self._session(path, threads, False)
            except RuntimeUnavailable:
                raise
            except Exception as exc:
                raise RuntimeUnavailable(f'{backend}: the {part} part could not be exported or loaded '
                                         f'({type(exc).__name__}: {exc})') from None
            diff = check_part(model, part, f32, self.image_hw)
            if not diff <= CHECK_TOLERANCE:
                raise RuntimeUnavailable(f'{backend}: the {part} part differs from PyTorch by {diff:.2g} '
                                         f'(more than {CHECK_TOLERANCE:g})')
            self.paths[part], self.check[part] = path, diff
            self.sessions[part] = self._session(path, threads, True) if self.bfloat16 else f32

    def _session(self, path, threads, bfloat16):
        if self.backend == 'onnxruntime':
            return _OrtSession(path, threads)
        return _OpenVinoSession(path, threads, bfloat16)

    @property
    def precision(self) -> str:
        return 'bfloat16' if self.bfloat16 else 'float32'

    def _run(self, part: str, tensors: Sequence[torch.Tensor]) -> List[torch.Tensor]:
        out = self.sessions[part]([_numpy(t) for t in tensors])
        return [torch.from_numpy(np.ascontiguousarray(o, dtype=np.float32)).to(self.device) for o in out]

    def _check_size(self, image_b3hw: torch.Tensor) -> None:
        if tuple(image_b3hw.shape) != (1, 3) + self.image_hw:
            raise RuntimeUnavailable(f'{self.backend}: the ONNX files are for (1, 3, {self.image_hw[0]}, '
                                     f'{self.image_hw[1]}) images, got {tuple(image_b3hw.shape)}')

    def extract_features(self, image_b3hw: torch.Tensor) -> ImageFeatures:
        self._check_size(image_b3hw)
        fusion, half = self._run('features', [image_b3hw])
        return ImageFeatures(fusion, half)

    def knet(self, residual_bdhw: torch.Tensor, image_b3hw: torch.Tensor) -> torch.Tensor:
        self._check_size(image_b3hw)
        return self._run('knet', [residual_bdhw, image_b3hw])[0]

    def refine(self, logp_bdhw: torch.Tensor, feats: ImageFeatures, image_b3hw: torch.Tensor) -> torch.Tensor:
        self._check_size(image_b3hw)
        return self._run('rnet', [logp_bdhw, feats.fusion, feats.half, image_b3hw])[0]


class FallbackRunner:
    """A runtime with PyTorch behind it: the first error of the runtime is reported through ``note`` and PyTorch
    runs every call from then on (the call that failed included)."""

    def __init__(self, runtime, torch_runner: TorchRunner, note: Callable[[str], None]):
        self.runtime = runtime
        self.torch = torch_runner
        self.note = note
        self.failed: Optional[str] = None

    @property
    def backend(self) -> str:
        return self.torch.backend if self.failed else self.runtime.backend

    def _call(self, name: str, *args):
        if self.failed is None:
            try:
                return getattr(self.runtime, name)(*args)
            except Exception as exc:
                self.failed = f'{type(exc).__name__}: {exc}'
                self.note(f'inference_backend={self.runtime.backend} failed while running ({self.failed}); '
                          'running PyTorch from now on')
        return getattr(self.torch, name)(*args)

    def extract_features(self, image_b3hw):
        return self._call('extract_features', image_b3hw)

    def knet(self, residual_bdhw, image_b3hw):
        return self._call('knet', residual_bdhw, image_b3hw)

    def refine(self, logp_bdhw, feats, image_b3hw):
        return self._call('refine', logp_bdhw, feats, image_b3hw)


def build_runner(model, backend: str, image_hw: Tuple[int, int], device='cpu', bfloat16: bool = False,
                 autocast: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext,
                 note: Callable[[str], None] = lambda text: None, threads: Optional[int] = None):
    """The runner of ``backend`` for ``model`` at the processing size ``image_hw`` (H, W): a :class:`TorchRunner`
    for 'torch'; else an :class:`OnnxRunner` behind a :class:`FallbackRunner`, or, where the runtime cannot be
    used here (not installed, a part that does not export, load or pass the check, a device other than the CPU),
    a TorchRunner after one ``note`` saying why."""
    if backend not in BACKENDS:
        raise ValueError(f'inference_backend must be one of {BACKENDS}, not {backend!r}')
    torch_runner = TorchRunner(model, autocast)
    if backend == 'torch':
        return torch_runner
    if torch.device(device).type != 'cpu':
        note(f'inference_backend={backend} runs on the CPU only; device {device}: running PyTorch')
        return torch_runner
    try:
        runtime = OnnxRunner(model, backend, image_hw, bfloat16=bfloat16, threads=threads)
    except RuntimeUnavailable as exc:
        note(f'inference_backend={backend} cannot be used: {exc}; running PyTorch')
        return torch_runner
    return FallbackRunner(runtime, torch_runner, note)
