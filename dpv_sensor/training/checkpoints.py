"""Training checkpoints and the weights export (safetensors + JSON, never pickle).

Checkpoints (every ``ckpt_every`` steps, and at the end/interrupt) are directories
``<run>/checkpoints/step_XXXXXXX/`` with ``model.safetensors`` (weights), ``optimizer.safetensors``
(AdamW moments, RNG state) and ``state.json`` (step, history, lr schedule, GradScaler, the data
cursor); ``<run>/checkpoints/latest.json`` is replaced atomically and names the newest complete one.
No pickle anywhere: ``--resume`` reads only safetensors and JSON. The export (whenever the validation
score improves) goes through :func:`dpv_sensor.core.nets.checkpoint.save_checkpoint`, atomically.
"""
from __future__ import annotations

import json
import os
import pathlib
import shutil
from typing import Dict, Optional, Tuple

import torch
import torch.nn as nn

from dpv_sensor.common import to_jsonable

__all__ = ['save_training_state', 'latest_checkpoint', 'load_training_state', 'export_weights', 'export_checkpoint']


def _atomic_write_text(path: pathlib.Path, text: str) -> None:
    tmp = path.with_name(path.name + '.tmp')
    tmp.write_text(text)
    os.replace(tmp, path)


def _optimizer_to_flat(optimizer: torch.optim.Optimizer) -> Tuple[Dict[str, torch.Tensor], Dict]:
    sd = optimizer.state_dict()
    tensors, scalars = {}, {}
    for pid, st in sd['state'].items():
        for k, v in st.items():
            if torch.is_tensor(v):
                flat = v.detach().cpu().contiguous()
                tensors[f'state.{pid}.{k}'] = flat.reshape(-1) if v.dim() == 0 else flat
                if v.dim() == 0:
                    scalars[f'{pid}.{k}'] = 'scalar'
            else:
                scalars[f'{pid}.{k}'] = v
    return tensors, {'param_groups': to_jsonable(sd['param_groups']), 'scalars': scalars}


def _optimizer_from_flat(tensors: Dict[str, torch.Tensor], meta: Dict) -> Dict:
    state: Dict[int, Dict] = {}
    for name, v in tensors.items():
        if not name.startswith('state.'):
            continue
        _, pid, k = name.split('.', 2)
        if meta['scalars'].get(f'{pid}.{k}') == 'scalar':
            v = v.reshape(())
        state.setdefault(int(pid), {})[k] = v
    for key, v in meta['scalars'].items():
        if v != 'scalar':
            pid, k = key.split('.', 1)
            state.setdefault(int(pid), {})[k] = v
    return {'state': state, 'param_groups': meta['param_groups']}


def save_training_state(run_dir: str, step: int, model: nn.Module, optimizer: torch.optim.Optimizer,
                        state: Dict, keep: int = 3) -> pathlib.Path:
    """Write ``<run_dir>/checkpoints/step_<step>/`` and point ``latest.json`` at it (atomically)."""
    from safetensors.torch import save_file
    ck = pathlib.Path(run_dir) / 'checkpoints'
    ck.mkdir(parents=True, exist_ok=True)
    name = f'step_{step:07d}'
    tmp = ck / (name + '.tmp')
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    save_file({k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}, str(tmp / 'model.safetensors'))
    opt_t, opt_meta = _optimizer_to_flat(optimizer)
    opt_t['rng.torch'] = torch.get_rng_state()
    if torch.cuda.is_available():
        opt_t['rng.cuda'] = torch.cuda.get_rng_state()
    save_file(opt_t, str(tmp / 'optimizer.safetensors'))
    full = dict(state)
    full['step'] = int(step)
    full['optimizer'] = opt_meta
    (tmp / 'state.json').write_text(json.dumps(to_jsonable(full), indent=1))
    final = ck / name
    if final.exists():
        shutil.rmtree(final)
    os.replace(tmp, final)
    _atomic_write_text(ck / 'latest.json', json.dumps({'step': int(step), 'dir': name}))
    olds = sorted(p for p in ck.glob('step_*') if p.is_dir() and not p.name.endswith('.tmp') and p.name != name)
    for p in olds[:max(0, len(olds) - (keep - 1))]:
        shutil.rmtree(p, ignore_errors=True)
    return final


def latest_checkpoint(run_dir: str) -> Optional[pathlib.Path]:
    """The checkpoint directory named by ``latest.json`` (None when there is none)."""
    ck = pathlib.Path(run_dir) / 'checkpoints'
    f = ck / 'latest.json'
    if not f.is_file():
        return None
    d = ck / json.loads(f.read_text())['dir']
    return d if (d / 'state.json').is_file() else None


def load_training_state(ckpt_dir, model: nn.Module, optimizer: Optional[torch.optim.Optimizer] = None,
                        device='cpu') -> Dict:
    """Restore model (and optimizer, RNG) from a checkpoint directory; returns its state.json dict."""
    from safetensors.torch import load_file
    ckpt_dir = pathlib.Path(ckpt_dir)
    state = json.loads((ckpt_dir / 'state.json').read_text())
    sd = load_file(str(ckpt_dir / 'model.safetensors'), device=str(device))
    model.load_state_dict(sd)
    opt_t = load_file(str(ckpt_dir / 'optimizer.safetensors'))
    if optimizer is not None:
        osd = _optimizer_from_flat(opt_t, state['optimizer'])
        optimizer.load_state_dict(osd)
    if 'rng.torch' in opt_t:
        torch.set_rng_state(opt_t['rng.torch'])
    if 'rng.cuda' in opt_t and torch.cuda.is_available():
        torch.cuda.set_rng_state(opt_t['rng.cuda'])
    return state


def export_weights(model: nn.Module, path: str, metadata: Dict) -> None:
    """Export the weights with metadata via nets/checkpoint.save_checkpoint, atomically
    (write a temp file in the same folder, then rename over the target)."""
    from dpv_sensor.core.nets.checkpoint import save_checkpoint
    target = pathlib.Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f'.{target.stem}.tmp-{os.getpid()}.safetensors')
    try:
        save_checkpoint(str(tmp), model, to_jsonable(metadata))
        os.chmod(tmp, 0o644)          # a packaged file: readable by the user the node runs as
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()


def export_checkpoint(ckpt_dir, path: str) -> Dict:
    """Export one training checkpoint's weights (``<run>/checkpoints/step_XXXXXXX``) as weights the node loads,
    whatever its validation said: to score a chosen step of a run on other data than the trainer's validation
    (the trainer itself exports only a better validation score). The metadata say which run and step, and carry
    the run's configuration; returns them."""
    from dpv_sensor.core.nets.model import DPVNet
    from safetensors.torch import load_file
    ckpt_dir = pathlib.Path(ckpt_dir)
    state = json.loads((ckpt_dir / 'state.json').read_text())
    cfg = state.get('config', {})
    model = DPVNet(cfg.get('preset', 'lite'))
    model.load_state_dict(load_file(str(ckpt_dir / 'model.safetensors')))
    prior_steps = 0
    if cfg.get('init_weights'):
        from dpv_sensor.core.nets.checkpoint import read_metadata
        try:
            prior_steps = int(read_metadata(cfg['init_weights']).get('steps') or 0)
        except (OSError, ValueError, RuntimeError) as exc:
            import warnings
            warnings.warn(f'export: the steps of the initial weights {cfg["init_weights"]} cannot be read ({exc}); '
                          f'the exported "steps" counts this run\'s {int(state["step"])} only', stacklevel=2)
            prior_steps = 0
    meta = {'steps_this_run': int(state['step']), 'steps': prior_steps + int(state['step']),
            'exported_from': f'{ckpt_dir.parent.parent.name}/{ckpt_dir.name}',
            'train_input_size': [cfg.get('width'), cfg.get('height')], 'training_config': cfg,
            'validation_metrics': None}
    export_weights(model, path, meta)
    return meta
