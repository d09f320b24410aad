"""Seconds per training step of a preset, per precision: what ``train --amp`` buys on this machine.

    python -m dpv_sensor.benchmarks.train_step                         # lite, 256x192, batch 2, unroll 4, 1 thread
    python -m dpv_sensor.benchmarks.train_step --amps off bf16 --rounds 2 --steps 3

One step is what ``tools.train`` does per optimiser step: the unrolled filter loss of one batch (D-Net on every
keyframe, K-Net at every filter step, R-Net and the loss) and its backward pass. The batches are rendered once
(seeds from the training range, so nothing held out is touched) and reused, so every precision sees the same
data; each round times ``steps`` steps after one warm-up step, and the rounds alternate the precisions, so a
machine whose load changes affects them alike. Printed per round: the mean seconds per step and the losses
(equal losses across precisions show the autocast does not change what is learned, to that many digits).
No optimiser update is applied, so every round starts from the same weights.
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from typing import Dict, List, Optional, Sequence

import torch

__all__ = ['run']


def run(preset: str = 'lite', width: int = 256, height: int = 192, batch_size: int = 2, unroll: int = 4,
        amps: Sequence[str] = ('off', 'bf16'), rounds: int = 2, steps: int = 3, threads: int = 1,
        init_weights: Optional[str] = None, seed_base: int = 9_900_000) -> List[Dict]:
    """Rows ``{amp, dtype, round, s_per_step, losses}`` in the order they were measured."""
    from dpv_sensor.training.config import TrainConfig
    from dpv_sensor.training.loop import Trainer, resolve_amp
    from dpv_sensor.training.unrolled import batch_to_device
    torch.set_num_threads(threads)
    cfg = TrainConfig(preset=preset, run_dir=tempfile.mkdtemp(prefix='train_step_'), width=width, height=height,
                      batch_size=batch_size, unroll=unroll, num_workers=0, threads=threads,
                      init_weights=init_weights, seed_base=seed_base)
    trainer = Trainer(cfg, quiet=True)
    it = iter(trainer.loader())
    batches = [batch_to_device(next(it), trainer.device) for _ in range(steps + 1)]

    def one(batch, dtype) -> float:
        with torch.autocast(trainer.device.type, dtype=dtype or torch.float32, enabled=dtype is not None):
            loss, _ = trainer.unrolled(batch)
        trainer.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        return float(loss.detach())

    rows = []
    for r in range(rounds):
        for amp in amps:
            dtype = resolve_amp(amp, trainer.device)
            one(batches[0], dtype)
            t0 = time.perf_counter()
            losses = [one(b, dtype) for b in batches[1:]]
            rows.append({'amp': amp, 'dtype': str(dtype or torch.float32).replace('torch.', ''), 'round': r,
                         's_per_step': (time.perf_counter() - t0) / steps, 'losses': losses})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--preset', default='lite')
    ap.add_argument('--width', type=int, default=256)
    ap.add_argument('--height', type=int, default=192)
    ap.add_argument('--batch-size', type=int, default=2)
    ap.add_argument('--unroll', type=int, default=4)
    ap.add_argument('--amps', nargs='+', default=['off', 'bf16'], choices=['auto', 'off', 'bf16', 'fp16'])
    ap.add_argument('--rounds', type=int, default=2)
    ap.add_argument('--steps', type=int, default=3, help='timed steps per round (after one warm-up step)')
    ap.add_argument('--threads', type=int, default=1)
    ap.add_argument('--init-weights', default=None, help='start from these weights (default: random init)')
    ap.add_argument('--json', default=None, help='also write the rows to this file')
    a = ap.parse_args(argv)
    rows = run(a.preset, a.width, a.height, a.batch_size, a.unroll, a.amps, a.rounds, a.steps, a.threads,
               a.init_weights)
    print(f'{a.preset} {a.width}x{a.height} batch {a.batch_size} unroll {a.unroll}, {a.threads} thread(s)')
    for row in rows:
        print(f"  round {row['round']} {row['dtype']:9s} {row['s_per_step']:6.2f} s/step   losses "
              + ' '.join(f'{x:.4f}' for x in row['losses']))
    if a.json:
        with open(a.json, 'w') as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
