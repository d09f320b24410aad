"""Training pipeline: data stream, unrolled loss, checkpoints, resume, export.

Everything runs at tiny sizes (<= 64x48, a few steps) so the file stays well under a minute on a
shared 2-core CPU; nothing here depends on long training.
"""
from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import shutil
import time

import numpy as np
import pytest
import torch

from dpv_sensor.training.dataset import (TRAIN_SEED_BASE, VAL_SEEDS, SceneStream, StreamConfig, WindowLayout,
                                         check_not_heldout)
from dpv_sensor.training import checkpoints, config, loop, unrolled, validation

from conftest import cpu_native_bf16
from keyframe_spy import KeyframeSpy, frame_mean_abs_rel


def _small_stream(steps=2, w=64, h=48, **kw):
    return StreamConfig(width=w, height=h, layout=WindowLayout(steps=steps), gap_min=2, gap_max=3, **kw)


def test_window_layout_centered_and_causal():
    ref, src = WindowLayout(steps=3, ref_position='center').indices()
    assert ref.tolist() == [2, 3, 4]
    assert src.tolist() == [[0, 1, 3, 4], [1, 2, 4, 5], [2, 3, 5, 6]]
    ref, src = WindowLayout(steps=2, ref_position='last').indices()
    assert ref.tolist() == [4, 5]
    assert src[1].tolist() == [1, 2, 3, 4]


def test_seed_sharding_is_disjoint_and_never_validation():
    cfg = _small_stream()
    seen = set()
    for rank in range(3):
        ds = SceneStream(cfg, rank=rank, world_size=3)
        seeds = {ds.seed_of(i) for i in range(50)}
        assert not (seeds & seen)
        seen |= seeds
    assert min(seen) >= TRAIN_SEED_BASE
    assert not (seen & set(VAL_SEEDS))
    with pytest.raises(ValueError):
        StreamConfig(seed_base=5)
    with pytest.raises(ValueError):
        check_not_heldout('/x/shared/data/sun3d_3dmatch_frag1/')
    for name in ('tum_fr1_rpy', 'icl_nuim_lr_kt3', 'ICL_NUIM_LR_KT3_copy'):
        with pytest.raises(ValueError, match='held-out'):
            check_not_heldout(f'/x/data/{name}')
    check_not_heldout('/x/data/tartanair_hospital')
    with pytest.raises(ValueError):
        config.TrainConfig(val_seeds=(150,)).check()


def test_sample_layout_geometry_and_determinism():
    ds = SceneStream(_small_stream(steps=2), start_index=7)
    a = ds.make_sample(7)
    b = next(iter(ds))
    M = 6
    assert a['images'].shape == (M, 3, 48, 64) and a['depths'].shape == (M, 48, 64)
    assert torch.equal(a['images'], b['images'])                 # sample i is a function of i only
    assert int(a['seed']) == TRAIN_SEED_BASE + 7
    assert torch.allclose(a['poses'][0], torch.eye(4), atol=1e-5)   # poses relative to the first keyframe
    assert float(a['images'].min()) >= 0 and float(a['images'].max()) <= 1
    assert (a['depths'] > 0).float().mean() > 0.5
    c = ds.make_sample(8)
    assert not torch.equal(a['images'], c['images'])              # a fresh scene per sample
    assert a['src_count'].tolist() == [4, 4]                      # full windows by default


def test_run_played_backwards_keeps_time_moving_forward():
    """Folder runs are sometimes played backwards (another plausible trajectory). Their stamps must still
    increase, or the filter resets on "time went backwards" at every step and K-Net learns nothing there."""
    from dpv_sensor.data.synthetic import render_sequence
    from dpv_sensor.core.nets.model import DPVNet
    from dpv_sensor.training.dataset import sample_from_sequence
    layout = WindowLayout(steps=3, window=5, ref_position='last')
    seq = render_sequence(TRAIN_SEED_BASE + 3, 30, width=64, height=48, lazy=True)
    ids = list(range(0, 3 * layout.num_keyframes, 3))[::-1]
    smp = sample_from_sequence(seq, ids, layout, np.random.default_rng(0))
    st = smp['stamps'].numpy()
    assert st[0] == 0 and np.all(np.diff(st) > 0)
    assert np.allclose(np.diff(st), 3 / 30, atol=1e-4)           # the spacing of the frames, mirrored
    model = DPVNet('lite')
    with torch.no_grad():
        _, stats = unrolled.run_unrolled(model, {k: v[None] for k, v in smp.items()}, model.depth_planes())
    assert stats['resets'] == 0


def test_stream_start_runs_use_growing_source_counts():
    causal = SceneStream(_small_stream(steps=3, ref_positions=('last',), startup_prob=1.0))
    smp = causal.make_sample(0)
    assert smp['ref_idx'].tolist() == [4, 5, 6]
    assert smp['src_count'].tolist() == [1, 2, 3]                 # like the estimator after a (re)start
    centred = SceneStream(_small_stream(steps=3, ref_positions=('center',), startup_prob=1.0))
    assert centred.make_sample(0)['src_count'].tolist() == [4, 4, 4]


def test_pose_noise_corrupts_relative_motion_but_not_images_or_depth():
    from dpv_sensor.stream.window_refiner import relative_pose_errors
    clean = SceneStream(_small_stream(steps=2)).make_sample(3)
    noisy = SceneStream(_small_stream(steps=2, pose_noise_prob=1.0, pose_noise_rot_deg=1.0,
                                      pose_noise_trans_rel=0.1)).make_sample(3)
    assert torch.equal(clean['images'], noisy['images']) and torch.equal(clean['depths'], noisy['depths'])
    assert torch.allclose(noisy['poses'][0], torch.eye(4), atol=1e-6)     # still relative to the first keyframe
    t_err, r_err = relative_pose_errors([T.double().numpy() for T in noisy['poses']],
                                        [T.double().numpy() for T in clean['poses']])
    assert np.all(r_err <= 1.0 + 1e-3) and r_err.max() > 0.0 and t_err.max() > 0.0
    steps = np.linalg.norm(np.diff(clean['poses'][:, :3, 3].double().numpy(), axis=0), axis=1)
    assert np.all(t_err <= 0.1 * steps + 1e-5)
    assert torch.equal(SceneStream(_small_stream(steps=2, pose_noise_prob=1.0)).make_sample(3)['poses'],
                       SceneStream(_small_stream(steps=2, pose_noise_prob=1.0)).make_sample(3)['poses'])
    with pytest.raises(ValueError, match='pose noise'):
        _small_stream(pose_noise_prob=1.5)


def test_world_scale_scales_depths_and_translations_together_and_nothing_else():
    clean = SceneStream(_small_stream(steps=2)).make_sample(3)
    stream = SceneStream(_small_stream(steps=2, world_scale_prob=1.0, world_scale=(0.5, 2.0)))
    scaled = stream.make_sample(3)
    assert torch.equal(clean['images'], scaled['images'])                 # a larger world looks the same
    valid = clean['depths'] > 0
    s = float((scaled['depths'][valid] / clean['depths'][valid]).median())
    assert 0.5 <= s <= 2.0 and abs(s - 1.0) > 1e-3
    assert torch.allclose(scaled['depths'], clean['depths'] * s, rtol=1e-6)
    assert torch.allclose(scaled['poses'][:, :3, :3], clean['poses'][:, :3, :3])      # rotations untouched
    assert torch.allclose(scaled['poses'][:, :3, 3], clean['poses'][:, :3, 3] * s, rtol=1e-5, atol=1e-7)
    assert torch.equal(stream.make_sample(3)['depths'], scaled['depths'])              # the same factor again
    factors = {round(float((stream.make_sample(i)['depths'].max() / SceneStream(_small_stream(steps=2))
                            .make_sample(i)['depths'].max())), 4) for i in range(3)}
    assert len(factors) == 3                                                           # one factor per sample
    never = SceneStream(_small_stream(steps=2, world_scale_prob=0.0, world_scale=(0.5, 2.0))).make_sample(3)
    assert torch.equal(never['depths'], clean['depths']) and torch.equal(never['poses'], clean['poses'])
    with pytest.raises(ValueError, match='world scale'):
        _small_stream(world_scale=(2.0, 0.5))


def test_unrolled_loss_falls_and_reaches_every_net():
    from dpv_sensor.core.nets.model import DPVNet
    torch.manual_seed(0)
    torch.set_num_threads(max(1, min(2, torch.get_num_threads())))
    model = DPVNet('lite')
    depths = model.depth_planes()
    # a stream-start run: step 0 has a single source view, step 1 two
    smp = SceneStream(_small_stream(steps=2, ref_positions=('last',), startup_prob=1.0)).make_sample(0)
    assert smp['src_count'].tolist() == [1, 2]
    batch = {k: v[None] for k, v in smp.items()}
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    losses = []
    for it in range(10):
        loss, stats = unrolled.run_unrolled(model, batch, depths, aux_weight=0.5)
        assert math.isfinite(stats['loss']) and stats['resets'] == 0
        opt.zero_grad()
        loss.backward()
        if it == 0:
            for name, sub in (('features', model.features), ('knet', model.knet), ('rnet', model.rnet)):
                g = sum(float(p.grad.abs().sum()) for p in sub.parameters() if p.grad is not None)
                assert g > 0, f'no gradient reaches {name}'
        opt.step()
        losses.append(stats['loss'])
    assert np.mean(losses[-3:]) < losses[0] - 0.05, losses


def test_optimizer_state_roundtrip_without_pickle():
    m = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Linear(4, 1))
    opt = torch.optim.AdamW(m.parameters(), lr=1e-2)
    for _ in range(3):
        opt.zero_grad()
        m(torch.randn(5, 3)).sum().backward()
        opt.step()
    tensors, meta = checkpoints._optimizer_to_flat(opt)
    meta = json.loads(json.dumps(meta))
    opt2 = torch.optim.AdamW(m.parameters(), lr=5.0)
    opt2.load_state_dict(checkpoints._optimizer_from_flat(tensors, meta))
    s1, s2 = opt.state_dict(), opt2.state_dict()
    assert s2['param_groups'][0]['lr'] == pytest.approx(1e-2)
    for pid in s1['state']:
        for k in ('exp_avg', 'exp_avg_sq', 'step'):
            assert torch.equal(torch.as_tensor(s1['state'][pid][k]), torch.as_tensor(s2['state'][pid][k]))


def _tiny_config(tmp_path, steps):
    return config.TrainConfig(preset='lite', run_dir=str(tmp_path / 'run'),
                            export_path=str(tmp_path / 'w' / 'lite.safetensors'),
                            width=48, height=32, steps=steps, batch_size=1, unroll=2, gap_min=2, gap_max=3,
                            warmup=1, num_workers=0, threads=1, ckpt_every=2, log_every=1, val_every=3,
                            val_seeds=(0,), val_keyframes=5, val_gap=2)


def test_trainer_checkpoint_resume_and_export(tmp_path):
    from dpv_sensor.core.nets.checkpoint import load_checkpoint
    from safetensors.torch import load_file
    out = loop.train(_tiny_config(tmp_path, steps=3), quiet=True)
    assert out['step'] == 3
    run = tmp_path / 'run'
    ck = checkpoints.latest_checkpoint(str(run))
    assert ck is not None and ck.name == 'step_0000003'
    state = json.loads((ck / 'state.json').read_text())
    assert state['step'] == 3 and state['samples_seen'] == 3
    assert [v['step'] for v in state['history']['val']] == [0, 3]
    for f in ('loss_curves.png', 'val_montage_0000003.png', 'train.jsonl', 'val.jsonl'):
        assert (run / f).is_file(), f
    # the export loads through the project's checkpoint reader and carries the metadata
    assert (tmp_path / 'w' / 'lite.safetensors').stat().st_mode & 0o044 == 0o044   # world-readable package file
    model, meta = load_checkpoint(str(tmp_path / 'w' / 'lite.safetensors'))
    assert meta['preset'] == 'lite' and meta['D'] == model.preset.num_planes
    # the export is the best validation (lowest score) of the two, at step 0 or 3, and carries its metrics
    best = min(state['history']['val'], key=lambda v: v['score'])
    assert meta['steps'] == best['step'] and state['best'] == pytest.approx(best['score'])
    assert meta['validation_metrics']['net_knet']['abs_rel'] == pytest.approx(best['metrics']['net_knet']['abs_rel'])
    assert meta['training_data']['train_seed_range'][0] >= TRAIN_SEED_BASE
    saved = load_file(str(ck / 'model.safetensors'))
    # any checkpoint exports as loadable weights, whatever its validation said (train --export-step)
    from dpv_sensor.tools import train as train_tool
    step3 = str(tmp_path / 'step3.safetensors')
    assert train_tool.main(['--run-dir', str(run), '--export-step', '3', '--export', step3]) == 0
    model3, meta3 = load_checkpoint(step3)
    assert meta3['exported_from'] == 'run/step_0000003' and meta3['steps_this_run'] == meta3['steps'] == 3
    assert all(torch.equal(v, saved[k]) for k, v in model3.state_dict().items())
    assert train_tool.main(['--run-dir', str(run), '--export-step', '4', '--export', step3]) == 2
    # a run started from weights that can no longer be read: the export says so and counts this run's steps only
    from dpv_sensor.training.checkpoints import export_checkpoint
    ck3 = run / 'checkpoints' / 'step_0000003'
    state3 = json.loads((ck3 / 'state.json').read_text())
    moved = tmp_path / 'moved'
    shutil.copytree(ck3, moved / 'checkpoints' / 'step_0000003')
    state3.setdefault('config', {})['init_weights'] = str(tmp_path / 'gone.safetensors')
    (moved / 'checkpoints' / 'step_0000003' / 'state.json').write_text(json.dumps(state3))
    with pytest.warns(UserWarning, match='gone.safetensors cannot be read'):
        meta_gone = export_checkpoint(moved / 'checkpoints' / 'step_0000003', str(tmp_path / 'gone_export.safetensors'))
    assert meta_gone['steps'] == meta_gone['steps_this_run'] == 3

    # resume: continues at step 3 with the saved weights and optimiser, runs to 5
    t = loop.Trainer(_tiny_config(tmp_path, steps=5), resume=True, quiet=True)
    assert t.step == 3 and t.samples_seen == 3
    for k, v in t.model.state_dict().items():
        assert torch.equal(v, saved[k]), k
    assert len(t.optimizer.state) > 0
    assert t.loader().dataset.start_index == 3          # the data stream continues, no scene repeats
    out = t.train()
    assert out['step'] == 5
    assert checkpoints.latest_checkpoint(str(run)).name == 'step_0000005'
    rows = [json.loads(line) for line in (run / 'train.jsonl').read_text().splitlines()]
    assert [r['step'] for r in rows] == [1, 2, 3, 4, 5]


def test_train_modules_knet_updates_only_knet(tmp_path):
    """--train-modules knet: D-Net runs without autograd, R-Net is frozen, only K-Net's weights move,
    and the loss is the R-Net NLL alone (the auxiliary D-Net term carries no gradient then)."""
    cfg = dataclasses.replace(_tiny_config(tmp_path, steps=2), train_modules=('knet',), val_every=100)
    t = loop.Trainer(cfg, quiet=True)
    before = {k: v.clone() for k, v in t.model.state_dict().items()}
    trainable = {n for n, p in t.model.named_parameters() if p.requires_grad}
    assert trainable and all(n.startswith('knet.') for n in trainable)
    assert sum(len(g['params']) for g in t.optimizer.param_groups) == len(trainable)
    t.train()
    after = t.model.state_dict()
    moved = {k for k in before if not torch.equal(before[k], after[k])}
    assert moved and all(k.startswith('knet.') for k in moved), moved
    rows = [json.loads(line) for line in (tmp_path / 'run' / 'train.jsonl').read_text().splitlines()]
    assert all(r['loss'] == pytest.approx(r['nll_full']) for r in rows)
    meta = t.metadata({})
    assert meta['trained_modules'] == ['knet'] and 'D-Net' not in meta['loss']
    with pytest.raises(ValueError, match='train_modules'):
        dataclasses.replace(cfg, train_modules=('dnet',)).check()
    assert config.TrainConfig.from_json(cfg.to_json()).train_modules == ('knet',)


def test_selection_metric_names():
    assert config.parse_select_metric('abs_rel_knet') == ('abs_rel', 'knet', 'clean', False)
    assert config.parse_select_metric('confident_half_ratio_global_noisy') == \
        ('confident_half_ratio', 'global', 'noisy', False)
    assert config.parse_select_metric('nll_full_knet_both') == ('nll_full', 'knet', 'both', False)
    assert config.parse_select_metric('stream_abs_rel_knet_both') == ('abs_rel', 'knet', 'both', True)
    assert config.parse_select_metric('stream_delta1_global') == ('delta1', 'global', 'clean', True)
    for bad in ('abs_rel', 'abs_rel_kalman', 'abs_rel_knet_noisier', '_knet', 'stream_knet', 'stream_'):
        with pytest.raises(ValueError):
            config.parse_select_metric(bad)
    with pytest.raises(ValueError, match='val_pose_noise'):
        config.parse_select_metric('abs_rel_knet_both', noisy_validation=False)
    with pytest.raises(ValueError, match='val_stream_seeds'):
        config.parse_select_metric('stream_abs_rel_knet', stream_validation=False)
    with pytest.raises(ValueError, match='val_stream_pose_noise'):
        config.parse_select_metric('stream_abs_rel_knet_noisy', stream_noisy_validation=False)
    # the window validation's noisy poses are not needed for a streaming score, and the other way round
    assert config.parse_select_metric('stream_abs_rel_knet_both', noisy_validation=False).stream
    m = {'net_knet': {'abs_rel': 0.1}, 'noisy_net_knet': {'abs_rel': 0.3},
         'stream_net_knet': {'abs_rel': 0.2}, 'stream_noisy_net_knet': {'abs_rel': 0.6}}
    assert config.select_score(m, 'abs_rel_knet') == 0.1
    assert config.select_score(m, 'abs_rel_knet_noisy') == 0.3
    assert config.select_score(m, 'abs_rel_knet_both') == pytest.approx(0.2)
    assert config.select_score(m, 'abs_rel_global') is None
    assert config.select_score(m, 'stream_abs_rel_knet') == 0.2
    assert config.select_score(m, 'stream_abs_rel_knet_both') == pytest.approx(0.4)
    assert config.select_score(m, 'stream_abs_rel_global_both') is None
    # a run asks for the validations its selection metric needs
    with pytest.raises(ValueError, match='val_stream_seeds'):
        config.TrainConfig(select_metric='stream_abs_rel_knet').check()
    with pytest.raises(ValueError, match='not held out'):
        config.TrainConfig(val_stream_seeds=(100,)).check()
    cfg = config.TrainConfig(val_stream_seeds=(20, 21), select_metric='stream_abs_rel_global_both').check()
    assert cfg.stream_spec().modes == ('knet', 'global') and cfg.stream_spec().noisy
    assert config.TrainConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg


def test_streaming_validation_scores_whole_sequences_through_the_estimator(tmp_path, monkeypatch):
    """--val-stream-seeds: every validation also streams rendered held-out sequences frame by frame through the
    Estimator (GT and noisy poses), reports stream_[noisy_]net_knet, selects on it, plots it and leaves the model
    in training mode."""
    from dpv_sensor.data.synthetic import render_sequence
    from dpv_sensor.tools import train as tool
    a = tool.build_parser().parse_args(['--val-stream-seeds', '20-21', '--val-stream-frames', '30',
                                        '--select-metric', 'stream_abs_rel_knet_both'])
    c = tool.config_from_args(a)
    assert c.val_stream_seeds == (20, 21) and c.val_stream_frames == 30 and c.val_stream_pose_noise == (0.03, 0.5)
    cfg = dataclasses.replace(_tiny_config(tmp_path, steps=1), val_stream_seeds=(20,), val_stream_frames=16,
                              select_metric='stream_abs_rel_knet_both')
    t = loop.Trainer(cfg, quiet=True)
    t.model.train()
    spy = KeyframeSpy(monkeypatch)
    metrics = t.validate()
    assert t.model.training
    clean, noisy = metrics['stream_net_knet'], metrics['stream_noisy_net_knet']
    assert 'net_knet' in metrics and 'stream_net_global' not in metrics
    for m in (clean, noisy):
        assert m['frames'] > 0 and len(m['per_seed']) == 1 and 0 < m['abs_rel'] < 10
    assert clean['abs_rel'] != noisy['abs_rel']
    # the numbers are the frame-mean abs_rel of the depth the estimator published, computed here from its outputs
    # and the rendered GT (the GT-pose pass first, then the noisy one), with the trainer's own model in it
    runs = spy.runs()
    assert len(runs) == 2 and all(pipe.estimator.model is t.model for pipe, _ in runs)
    seq = render_sequence(20, 16, width=320, height=240, lazy=True)
    for m, (pipe, outputs) in zip((clean, noisy), runs):
        assert m['frames'] == len(outputs) > 0
        assert m['abs_rel'] == pytest.approx(frame_mean_abs_rel(outputs, seq, pipe.estimator), rel=1e-6)
    row = json.loads((tmp_path / 'run' / 'val.jsonl').read_text().splitlines()[-1])
    assert row['score'] == pytest.approx((clean['abs_rel'] + noisy['abs_rel']) / 2)
    assert t.best == pytest.approx(row['score'])
    assert t.metadata(metrics)['training_data']['validation_stream']['seeds'] == [20]
    assert (tmp_path / 'run' / 'loss_curves.png').is_file()
    # a streaming validation that fails is logged and skipped: the run goes on, nothing is exported on it
    def broken(*a, **k):
        raise RuntimeError('estimator exploded')
    t.stream_validator = broken
    t.stream_validator.spec = t.cfg.stream_spec()
    best = t.best
    metrics = t.validate()
    assert 'net_knet' in metrics and 'stream_net_knet' not in metrics and t.best == best


def test_amp_resolution_per_device():
    cpu, cuda = torch.device('cpu'), torch.device('cuda')
    # the CPU autocasts to bfloat16 by default only where oneDNN has native kernels: judged here from the CPU's
    # own flags, not from the function that makes the choice
    native = cpu_native_bf16()
    if native is not None:
        assert loop.resolve_amp('auto', cpu) is (torch.bfloat16 if native else None)
    assert loop.resolve_amp('off', cpu) is None
    assert loop.resolve_amp('bf16', cpu) is torch.bfloat16
    with pytest.raises(ValueError, match='CUDA only'):
        loop.resolve_amp('fp16', cpu)
    assert loop.resolve_amp('fp16', cuda) is torch.float16
    assert loop.resolve_amp('bf16', cuda) is torch.bfloat16
    assert loop.resolve_amp('off', cuda) is None
    with pytest.raises(ValueError, match='amp must be'):
        loop.resolve_amp('fp8', cpu)


def test_cpu_bf16_training_step_matches_float32():
    """One unrolled step under CPU bfloat16 autocast (``--amp bf16``): the loss stays float32 and agrees with
    float32 to 1 %, and the gradient points the same way."""
    from dpv_sensor.core.nets.model import DPVNet
    torch.manual_seed(0)
    model = DPVNet('lite')
    depths = model.depth_planes()
    smp = SceneStream(_small_stream(steps=2, ref_positions=('last',), startup_prob=0.0)).make_sample(0)
    batch = {k: v[None] for k, v in smp.items()}
    grads, losses = {}, {}
    for name, enabled in (('fp32', False), ('bf16', True)):
        model.zero_grad(set_to_none=True)
        with torch.autocast('cpu', dtype=torch.bfloat16, enabled=enabled):
            loss, _ = unrolled.run_unrolled(model, batch, depths, aux_weight=0.5)
        assert loss.dtype == torch.float32
        loss.backward()
        losses[name] = float(loss.detach())
        grads[name] = torch.cat([p.grad.flatten() for p in model.parameters() if p.grad is not None])
    assert losses['bf16'] == pytest.approx(losses['fp32'], rel=0.01)
    assert float(torch.nn.functional.cosine_similarity(grads['fp32'], grads['bf16'], dim=0)) > 0.95


def test_noisy_pose_validation_corrupts_relative_poses_and_is_reported(tmp_path):
    """--val-pose-noise: the validation batches are scored a second time with odometry-like poses (images and
    depth unchanged, the same poses at every validation), as noisy_net_<mode>; a *_both metric selects on the mean."""
    from dpv_sensor.tools import train as tool
    a = tool.build_parser().parse_args(['--val-pose-noise', '0.05', '1.0', '--select-metric', 'abs_rel_knet_both'])
    assert tool.config_from_args(a).val_pose_noise == (0.05, 1.0)
    with pytest.raises(ValueError):
        tool.config_from_args(tool.build_parser().parse_args(['--select-metric', 'abs_rel_knet_noisy']))
    cfg = dataclasses.replace(_tiny_config(tmp_path, steps=1), val_pose_noise=(0.05, 1.0),
                              select_metric='abs_rel_knet_both')
    t = loop.Trainer(cfg, quiet=True)
    clean, noisy = t.val_batches(), t.noisy_val_batches()
    assert t.noisy_val_batches() is noisy
    again = validation.corrupt_validation_batches(clean, 0.05, 1.0)
    for b, n, n2 in zip(clean, noisy, again):
        assert torch.equal(b['images'], n['images']) and torch.equal(b['depths'], n['depths'])
        torch.testing.assert_close(n['poses'], n2['poses'])
        rel = lambda P, i: torch.linalg.inv(P[0, i]) @ P[0, i + 1]       # noqa: E731
        moved = max(float((rel(b['poses'], i) - rel(n['poses'], i)).abs().max())
                    for i in range(n['poses'].shape[1] - 1))
        assert moved > 1e-3
    metrics = t.validate()
    for mode in config.FILTER_MODES:
        assert f'noisy_net_{mode}' in metrics and f'net_{mode}' in metrics
    assert metrics['noisy_net_knet']['abs_rel'] != metrics['net_knet']['abs_rel']
    row = json.loads((tmp_path / 'run' / 'val.jsonl').read_text().splitlines()[-1])
    assert row['score'] == pytest.approx((metrics['net_knet']['abs_rel'] + metrics['noisy_net_knet']['abs_rel']) / 2)


def test_cli_parses_and_refuses_sun3d(tmp_path):
    from dpv_sensor.tools import train as tool
    a = tool.build_parser().parse_args(['--val-seeds', '0-2,7', '--steps', '9'])
    cfg = tool.config_from_args(a)
    assert cfg.val_seeds == (0, 1, 2, 7) and cfg.steps == 9
    assert tool.main(['--folders', str(tmp_path / 'sun3d_3dmatch_frag2'), '--folder-prob', '0.5',
                      '--run-dir', str(tmp_path / 'r')]) == 2
    for name in ('tum_fr1_rpy', 'icl_nuim_lr_kt3'):
        assert tool.main(['--folders', str(tmp_path / name), '--folder-prob', '0.5',
                          '--run-dir', str(tmp_path / f'r_{name}')]) == 2


def test_train_step_benchmark_times_every_precision_on_the_same_batches(capsys):
    from dpv_sensor.benchmarks import train_step
    assert train_step.main(['--width', '64', '--height', '48', '--batch-size', '1', '--unroll', '2',
                            '--steps', '1', '--rounds', '1', '--amps', 'off', 'bf16']) == 0
    out = capsys.readouterr().out
    assert 'float32' in out and 'bfloat16' in out
    rows = train_step.run(width=64, height=48, batch_size=1, unroll=2, steps=1, rounds=1, amps=('off', 'bf16'))
    assert [r['dtype'] for r in rows] == ['float32', 'bfloat16']
    assert all(r['s_per_step'] > 0 and len(r['losses']) == 1 for r in rows)
    assert rows[1]['losses'][0] == pytest.approx(rows[0]['losses'][0], rel=0.02)


def test_seed_lists_parse_and_refuse_garbage():
    from dpv_sensor.training.dataset import parse_seeds
    assert parse_seeds('0-2,7') == (0, 1, 2, 7) and parse_seeds('') == () and parse_seeds(' 5 ') == (5,)
    with pytest.raises(ValueError, match='seed list'):
        parse_seeds('a-b')


def test_selection_benchmark_scores_weight_files_like_the_streaming_validation(tmp_path, capsys, monkeypatch):
    """studies.selection: the figures equal the trainer's streaming validation of the same weights, are
    written as JSON and printed as a table; seeds outside the held-out range are refused."""
    from dpv_sensor.studies import selection
    from dpv_sensor.core.nets.checkpoint import save_checkpoint
    from dpv_sensor.core.nets.model import DPVNet
    from dpv_sensor.data.synthetic import render_sequence
    torch.manual_seed(3)
    model = DPVNet('lite').eval()
    w = tmp_path / 'w.safetensors'
    save_checkpoint(str(w), model, metadata={'steps': 7})
    out = tmp_path / 'sel.json'
    spy = KeyframeSpy(monkeypatch)
    assert selection.main(['--weights', str(w), '--seeds', '21', '--frames', '14', '--pose-noise', '0', '0',
                           '--threads', '1', '--out', str(out)]) == 0
    res = json.loads(out.read_text())['results'][str(w)]
    assert res['steps'] == 7 and 'stream_noisy_net_knet' not in res
    # the figure is the frame-mean abs_rel of what the estimator published with the saved weights, computed here
    ((pipe, outputs),) = spy.runs()
    loaded = pipe.estimator.model.state_dict()
    assert all(torch.equal(v, loaded[k]) for k, v in model.state_dict().items())
    seq = render_sequence(21, 14, width=320, height=240, lazy=True)
    assert res['stream_net_knet']['frames'] == len(outputs) > 0
    assert res['stream_net_knet']['abs_rel'] == pytest.approx(frame_mean_abs_rel(outputs, seq, pipe.estimator),
                                                              rel=1e-6)
    assert res['stream_net_knet']['per_seed'] == [round(res['stream_net_knet']['abs_rel'], 4)]
    assert f"| {w} | 7 | knet | {res['stream_net_knet']['abs_rel']:.4f} |" in capsys.readouterr().out
    assert selection.main(['--weights', str(w), '--seeds', '100']) == 2
    bad = tmp_path / 'bad.safetensors'
    bad.write_bytes(b'not a safetensors file')
    assert selection.main(['--weights', str(bad), '--seeds', '21', '--frames', '14']) == 2
    assert 'cannot load weights' in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert selection.main(['--weights', str(w), '--seeds', '21', '--frames', '14', '--device', 'cuda']) == 2
        assert 'CUDA is not available' in capsys.readouterr().err


def test_selection_paired_differences_by_hand():
    """Per-seed scores are the mean of the GT and noisy abs_rel; differences are paired by seed."""
    from dpv_sensor.studies import selection

    def res(gt, noisy=None):
        r = {'stream_net_knet': {'per_seed': gt}}
        if noisy is not None:
            r['stream_noisy_net_knet'] = {'per_seed': noisy}
        return r
    results = {'A': res([0.10, 0.20, 0.30], [0.30, 0.40, 0.50]),      # scores 0.20 0.30 0.40
               'B': res([0.10, 0.10, 0.30], [0.30, 0.30, 0.70]),      # scores 0.20 0.20 0.50: d = 0, -0.1, +0.1
               'C': res([0.15, 0.25, 0.35], [0.25, 0.35, 0.45])}      # scores 0.20 0.30 0.40: d = 0 everywhere
    rows = selection.paired_differences(results)
    assert [r['weights'] for r in rows] == ['B', 'C'] and rows[0]['base'] == 'A'
    assert rows[0]['mean_diff'] == pytest.approx(0.0, abs=1e-12) and rows[0]['std_err'] == pytest.approx(0.1 / 3 ** 0.5)
    assert rows[0]['seeds_better'] == 1 and rows[0]['seeds'] == 3
    assert rows[1]['mean_diff'] == pytest.approx(0.0, abs=1e-12) and rows[1]['std_err'] == pytest.approx(0.0, abs=1e-12)
    assert '| B | +0.0000 | 0.0577 | 1 of 3 |' in selection.difference_table(rows, 'knet')
    # GT poses only: the GT column alone; a single file: nothing to compare
    only_gt = selection.paired_differences({'A': res([0.1, 0.2]), 'B': res([0.2, 0.2])})
    assert only_gt[0]['mean_diff'] == pytest.approx(0.05) and only_gt[0]['seeds_better'] == 0
    assert selection.paired_differences({'A': res([0.1])}) == [] and selection.difference_table([], 'knet') == ''


def _all_ranks_worker(rank, world, port, flags, out_dir):
    import os
    os.environ.update(MASTER_ADDR='127.0.0.1', MASTER_PORT=str(port))
    torch.distributed.init_process_group('gloo', rank=rank, world_size=world)
    try:
        res = [loop.all_ranks(f[rank], 'cpu', world) for f in flags]
        (out_dir / f'rank{rank}.json').write_text(json.dumps(res))
    finally:
        torch.distributed.destroy_process_group()


def test_update_skip_is_agreed_by_every_rank(tmp_path):
    """A loss without gradient on one rank must skip the update on all of them (else DDP's all-reduce hangs)."""
    import socket
    import torch.multiprocessing as mp
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    flags = [(True, True), (True, False), (False, True), (False, False)]
    ctx = mp.spawn(_all_ranks_worker, args=(2, port, flags, tmp_path), nprocs=2, join=False)
    deadline = time.time() + 120
    while not ctx.join(timeout=5):
        if time.time() > deadline:
            for p in ctx.processes:
                p.kill()
            pytest.fail('the ranks did not agree within 120 s (a hang in the all-reduce)')
    for r in (0, 1):
        assert json.loads((tmp_path / f'rank{r}.json').read_text()) == [True, False, False, False]
    assert loop.all_ranks(True, 'cpu', 1) and not loop.all_ranks(False, 'cpu', 1)


def test_distributed_training_under_torchrun_on_cpu_without_ros_gtsam_or_rosbags(tmp_path):
    """`torchrun --nproc_per_node 2` (Gloo on the CPU): both ranks train on disjoint scene seeds (two per step),
    only rank 0 validates and writes files, and the export says so. And a GPU machine with only PyTorch, numpy,
    scipy and OpenCV must be able to train: every rank runs with the ROS, gtsam, bag and Open3D imports blocked,
    pose-noise augmentation and the streaming validation included (one run checks both: each rank is a fresh
    interpreter, the costliest part of either check)."""
    import subprocess
    import sys
    from dpv_sensor.core.nets.checkpoint import load_checkpoint
    repo = pathlib.Path(__file__).parents[1]
    script = tmp_path / 'train_without_ros.py'
    script.write_text(
        "import sys\n"
        f"sys.path.insert(0, {str(repo)!r})\n"
        "for m in ('gtsam', 'rclpy', 'rosbags', 'open3d'):\n"
        "    sys.modules[m] = None\n"
        "from dpv_sensor.tools import train\n"
        "sys.exit(train.main())\n")
    cmd = [sys.executable, '-m', 'torch.distributed.run', '--standalone', '--nproc_per_node', '2', str(script),
           '--preset', 'lite', '--run-dir', str(tmp_path / 'run'),
           '--export', str(tmp_path / 'w.safetensors'), '--width', '64', '--height', '48', '--batch-size', '1',
           '--unroll', '2', '--steps', '3', '--val-every', '3', '--val-seeds', '0', '--val-keyframes', '6',
           '--threads', '1', '--num-workers', '0', '--quiet', '--ckpt-every', '3', '--device', 'cpu',
           '--pose-noise-prob', '1.0', '--val-stream-seeds', '20', '--val-stream-frames', '10',
           '--select-metric', 'stream_abs_rel_knet_both']
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=str(repo))
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    finals = [json.loads(line) for line in res.stdout.splitlines() if line.startswith('{"step"')]
    assert sorted(f['step'] for f in finals) == [3, 3]
    assert sum(f['best'] is not None for f in finals) == 1          # only rank 0 validates
    state = json.loads((checkpoints.latest_checkpoint(str(tmp_path / 'run')) / 'state.json').read_text())
    assert state['world_size'] == 2 and state['samples_seen'] == 3
    assert [v['step'] for v in state['history']['val']] == [0, 3]
    _, meta = load_checkpoint(str(tmp_path / 'w.safetensors'))
    assert 'x 2' in meta['optimizer']
    lo, hi = meta['training_data']['train_seed_range']
    assert lo == TRAIN_SEED_BASE and hi - lo == 2 * max(1, meta['training_data']['samples_seen'])
    # the streaming validation ran on rank 0, with exact and noisy poses (the selection metric's two halves)
    from dpv_sensor.training.stream_validation import stream_metric_key
    metrics = state['history']['val'][-1]['metrics']
    for noisy in (False, True):
        assert metrics[stream_metric_key('knet', noisy)]['abs_rel'] > 0, sorted(metrics)
