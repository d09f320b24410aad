"""Checkpoints: safetensors weights + JSON metadata; never pickle.

File layout (standard safetensors): 8-byte little-endian header length N, N bytes of JSON header
(tensor names, dtypes, shapes, data offsets, and a ``__metadata__`` dict of strings), then the raw
tensor data. dpv_sensor stores its metadata as one JSON document under ``__metadata__['dpv_sensor']``:

    format          'dpv_sensor.nets/1' (a file-format name, not a module path: it stays when modules move)
    preset          preset name;  preset_config: the full Preset (so a customised one round-trips)
    num_planes (and D), d_min, d_max, input_size [w, h]
    training_data, steps, validation_metrics     (from the caller; None when not given)
    code_version    dpv_sensor.__version__ ('+g<hash>' appended when a git checkout is found)
    tensors_sha256  SHA-256 over the tensors (names, dtypes, shapes, bytes in name order)
    ... plus any other JSON-serialisable keys the caller passes.

:func:`load_checkpoint` reads the file's bytes, validates them itself and only then hands them to
``safetensors.torch.load``; every failure raises :class:`CheckpointError` with a message that names
the problem: file missing, not a safetensors file, truncated (size mismatch), not a dpv_sensor
checkpoint, wrong preset (or a preset whose D / d_min / d_max differ), missing or unexpected
tensors, shape mismatch, corrupted data (checksum mismatch), or weights adapted to a recording
(``adaptation`` in the metadata, written by the ``adapt`` tool) at another processing size than the
caller's (``processing_size``): adapted weights are fitted to the image scale they were adapted at.
"""
from __future__ import annotations

import hashlib
import json
import os
import struct
import tempfile
from pathlib import Path
from typing import Dict, Optional, Tuple, Union

import torch

from dpv_sensor.common import code_version
from dpv_sensor.core.nets.presets import Preset, get_preset, preset_from_dict

__all__ = ['CheckpointError', 'save_checkpoint', 'load_checkpoint', 'read_metadata', 'default_weights_path',
           'code_version', 'FORMAT', 'METADATA_KEY']

FORMAT = 'dpv_sensor.nets/1'         # the file format's name; every shipped and trained file carries it
METADATA_KEY = 'dpv_sensor'
_MAX_HEADER = 100 * 2 ** 20          # safetensors' own limit on the JSON header
# Preset fields that neither shape the weights nor change what they compute (memory chunking, the
# initial values of learnt scalars, the nominal input size, free text): a difference is not an error.
_RUNTIME_FIELDS = frozenset({'description', 'cost_plane_chunk', 'softmax_scale_init', 'knet_damping_init',
                             'input_size'})


class CheckpointError(RuntimeError):
    """A checkpoint could not be used; the message says why."""


def default_weights_path(preset: Union[str, Preset]) -> Path:
    """``<dpv_sensor package>/weights/<preset>.safetensors`` (the file may not exist)."""
    name = preset.name if isinstance(preset, Preset) else str(preset)
    try:
        from importlib.resources import files
        base = Path(str(files('dpv_sensor')))
    except (ImportError, ModuleNotFoundError, TypeError):    # pragma: no cover - very old Pythons
        base = Path(__file__).resolve().parents[2]
    return base / 'weights' / f'{name}.safetensors'


def _tensors_digest(tensors: Dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(name.encode())
        h.update(str(t.dtype).encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b'')
    return h.hexdigest()


def _state_tensors(model: torch.nn.Module) -> Dict[str, torch.Tensor]:
    """Persistent state as contiguous CPU tensors (safetensors needs contiguous, unshared storage)."""
    return {k: v.detach().to('cpu').contiguous().clone() for k, v in model.state_dict().items()}


def save_checkpoint(path, model, metadata: Optional[dict] = None) -> Path:
    """Write ``model`` (a DPVNet) and ``metadata`` to ``path`` (atomically: temp file + rename).

    ``metadata`` holds what the caller knows - ``training_data``, ``steps``, ``validation_metrics`` and any
    other JSON-serialisable keys. Preset, D, d_min, d_max, input size, code version and the checksum are
    filled in from the model; a caller value that contradicts the model raises CheckpointError.
    Returns the path.
    """
    from safetensors.torch import save as st_save

    preset: Preset = model.preset
    meta = dict(metadata or {})
    derived = {
        'format': FORMAT,
        'preset': preset.name,
        'preset_config': preset.to_dict(),
        'num_planes': preset.num_planes,
        'D': preset.num_planes,
        'd_min': preset.d_min,
        'd_max': preset.d_max,
        'input_size': list(preset.input_size),
    }
    for k, v in derived.items():
        if k in meta and k != 'input_size' and json.loads(json.dumps(meta[k])) != v:
            raise CheckpointError(f'metadata {k}={meta[k]!r} contradicts the model ({v!r})')
    if 'input_size' in meta:      # the size actually trained at may differ from the preset's nominal size
        derived['input_size'] = [int(x) for x in meta['input_size']]
    meta.update(derived)
    meta.setdefault('training_data', None)
    meta.setdefault('steps', None)
    meta.setdefault('validation_metrics', None)
    meta['code_version'] = meta.get('code_version') or code_version()
    tensors = _state_tensors(model)
    meta['tensors_sha256'] = _tensors_digest(tensors)
    try:
        text = json.dumps(meta, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise CheckpointError(f'metadata is not JSON-serialisable: {e}') from None
    data = st_save(tensors, metadata={METADATA_KEY: text})
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + '.', suffix='.tmp', dir=str(path.parent))
    try:
        with os.fdopen(fd, 'wb') as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


_DTYPE_SIZES = {'F64': 8, 'F32': 4, 'F16': 2, 'BF16': 2, 'I64': 8, 'I32': 4, 'I16': 2, 'I8': 1, 'U8': 1,
                'BOOL': 1, 'U16': 2, 'U32': 4, 'U64': 8, 'F8_E4M3': 1, 'F8_E5M2': 1}


def _parse_header(data: bytes, path: Path) -> Tuple[dict, int]:
    """Validate the safetensors framing of ``data``; returns (header dict, data-section offset)."""
    size = len(data)
    if size < 8:
        raise CheckpointError(f'{path}: not a safetensors file (only {size} bytes, no header)')
    (n,) = struct.unpack('<Q', data[:8])
    if n == 0 or n > _MAX_HEADER:
        raise CheckpointError(f'{path}: not a safetensors file (header length field {n} is implausible)')
    if 8 + n > size:
        start = data[8:9]
        if start == b'{':
            raise CheckpointError(f'{path}: truncated (size mismatch): the file has {size} bytes but its '
                                  f'header alone declares {8 + n}')
        raise CheckpointError(f'{path}: not a safetensors file (header length {n} exceeds the file size {size})')
    try:
        header = json.loads(data[8:8 + n].decode('utf-8'))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CheckpointError(f'{path}: not a safetensors file (header is not valid JSON: {e})') from None
    if not isinstance(header, dict):
        raise CheckpointError(f'{path}: not a safetensors file (header is not a JSON object)')
    end = 0
    for name, info in header.items():
        if name == '__metadata__':
            continue
        try:
            b, e = (int(x) for x in info['data_offsets'])
            shape = [int(s) for s in info['shape']]
            dsize = _DTYPE_SIZES[info['dtype']]
        except (KeyError, TypeError, ValueError):
            raise CheckpointError(f'{path}: not a safetensors file (bad header entry for tensor {name!r})') from None
        numel = 1
        for s in shape:
            numel *= s
        if e - b != numel * dsize or b < 0:
            raise CheckpointError(f'{path}: corrupted header: tensor {name!r} has shape {shape} '
                                  f'but occupies {e - b} bytes')
        end = max(end, e)
    expected = 8 + n + end
    if size != expected:
        what = 'truncated' if size < expected else 'has trailing bytes'
        raise CheckpointError(f'{path}: {what} (size mismatch): the file has {size} bytes, its header '
                              f'declares {expected}')
    return header, 8 + n


def _read(path) -> Tuple[bytes, dict, dict]:
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f'checkpoint file not found: {path}')
    if not path.is_file():
        raise CheckpointError(f'checkpoint path is not a file: {path}')
    data = path.read_bytes()
    header, _ = _parse_header(data, path)
    raw = (header.get('__metadata__') or {}).get(METADATA_KEY)
    if raw is None:
        raise CheckpointError(f'{path}: a safetensors file but not a dpv_sensor checkpoint '
                              f'(no {METADATA_KEY!r} metadata)')
    try:
        meta = json.loads(raw)
    except json.JSONDecodeError as e:
        raise CheckpointError(f'{path}: corrupted metadata (not valid JSON: {e})') from None
    if not isinstance(meta, dict) or meta.get('format') != FORMAT:
        found = meta.get('format') if isinstance(meta, dict) else None
        raise CheckpointError(f'{path}: unsupported checkpoint format {found!r} (expected {FORMAT!r})')
    return data, header, meta


def read_metadata(path) -> dict:
    """The dpv_sensor metadata of a checkpoint (validates the file framing, not the tensors)."""
    return _read(path)[2]


def load_checkpoint(path, preset: Union[None, str, Preset] = None, device='cpu', model=None,
                    processing_size: Optional[Tuple[int, int]] = None):
    """Load a checkpoint written by :func:`save_checkpoint`.

    Args:
        path: the .safetensors file.
        preset: the preset the caller expects (name or Preset). None: use the checkpoint's own.
        device: where to put the model.
        model: optionally an existing DPVNet to load into (its preset must match).
        processing_size: (width, height) the caller runs the nets at; weights adapted to a recording at
            another size are refused (None: not checked).
    Returns:
        (model in eval mode, metadata dict)
    Raises:
        CheckpointError naming the problem (see the module docstring).
    """
    from safetensors.torch import load as st_load

    from dpv_sensor.core.nets.model import DPVNet

    path = Path(path)
    data, header, meta = _read(path)
    try:
        stored = preset_from_dict(meta['preset_config'])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f'{path}: corrupted metadata (bad preset_config: {e})') from None
    if preset is None and model is not None:
        preset = model.preset
    use = _check_preset(path, preset, stored, meta) if preset is not None else stored
    if processing_size is not None:
        _check_adapted_size(path, meta, processing_size)
    net = model if model is not None else DPVNet(use)
    _check_tensor_shapes(path, net, header)
    try:
        tensors = st_load(data)
    except Exception as e:  # safetensors raises its own error types
        raise CheckpointError(f'{path}: not a safetensors file ({e})') from None
    digest = meta.get('tensors_sha256')
    if digest is None or _tensors_digest(tensors) != digest:
        raise CheckpointError(f'{path}: corrupted: tensor data checksum mismatch (SHA-256 differs from the '
                              f'one recorded at save time)')
    state = net.state_dict()
    for k, v in tensors.items():
        if v.dtype != state[k].dtype:
            raise CheckpointError(f'{path}: dtype mismatch for {k}: checkpoint {v.dtype} vs model {state[k].dtype}')
    net.load_state_dict(tensors, strict=True)
    net.set_channels_last(net._channels_last, net.knet.channels_last)   # restore memory layout
    return net.to(device).eval(), meta


def _check_preset(path: Path, preset: Union[str, Preset], stored: Preset, meta: dict) -> Preset:
    """The requested preset, after checking that the checkpoint's (``stored``) is the same one."""
    stored_name = meta.get('preset')
    want = get_preset(preset) if isinstance(preset, Preset) else _get_named(preset, path)
    if want.name != stored_name:
        raise CheckpointError(f'{path}: wrong preset: the checkpoint is for preset {stored_name!r} '
                              f'but preset {want.name!r} was requested')
    for field, label in (('num_planes', 'D'), ('d_min', 'd_min'), ('d_max', 'd_max')):
        if getattr(want, field) != meta.get(field) or getattr(want, field) != getattr(stored, field):
            raise CheckpointError(f'{path}: wrong preset: preset {want.name!r} has {label}='
                                  f'{getattr(want, field)} but the checkpoint has {label}={meta.get(field)}')
    wd, sd = want.to_dict(), stored.to_dict()
    diff = sorted(k for k, v in wd.items() if k not in _RUNTIME_FIELDS and sd.get(k) != v)
    if diff:
        raise CheckpointError(f"{path}: wrong preset: preset {want.name!r} differs from the checkpoint's "
                              f'in {", ".join(diff)}')
    return want


def _check_adapted_size(path: Path, meta: dict, processing_size) -> None:
    """Weights adapted to a recording (metadata ``adaptation``) run at the processing size they were adapted at."""
    adaptation = meta.get('adaptation')
    if not isinstance(adaptation, dict):
        return
    try:
        adapted = [int(v) for v in adaptation['processing_size']]
    except (KeyError, TypeError, ValueError):
        raise CheckpointError(f'{path}: corrupted metadata (adapted weights without a valid processing_size)') from None
    want = [int(v) for v in processing_size]
    if adapted != want:
        raise CheckpointError(f'{path}: adapted to a recording at processing size {adapted[0]}x{adapted[1]}, but '
                              f'the nets run at {want[0]}x{want[1]}: set processing_width:={adapted[0]} '
                              f'processing_height:={adapted[1]}, or adapt again at {want[0]}x{want[1]}')


def _check_tensor_shapes(path: Path, net, header: dict) -> None:
    """The checkpoint holds exactly the model's tensors, each with the model's shape."""
    expected = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    stored_shapes = {k: tuple(v['shape']) for k, v in header.items() if k != '__metadata__'}
    missing = sorted(set(expected) - set(stored_shapes))
    unexpected = sorted(set(stored_shapes) - set(expected))
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f'missing tensors {_names(missing)}')
        if unexpected:
            parts.append(f'unexpected tensors {_names(unexpected)}')
        raise CheckpointError(f'{path}: ' + '; '.join(parts))
    bad = [f'{k}: checkpoint {stored_shapes[k]} vs model {expected[k]}' for k in sorted(expected)
           if stored_shapes[k] != expected[k]]
    if bad:
        raise CheckpointError(f'{path}: shape mismatch: ' + '; '.join(bad[:5]) + (' ...' if len(bad) > 5 else ''))


def _get_named(name, path) -> Preset:
    try:
        return get_preset(name)
    except ValueError as e:
        raise CheckpointError(f'{path}: wrong preset: {e}') from None


def _names(names, limit: int = 6) -> str:
    shown = ', '.join(names[:limit])
    return f'[{shown}{", ..." if len(names) > limit else ""}] ({len(names)})'
