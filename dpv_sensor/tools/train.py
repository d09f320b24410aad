"""``ros2 run dpv_sensor train``: end-to-end NLL training of D-Net, K-Net and R-Net (paper sec. 3.3).

Examples::

    # the lite preset on a 2-core CPU, in the background, resumable
    nohup python -m dpv_sensor.tools.train --preset lite --run-dir runs/lite \\
        --threads 2 --num-workers 1 --resume > runs/lite/stdout.log 2>&1 &
    # continue after a stop (same command; --resume picks checkpoints/latest.json)
    # stop cleanly (writes a checkpoint first): kill -TERM <pid>

    # several GPUs: one process per GPU, each streams its own scene seeds; rank 0 writes
    torchrun --nproc_per_node 4 -m dpv_sensor.tools.train --preset paper --batch-size 4 --run-dir runs/paper

Outputs in --run-dir: train.jsonl / val.jsonl (metrics), loss_curves.png, val_montage_*.png,
checkpoints/step_*/ (model + optimizer as safetensors, state.json) and latest.json. The best weights
(by --select-metric on the held-out validation seeds) are exported atomically to --export
(default dpv_sensor/weights/<preset>.safetensors). See dpv_sensor/training/ for the details.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import signal
import sys
from typing import List, Optional

from dpv_sensor.training.dataset import TRAIN_SEED_BASE, parse_seeds
from dpv_sensor.training.checkpoints import latest_checkpoint
from dpv_sensor.training.config import MODULES, TrainConfig
from dpv_sensor.cli import tool_argv


def build_parser() -> argparse.ArgumentParser:
    d = TrainConfig()
    p = argparse.ArgumentParser(prog='train', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument('--preset', default=d.preset, help='network preset (lite | paper)')
    p.add_argument('--run-dir', default=d.run_dir, help='logs, plots and checkpoints go here')
    p.add_argument('--export', default=None, help='exported weights (default dpv_sensor/weights/<preset>.safetensors)')
    p.add_argument('--resume', action='store_true', help='continue from <run-dir>/checkpoints/latest.json if present')
    p.add_argument('--init-weights', default=None, help='start from these exported weights (new optimiser)')
    p.add_argument('--width', type=int, default=d.width, help='training image width (multiple of 4)')
    p.add_argument('--height', type=int, default=d.height, help='training image height (multiple of 4)')
    p.add_argument('--extra-sizes', nargs='*', default=[], metavar='WxH',
                   help='multi-scale training: further sizes, one drawn per batch (e.g. 160x128)')
    p.add_argument('--steps', type=int, default=d.steps, help='total optimiser steps (cosine schedule length)')
    p.add_argument('--batch-size', type=int, default=d.batch_size, help='samples per step and rank')
    p.add_argument('--unroll', type=int, default=d.unroll, help='filter steps (keyframes) unrolled per sample')
    p.add_argument('--ref-position', choices=('center', 'last'), default=d.ref_position,
                   help="reference keyframe in its 5-frame window ('last' = causal, the node's default); "
                        "used for validation, and for training with --no-ref-mix")
    p.add_argument('--no-ref-mix', action='store_true',
                   help='train only on --ref-position windows (default: centered and causal mixed per batch)')
    p.add_argument('--gap-min', type=int, default=d.gap_min, help='min frames between keyframes')
    p.add_argument('--gap-max', type=int, default=d.gap_max, help='max frames between keyframes')
    p.add_argument('--lr', type=float, default=d.lr)
    p.add_argument('--min-lr-ratio', type=float, default=d.min_lr_ratio, help='final lr / lr of the cosine')
    p.add_argument('--warmup', type=int, default=d.warmup, help='linear warm-up steps')
    p.add_argument('--weight-decay', type=float, default=d.weight_decay)
    p.add_argument('--clip', type=float, default=d.clip, help='gradient-norm clipping')
    p.add_argument('--aux-weight', type=float, default=d.aux_weight,
                   help='weight of the auxiliary NLL of the quarter-res D-Net measurement (0 = paper loss)')
    p.add_argument('--train-modules', nargs='+', choices=MODULES, default=list(d.train_modules), metavar='MODULE',
                   help=f'update only these sub-networks ({", ".join(MODULES)}; default: all). Without features '
                        'and cost_volume, D-Net runs without autograd and the auxiliary term is dropped, e.g. '
                        '`--train-modules knet` fine-tunes the damping alone over long unrolls')
    p.add_argument('--seed', type=int, default=d.seed, help='torch seed (weight init)')
    p.add_argument('--seed-base', type=int, default=d.seed_base,
                   help=f'first training scene seed (>= {TRAIN_SEED_BASE}; 0..99 are held out)')
    p.add_argument('--num-workers', type=int, default=d.num_workers, help='DataLoader worker processes (rendering)')
    p.add_argument('--threads', type=int, default=d.threads, help='torch CPU threads')
    p.add_argument('--device', default=d.device, help="'auto', 'cpu', 'cuda', 'cuda:1', ...")
    p.add_argument('--amp', choices=('auto', 'off', 'bf16', 'fp16'), default=d.amp,
                   help='mixed precision: on CUDA auto = bf16 (fp16 where bf16 is missing); on the CPU auto = bf16 '
                        'where the CPU has AMX / AVX512-BF16 (a lite step 1.75x faster), else float32')
    p.add_argument('--ckpt-every', type=int, default=d.ckpt_every, help='steps between checkpoints')
    p.add_argument('--log-every', type=int, default=d.log_every)
    p.add_argument('--val-every', type=int, default=d.val_every, help='steps between validations ("epoch")')
    p.add_argument('--val-seeds', default='0-5', help="held-out validation seeds, e.g. '0-5' (must lie in 0..99)")
    p.add_argument('--val-keyframes', type=int, default=d.val_keyframes, help='keyframes per validation sequence')
    p.add_argument('--val-gap', type=int, default=d.val_gap, help='frames between validation keyframes')
    p.add_argument('--val-width', type=int, default=0, help='validation width (0 = training width)')
    p.add_argument('--val-height', type=int, default=0, help='validation height (0 = training height)')
    p.add_argument('--folders', nargs='*', default=[],
                   help='sequence folders to mix in (e.g. tartanair_hospital; never SUN3D, tum_fr1_rpy or '
                        'icl_nuim_lr_kt3)')
    p.add_argument('--folder-prob', type=float, default=0.0, help='probability that a sample comes from --folders')
    p.add_argument('--startup-prob', type=float, default=0.0,
                   help='share of stream-start runs (causal windows with 1, 2, 3, 4 sources, as after a reset)')
    p.add_argument('--pose-noise-prob', type=float, default=d.pose_noise_prob,
                   help='share of samples whose poses get odometry-like errors (depths stay exact)')
    p.add_argument('--pose-noise-rot-deg', type=float, default=d.pose_noise_rot_deg,
                   help='largest rotation error per keyframe step of those samples (deg)')
    p.add_argument('--pose-noise-trans-rel', type=float, default=d.pose_noise_trans_rel,
                   help='largest translation error per step of those samples (fraction of the step)')
    p.add_argument('--world-scale-prob', type=float, default=d.world_scale_prob,
                   help='share of samples whose whole world is scaled: depths and translations times one factor, '
                        'images unchanged, so the networks read depth from the cost volume, not from room sizes')
    p.add_argument('--world-scale', type=float, nargs=2, default=list(d.world_scale), metavar=('MIN', 'MAX'),
                   help='range of that factor (drawn log-uniformly)')
    p.add_argument('--no-augment', action='store_true', help='disable photometric augmentation')
    p.add_argument('--select-metric', default=d.select_metric,
                   help='validation score deciding exports, lower is better: <metric>_<mode> (GT poses), '
                        '<metric>_<mode>_noisy (the --val-pose-noise validation) or <metric>_<mode>_both (their mean); '
                        'prefixed stream_, the same from the streaming validation (--val-stream-seeds)')
    p.add_argument('--val-pose-noise', type=float, nargs=2, default=list(d.val_pose_noise),
                   metavar=('REL_T', 'ROT_DEG'),
                   help='also validate with odometry-like poses: relative translation error and rotation error (deg) '
                        'per keyframe step, accumulating (0 0 = off); reported as noisy_net_<mode>')
    p.add_argument('--val-stream-seeds', default='',
                   help="also stream these held-out seeds (e.g. '20-25') frame by frame through the estimator at "
                        "every validation, as the node runs the weights; reported as stream_net_<mode> and "
                        "stream_noisy_net_<mode>, selectable as stream_<metric>_<mode>[_noisy|_both] "
                        "(5-8 s per 60-frame sequence and pose source with lite on one core)")
    p.add_argument('--val-stream-frames', type=int, default=d.val_stream_frames, help='frames per streamed sequence')
    p.add_argument('--val-stream-pose-noise', type=float, nargs=2, default=list(d.val_stream_pose_noise),
                   metavar=('REL_T', 'ROT_DEG'),
                   help="odometry-like pose errors per frame of the streaming validation's noisy pass (0 0 = off)")
    p.add_argument('--max-minutes', type=float, default=0.0, help='stop with a checkpoint after this wall time')
    p.add_argument('--quiet', action='store_true', help='no progress bar or log lines')
    p.add_argument('--export-step', type=int, default=None, metavar='STEP',
                   help='train nothing: export checkpoint STEP of --run-dir to --export (required) and exit')
    return p


def config_from_args(a: argparse.Namespace) -> TrainConfig:
    return TrainConfig(
        preset=a.preset, run_dir=a.run_dir, export_path=a.export, width=a.width, height=a.height,
        extra_sizes=tuple(tuple(int(v) for v in s.lower().split('x')) for s in a.extra_sizes), steps=a.steps,
        batch_size=a.batch_size, unroll=a.unroll, ref_position=a.ref_position, ref_mix=not a.no_ref_mix,
        gap_min=a.gap_min,
        gap_max=a.gap_max, lr=a.lr, min_lr_ratio=a.min_lr_ratio, warmup=a.warmup, weight_decay=a.weight_decay,
        clip=a.clip, aux_weight=a.aux_weight, seed=a.seed, seed_base=a.seed_base, num_workers=a.num_workers,
        threads=a.threads, device=a.device, amp=a.amp, ckpt_every=a.ckpt_every, log_every=a.log_every,
        val_every=a.val_every, val_seeds=parse_seeds(a.val_seeds), val_keyframes=a.val_keyframes,
        val_gap=a.val_gap, val_width=a.val_width, val_height=a.val_height, folders=tuple(a.folders),
        folder_prob=a.folder_prob, augment=not a.no_augment, select_metric=a.select_metric,
        val_pose_noise=tuple(a.val_pose_noise), val_stream_seeds=parse_seeds(a.val_stream_seeds),
        val_stream_frames=a.val_stream_frames, val_stream_pose_noise=tuple(a.val_stream_pose_noise),
        init_weights=a.init_weights, max_minutes=a.max_minutes, startup_prob=a.startup_prob,
        pose_noise_prob=a.pose_noise_prob, pose_noise_rot_deg=a.pose_noise_rot_deg,
        pose_noise_trans_rel=a.pose_noise_trans_rel, world_scale_prob=a.world_scale_prob,
        world_scale=tuple(a.world_scale), train_modules=tuple(a.train_modules)).check()


def _export_step(a: argparse.Namespace) -> int:
    from dpv_sensor.training.checkpoints import export_checkpoint
    ckpt = pathlib.Path(a.run_dir) / 'checkpoints' / f'step_{a.export_step:07d}'
    if not a.export or not (ckpt / 'state.json').is_file():
        print(f'train: --export-step needs --export and the checkpoint {ckpt}'
              + ('' if (ckpt / 'state.json').is_file() else ' (not found)'), file=sys.stderr)
        return 2
    export_checkpoint(ckpt, a.export)
    print(json.dumps({'exported': a.export, 'from': str(ckpt)}))
    return 0


def _sigterm(signum, frame):
    raise KeyboardInterrupt(f'signal {signum}')


def main(argv: Optional[List[str]] = None) -> int:
    argv = tool_argv(argv)   # training has no ROS parameters
    a = build_parser().parse_args(argv)
    try:
        cfg = config_from_args(a)
    except ValueError as e:
        print(f'train: {e}', file=sys.stderr)
        return 2
    if a.export_step is not None:
        return _export_step(a)
    if a.resume and latest_checkpoint(cfg.run_dir) is not None:
        # the stored run's configuration wins for everything that shapes the data stream, except
        # what the user is expected to change on resume (length, cadence, threads, device)
        stored = json.loads((latest_checkpoint(cfg.run_dir) / 'state.json').read_text()).get('config', {})
        keep_new = {'steps', 'run_dir', 'export_path', 'num_workers', 'threads', 'device', 'ckpt_every',
                    'log_every', 'val_every', 'max_minutes', 'amp', 'init_weights', 'keep_checkpoints'}
        merged = {**stored, **{k: v for k, v in cfg.to_json().items() if k in keep_new}}
        cfg = TrainConfig.from_json(merged).check()
    signal.signal(signal.SIGTERM, _sigterm)
    from dpv_sensor.training.loop import train
    out = train(cfg, resume=a.resume, quiet=a.quiet, argv=['python -m dpv_sensor.tools.train'] + argv)
    print(json.dumps({'step': out['step'], 'best': out['best']}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
