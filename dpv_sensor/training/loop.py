"""The training loop: end-to-end NLL training of D-Net, K-Net and R-Net with the DPV filter unrolled.

The loss of one batch is :mod:`.unrolled`'s (paper sec. 3.3); the settings are :class:`.config.TrainConfig`;
validation is :mod:`.validation` (windows) and :mod:`.stream_validation` (whole streams through the Estimator);
checkpoints and the export are :mod:`.checkpoints`, the figures :mod:`.plots`. This module owns the
:class:`Trainer` that ties them together.

Partial fine-tuning (``train_modules``, e.g. ``('knet',)``): only the named sub-networks of DPVNet get
updated; the others are frozen. Without features and cost_volume, D-Net runs without autograd and the
auxiliary term is dropped, which makes long unrolls of K-Net affordable on a CPU.

Optimiser: AdamW, lr 1e-3 with linear warm-up and cosine decay, weight decay only on conv
weights, gradient-norm clipping. The paper used Adam at 1e-5 for 20 epochs on a GPU over tens of
thousands of real frames; with a CPU budget of a few thousand steps of batch 2-4, 1e-5 would barely
move the weights, and our nets have no batch norm but Fixup-like scaled initialisation, which is
stable at 1e-3 with clipping. AMP: bfloat16 (or float16 with a GradScaler) on CUDA, bfloat16 on CPUs with
native kernels (see :func:`resolve_amp`).

Validation runs every ``val_every`` steps on rank 0; with ``val_stream_seeds`` it also streams whole held-out
sequences through the product's Estimator, which is how the node uses the weights: ``stream_abs_rel_knet_both``
and the like select exports on that. Plots: ``<run>/loss_curves.png``, ``<run>/val_montage_XXXXXXX.png``.
Whenever the validation score improves, the weights are exported atomically (temp file + rename)
to the export path with metadata via :func:`dpv_sensor.core.nets.checkpoint.save_checkpoint`.

Distributed: under ``torchrun`` (WORLD_SIZE > 1) a process group is initialised (NCCL on CUDA, Gloo
otherwise), the unrolled model is wrapped in DistributedDataParallel, every rank streams its own
disjoint scene seeds (seed = base + i * world + rank) and only rank 0 validates and writes files.
"""
from __future__ import annotations

import datetime
import json
import math
import os
import pathlib
import shutil
import sys
import time
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch
import torch.nn as nn

from dpv_sensor.common import code_version, to_jsonable
from dpv_sensor.core import dpv as dpvops
from dpv_sensor.core.nets.model import cpu_bf16_fast
from dpv_sensor.training.checkpoints import (export_weights, latest_checkpoint, load_training_state,
                                             save_training_state)
from dpv_sensor.training.config import MODULES, TrainConfig, select_score
from dpv_sensor.training.dataset import VAL_SEEDS, SceneStream
from dpv_sensor.training.plots import plot_curves, save_montage
from dpv_sensor.training.stream_validation import StreamValidator
from dpv_sensor.training.unrolled import UnrolledModel, batch_to_device
from dpv_sensor.training.validation import corrupt_validation_batches, evaluate_batches, render_validation_batches

__all__ = ['Trainer', 'train', 'resolve_amp', 'all_ranks', 'TrainConfig', 'latest_checkpoint']


# ----------------------------------------------------------------------------------------------
# the trainer
# ----------------------------------------------------------------------------------------------

def _dist_env() -> Tuple[int, int, int]:
    world = int(os.environ.get('WORLD_SIZE', '1'))
    rank = int(os.environ.get('RANK', '0'))
    local = int(os.environ.get('LOCAL_RANK', '0'))
    return world, rank, local


def all_ranks(flag: bool, device, world: int) -> bool:
    """``flag`` and-ed over the ranks of the process group (just ``flag`` when ``world`` is 1)."""
    if world <= 1:
        return bool(flag)
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    torch.distributed.all_reduce(t, op=torch.distributed.ReduceOp.MIN)
    return bool(t.item() > 0.5)


def _lr_at(cfg: TrainConfig, step: int) -> float:
    if step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    t = min(1.0, (step - cfg.warmup) / max(1, cfg.steps - cfg.warmup))
    return cfg.lr * (cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * t)))


def _param_groups(model: nn.Module, weight_decay: float):
    decay, no_decay = [], []
    for _, p in model.named_parameters():
        if not p.requires_grad:
            continue
        (decay if p.dim() >= 2 else no_decay).append(p)
    return [{'params': decay, 'weight_decay': weight_decay}, {'params': no_decay, 'weight_decay': 0.0}]


def _worker_init(_):
    """Rendering workers: one thread each (torch and OpenCV), so they never oversubscribe the CPU."""
    torch.set_num_threads(1)
    try:
        import cv2
        cv2.setNumThreads(1)
    except Exception:
        pass


def resolve_amp(amp: str, device: torch.device) -> Optional[torch.dtype]:
    """The autocast dtype of a training step, or None for float32.

    CUDA: ``auto`` is bfloat16 where supported, else float16 (with a gradient scaler); ``bf16`` / ``fp16``
    force one. CPU: ``auto`` is bfloat16 where oneDNN has native kernels (:func:`cpu_bf16_fast`: AMX or
    AVX512-BF16; a lite step at 256x192 then takes 2.1 s instead of 3.8 s, and validation tracks a float32 run
    with the same seeds to 3 digits) and float32 elsewhere; ``bf16`` forces it; ``fp16`` is refused (CPU
    autocast has no float16 kernels worth using). The cost volume, filter, readout and loss stay float32.
    """
    if amp not in ('auto', 'off', 'bf16', 'fp16'):
        raise ValueError(f'amp must be auto, off, bf16 or fp16, got {amp!r}')
    if amp == 'off':
        return None
    if device.type == 'cuda':
        if amp == 'fp16' or (amp == 'auto' and not torch.cuda.is_bf16_supported()):
            return torch.float16
        return torch.bfloat16
    if amp == 'fp16':
        raise ValueError('--amp fp16 is CUDA only; on the CPU use --amp bf16 (or off)')
    if amp == 'bf16' or cpu_bf16_fast():
        return torch.bfloat16
    return None


class Trainer:
    """Owns model, optimiser, data, validation and checkpoints of one run (see the module docstring)."""

    def __init__(self, cfg: TrainConfig, resume: bool = False, quiet: bool = False, argv: Optional[List[str]] = None):
        from dpv_sensor.core.nets.model import DPVNet
        from dpv_sensor.core.nets.presets import get_preset
        self.cfg = cfg.check()
        self.quiet = quiet
        self.argv = list(argv) if argv is not None else list(sys.argv)
        self.world, self.rank, self.local_rank = _dist_env()
        self.is_main = self.rank == 0
        if cfg.device == 'auto':
            dev = f'cuda:{self.local_rank}' if torch.cuda.is_available() else 'cpu'
        else:
            dev = cfg.device
        self.device = torch.device(dev)
        if self.device.type == 'cpu':
            torch.set_num_threads(max(1, cfg.threads))
        if self.world > 1 and not torch.distributed.is_initialized():
            if self.device.type == 'cuda':
                torch.cuda.set_device(self.device)
            torch.distributed.init_process_group(backend='nccl' if self.device.type == 'cuda' else 'gloo')
        torch.manual_seed(cfg.seed)
        self.preset = get_preset(cfg.preset)
        self.model = DPVNet(self.preset).to(self.device)
        if cfg.init_weights:
            from dpv_sensor.core.nets.checkpoint import load_checkpoint
            src, self.init_meta = load_checkpoint(cfg.init_weights, preset=self.preset)
            self.model.load_state_dict(src.state_dict())
        else:
            self.init_meta = None
        self.depths = dpvops.depth_planes(self.preset.d_min, self.preset.d_max, self.preset.num_planes,
                                          device=self.device)
        for name, child in self.model.named_children():
            child.requires_grad_(cfg.trains(name))
        self.optimizer = torch.optim.AdamW(_param_groups(self.model, cfg.weight_decay), lr=cfg.lr,
                                           betas=(0.9, 0.999))
        self.amp_dtype = resolve_amp(cfg.amp, self.device)
        if self.amp_dtype is not None and self.device.type == 'cpu' and not cpu_bf16_fast():
            self._log('warning: --amp bf16 on a CPU without AVX512-BF16/AMX runs emulated and is slower than float32')
        self.scaler = torch.amp.GradScaler('cuda', enabled=self.amp_dtype == torch.float16)
        self.step = 0
        self.history: Dict = {'train': [], 'val': []}
        self._curves_drawn: Optional[tuple] = None        # the history's lengths when loss_curves.png was drawn
        self.best: Optional[float] = None
        self.best_metrics: Optional[Dict] = None
        self.classical_ref: Optional[Dict] = None
        self.samples_seen = 0
        self.wall_s = 0.0
        self.run_dir = pathlib.Path(cfg.run_dir)
        if self.is_main:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        if resume:
            ck = latest_checkpoint(cfg.run_dir)
            if ck is None:
                self._log(f'no checkpoint in {cfg.run_dir}/checkpoints; starting from scratch')
            else:
                st = load_training_state(ck, self.model, self.optimizer, device=self.device)
                self.step = int(st['step'])
                self.history = st.get('history', self.history)
                self.best = st.get('best')
                self.best_metrics = st.get('best_metrics')
                self.classical_ref = st.get('classical_ref')
                self.samples_seen = int(st.get('samples_seen', 0))
                self.wall_s = float(st.get('wall_s', 0.0))
                if st.get('scaler'):
                    self.scaler.load_state_dict(st['scaler'])
                self._log(f'resumed from {ck} at step {self.step}')
        self.unrolled = UnrolledModel(self.model, self.depths, cfg.aux_weight,
                                      measure_grad=cfg.measurement_trained).to(self.device)
        self.ddp = None
        if self.world > 1:
            from torch.nn.parallel import DistributedDataParallel as DDP
            self.ddp = DDP(self.unrolled, device_ids=[self.device.index] if self.device.type == 'cuda' else None)
        self._val_batches = None
        self._noisy_val_batches = None
        self.stream_validator = StreamValidator(cfg.stream_spec())

    # -- helpers --------------------------------------------------------------------------------
    def _validates_now(self) -> bool:
        return self.step % self.cfg.val_every == 0 or self.step == self.cfg.steps

    def _plot_curves(self) -> None:
        """loss_curves.png, unless nothing was added to the history since it was last drawn."""
        drawn = (len(self.history['train']), len(self.history['val']))
        if drawn != self._curves_drawn:
            plot_curves(self.history, str(self.run_dir / 'loss_curves.png'), self.classical_ref)
            self._curves_drawn = drawn

    def _log(self, msg: str) -> None:
        if self.is_main and not self.quiet:
            print(f'[train {datetime.datetime.now().strftime("%H:%M:%S")}] {msg}', flush=True)

    def _append_jsonl(self, name: str, row: Dict) -> None:
        if self.is_main:
            with open(self.run_dir / name, 'a') as f:
                f.write(json.dumps(to_jsonable(row)) + '\n')

    def loader(self):
        """DataLoader over this rank's disjoint seed stream, continuing at the resumed sample."""
        from torch.utils.data import DataLoader
        per_rank_start = self.step * self.cfg.batch_size
        ds = SceneStream(self.cfg.stream_config(), rank=self.rank, world_size=self.world, start_index=per_rank_start)
        kw = {}
        if self.cfg.num_workers > 0:
            kw = dict(num_workers=self.cfg.num_workers, worker_init_fn=_worker_init, prefetch_factor=2,
                      persistent_workers=False)
        return DataLoader(ds, batch_size=self.cfg.batch_size, pin_memory=self.device.type == 'cuda', **kw)

    def val_batches(self):
        if self._val_batches is None:
            w = self.cfg.val_width or self.cfg.width
            h = self.cfg.val_height or self.cfg.height
            self._val_batches = render_validation_batches(self.cfg.val_seeds, self.cfg.val_keyframes,
                                                          self.cfg.val_gap, w, h, self.cfg.layout())
        return self._val_batches

    def noisy_val_batches(self):
        """The validation batches with ``val_pose_noise`` odometry-like pose errors (same poses every time)."""
        if self._noisy_val_batches is None:
            self._noisy_val_batches = corrupt_validation_batches(self.val_batches(), *self.cfg.val_pose_noise)
        return self._noisy_val_batches

    def state_dict_json(self) -> Dict:
        return {'config': self.cfg.to_json(), 'history': self.history, 'best': self.best,
                'best_metrics': self.best_metrics, 'classical_ref': self.classical_ref,
                'samples_seen': self.samples_seen, 'wall_s': self.wall_s,
                'scaler': self.scaler.state_dict() if self.scaler.is_enabled() else None,
                'code_version': code_version(), 'world_size': self.world}

    def save(self) -> None:
        if self.is_main:
            save_training_state(str(self.run_dir), self.step, self.model, self.optimizer, self.state_dict_json(),
                                keep=self.cfg.keep_checkpoints)

    def metadata(self, metrics: Dict) -> Dict:
        cfg = self.cfg
        data = {
            'description': 'synthetic scenes rendered on the fly by dpv_sensor.data.synthetic.render_sequence, '
                           'one fresh scene per sample, runs of consecutive keyframes with 5-frame windows, '
                           'GT poses and depth, photometric augmentation'
                           + (f"; {cfg.folder_prob:.0%} of the samples from the sequence folders "
                              f"{', '.join(os.path.basename(os.path.normpath(f)) for f in cfg.folders)} "
                              '(random scale and crop)' if cfg.folders and cfg.folder_prob > 0 else ''),
            'train_seed_range': [cfg.seed_base, cfg.seed_base + max(1, self.samples_seen) * self.world],
            'train_seed_rule': 'seed = seed_base + i * world_size + rank, i = 0 .. samples per rank - 1',
            'samples_seen': self.samples_seen,
            'validation_seeds': list(cfg.val_seeds),
            'validation_pose_noise': list(cfg.val_pose_noise),
            'validation_stream': ({'seeds': list(cfg.val_stream_seeds), 'frames': cfg.val_stream_frames,
                                   'pose_noise': list(cfg.val_stream_pose_noise),
                                   'how': 'every frame through dpv_sensor.stream.estimator.Estimator (node defaults)'}
                                  if cfg.val_stream_seeds else None),
            'selection_metric': cfg.select_metric,
            'held_out_seed_range': [VAL_SEEDS.start, VAL_SEEDS.stop - 1],
            'mixed_folders': [os.path.basename(os.path.normpath(f)) for f in cfg.folders],
            'folder_prob': cfg.folder_prob,
            'never_trained_on': ['sun3d_3dmatch_frag1', 'sun3d_3dmatch_frag2', 'tum_fr1_rpy', 'icl_nuim_lr_kt3',
                                 f'synthetic seeds {VAL_SEEDS.start}..{VAL_SEEDS.stop - 1}'],
            'train_size': [cfg.width, cfg.height],
            'keyframe_gap_frames': [cfg.gap_min, cfg.gap_max],
            'unrolled_steps': cfg.unroll,
            'window': cfg.window,
            'window_layouts': ['center', 'last'] if cfg.ref_mix else [cfg.ref_position],
            'validation_window': cfg.ref_position,
            'extra_sizes': [list(s) for s in cfg.extra_sizes],
        }
        data['startup_prob'] = cfg.startup_prob
        prior_steps = 0
        if self.init_meta is not None:
            prior_steps = int(self.init_meta.get('steps') or 0)
            data['initialised_from'] = {'file': os.path.basename(cfg.init_weights), 'steps': prior_steps,
                                        'training_data': self.init_meta.get('training_data'),
                                        'loss': self.init_meta.get('loss'),
                                        'optimizer': self.init_meta.get('optimizer')}
        return {
            'steps_this_run': self.step, 'steps_total': prior_steps + self.step,
            'preset': self.preset.name, 'D': self.preset.num_planes, 'd_min': self.preset.d_min,
            'd_max': self.preset.d_max, 'input_size': list(self.preset.input_size),
            'train_input_size': [cfg.width, cfg.height],
            'training_data': data, 'steps': prior_steps + self.step, 'wall_time_s': round(self.wall_s, 1),
            'validation_metrics': metrics, 'validation_seeds': list(cfg.val_seeds),
            'loss': (f'mean over {cfg.unroll} unrolled knet-filter steps of NLL(R-Net output)'
                     + (f' + {cfg.aux_weight} * NLL(D-Net 1/4-res measurement)' if cfg.measurement_trained else '')),
            'trained_modules': [m for m in MODULES if cfg.trains(m)],
            'optimizer': (f'AdamW lr {cfg.lr} cosine (warm-up {cfg.warmup}), wd {cfg.weight_decay}, '
                          f'clip {cfg.clip}, batch {cfg.batch_size} x {self.world}'),
            'code_version': code_version(),
            'exported_at': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
            'command': ' '.join(self.argv),
        }

    # -- validation -----------------------------------------------------------------------------
    def validate(self) -> Dict:
        cfg = self.cfg
        t0 = time.time()
        batches = self.val_batches()
        if self.classical_ref is None:
            from dpv_sensor.core.classical import ClassicalMeasurement
            cm = ClassicalMeasurement(self.preset.d_min, self.preset.d_max, self.preset.num_planes)
            ref = evaluate_batches(None, batches, self.depths, self.device, modes=('none', 'global'), classical=cm)
            ex = ref.pop('examples')
            self.classical_ref = ref
            self._classical_examples = ex
            self._log('classical on validation seeds: ' + json.dumps(to_jsonable(ref)))
        res = evaluate_batches(self.model, batches, self.depths, self.device)
        examples = res.pop('examples')
        examples += getattr(self, '_classical_examples', [])
        metrics = dict(res)
        if max(cfg.val_pose_noise) > 0:
            noisy = evaluate_batches(self.model, self.noisy_val_batches(), self.depths, self.device)
            noisy.pop('examples')
            metrics.update({f'noisy_{k}': v for k, v in noisy.items()})
        window_keys = list(metrics)
        if self.stream_validator.spec.enabled:
            try:
                metrics.update(self.stream_validator(self.model, self.device,
                                                     progress=lambda m: self._log(f'streaming validation {m}')))
            except Exception as e:      # a long run outlives a failed validation; no score means no export
                self._log(f'streaming validation FAILED ({type(e).__name__}: {e}); continuing without it')
        score = select_score(metrics, cfg.select_metric)
        entry = {'step': self.step, 'metrics': metrics, 'score': score, 'seconds': time.time() - t0}
        self.history['val'].append(entry)
        self._append_jsonl('val.jsonl', entry)
        self._log(f'validation step {self.step}: ' + ', '.join(
            f"{k}: abs_rel {v['abs_rel']:.4f} d1 {v['delta1']:.3f} nll(meas1/4 {v['nll_meas_q']:.3f} "
            f"filt1/4 {v['nll_filtered_q']:.3f} full {v['nll_full']:.3f}) conf-half {v['confident_half_ratio']:.2f}"
            for k, v in metrics.items() if k in window_keys) + f' ({entry["seconds"]:.0f} s)'
            + (f'; {cfg.select_metric} {score:.4f}' if score is not None else ''))
        d_min, d_max = self.preset.d_min, self.preset.d_max
        save_montage(examples, str(self.run_dir / f'val_montage_{self.step:07d}.png'), d_min, d_max,
                     title=f'step {self.step}, held-out seed {cfg.val_seeds[0]}, last keyframe')
        shutil.copyfile(self.run_dir / f'val_montage_{self.step:07d}.png', self.run_dir / 'val_montage_latest.png')
        self._plot_curves()
        if score is not None and math.isfinite(score) and (self.best is None or score < self.best):
            self.best = float(score)
            self.best_metrics = {**metrics, 'classical_same_windows': self.classical_ref}
            # the best weights also stay in the run dir (plain safetensors), whatever happens to the export
            from safetensors.torch import save_file
            tmp = self.run_dir / 'best_model.safetensors.tmp'
            save_file({k: v.detach().cpu().contiguous() for k, v in self.model.state_dict().items()}, str(tmp),
                      metadata={'step': str(self.step), 'score': str(score)})
            os.replace(tmp, self.run_dir / 'best_model.safetensors')
            try:
                export_weights(self.model, cfg.resolved_export(), self.metadata(self.best_metrics))
                self._log(f'new best {cfg.select_metric} {score:.4f}: exported {cfg.resolved_export()}')
            except Exception as e:          # never let an export problem kill a long run
                self._log(f'new best {cfg.select_metric} {score:.4f}; EXPORT FAILED ({type(e).__name__}: {e}); '
                          f'weights kept in {self.run_dir / "best_model.safetensors"}')
        return metrics

    # -- training -------------------------------------------------------------------------------
    def _all_ranks_have_grad(self, loss: torch.Tensor) -> bool:
        """Whether every rank's loss reaches a trained sub-network. A rank that skipped backward alone
        would leave the others waiting in DDP's gradient all-reduce, so the skip is collective."""
        return all_ranks(bool(loss.requires_grad), self.device, self.world)

    def train(self) -> Dict:
        from tqdm import tqdm
        cfg = self.cfg
        net = self.ddp if self.ddp is not None else self.unrolled
        self.model.train()
        start_wall = time.time()
        wall0 = self.wall_s
        loader = iter(self.loader())
        self._log(f'{cfg.preset} on {self.device}, steps in '
                  f'{"float32" if self.amp_dtype is None else str(self.amp_dtype).replace("torch.", "") + " autocast"}')
        bar = tqdm(total=cfg.steps, initial=self.step, disable=not self.is_main or self.quiet, dynamic_ncols=True,
                   mininterval=1.0 if sys.stderr.isatty() else 30.0, desc=f'train {cfg.preset}')
        last_log = []
        try:
            if self.is_main and self.step == 0 and not self.history['val']:
                self.validate()
            while self.step < cfg.steps:
                if cfg.max_minutes and (time.time() - start_wall) > cfg.max_minutes * 60:
                    self._log(f'--max-minutes {cfg.max_minutes} reached')
                    break
                t0 = time.time()
                batch = batch_to_device(next(loader), self.device)
                t1 = time.time()
                lr = _lr_at(cfg, self.step)
                for g in self.optimizer.param_groups:
                    g['lr'] = lr
                with torch.autocast(device_type=self.device.type, dtype=self.amp_dtype or torch.float32,
                                    enabled=self.amp_dtype is not None):
                    loss, stats = net(batch)
                self.optimizer.zero_grad(set_to_none=True)
                if self._all_ranks_have_grad(loss):
                    self.scaler.scale(loss).backward()
                    self.scaler.unscale_(self.optimizer)
                    gnorm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.clip)
                    if torch.isfinite(gnorm):
                        self.scaler.step(self.optimizer)
                    else:
                        self._log(f'step {self.step}: non-finite gradient, update skipped')
                    self.scaler.update()
                else:   # only frozen sub-networks shaped this loss (here or on another rank), e.g.
                    # --train-modules knet with every unrolled step a filter reset
                    gnorm = torch.zeros(())
                    self._log(f'step {self.step}: the loss reaches no trained sub-network '
                              f'({stats.get("resets", 0)} filter resets), update skipped')
                self.step += 1
                self.samples_seen += cfg.batch_size
                t2 = time.time()
                self.wall_s = wall0 + (t2 - start_wall)
                stats.update(step=self.step, lr=lr, grad_norm=float(gnorm), t_data=t1 - t0, t_step=t2 - t1)
                last_log.append(stats)
                bar.update(1)
                bar.set_postfix(loss=f"{stats['loss']:.3f}", nll=f"{stats['nll_full']:.3f}")
                if self.step % cfg.log_every == 0 or self.step == cfg.steps:
                    row = {k: float(np.mean([s[k] for s in last_log])) for k in last_log[0] if k != 'step'}
                    row['step'] = self.step
                    row['wall_s'] = self.wall_s
                    self.history['train'].append(row)
                    self._append_jsonl('train.jsonl', row)
                    self._log(f"step {self.step} loss {row['loss']:.4f} nll_full {row['nll_full']:.4f} "
                              f"nll_q {row['nll_meas_q']:.4f} |g| {row['grad_norm']:.2f} lr {lr:.2e} "
                              f"{row['t_step']:.2f}+{row['t_data']:.2f} s/step")
                    last_log = []
                    if self.is_main and not self._validates_now():     # else the validation draws them
                        self._plot_curves()
                if self._validates_now():
                    if self.is_main:
                        self.validate()
                    if self.world > 1:
                        torch.distributed.barrier()
                if self.step % cfg.ckpt_every == 0:
                    self.save()
        except KeyboardInterrupt:
            self._log('interrupted; writing a checkpoint')
        finally:
            bar.close()
            self.save()
            if self.is_main:
                self._plot_curves()
        return {'step': self.step, 'best': self.best, 'history': self.history}


def train(cfg: TrainConfig, resume: bool = False, quiet: bool = False, argv: Optional[List[str]] = None) -> Dict:
    """Build a :class:`Trainer` and run it; returns {'step', 'best', 'history'}."""
    t = Trainer(cfg, resume=resume, quiet=quiet, argv=argv)
    try:
        return t.train()
    finally:
        if t.world > 1 and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
