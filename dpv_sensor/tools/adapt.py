"""``ros2 run dpv_sensor adapt``: fit the depth networks to your own recording, without depth labels.

Examples::

    # a rosbag2 of your robot (camera image or compressed image, camera_info, odometry, /tf_static: found by type)
    adapt my_building.mcap --out adapted/
    # a sequence folder (images/ PNG or JPEG, poses.txt, K.txt; depth/ is never read)
    adapt DATA/my_office --out adapted/ --minutes 10
    # then run the node with the adapted weights
    ros2 run dpv_sensor node --ros-args -p weights:=adapted/weights.safetensors

The recording is resized to the node's processing size (320x256 by default) and cut into keyframes as the node
cuts them; about --holdout of its keyframes are held out, in up to --holdout-blocks blocks spread over the
recording (a recording too short for blocks, under 14 keyframes, is refused: exit 2; --holdout-layout end holds out
its last --holdout share of frames instead). The networks are adapted on the rest with a photometric reprojection
loss across each keyframe window, using the recording's poses (--poses window: the poses the node would use, the
recording run once through its pipeline and refinement window), tied to the shipped weights
(dpv_sensor/training/adapt_loop.py; docs/adaptation.md). Both weights are then scored on each held-out run by
the depth's error at metric anchors: points of the held-out keyframes triangulated with the recording's poses
from frames never trained on (--judge anchors, the default; the photometric reprojection error is reported
beside it and vetoes weights it finds worse); the adapted weights are written only when the runs show the gain by a
one-sided sign-flip test at --significance (dpv_sensor/training/heldout_decision.py). A recording whose held-out
keyframes give too few anchors to judge (a camera turning in place, blank walls) is refused before training.
--minutes caps the whole run (the default fits a 700-image recording on a 2-core CPU).

Writes to --out: weights.safetensors (only when better; with metadata: base weights and their hash, the
recording, steps, losses, minutes, scores), report.json and report.png (loss curve and a before/after montage of
held-out frames). --gt FOLDER (a sequence folder with depth/ whose frames are the recording's) adds abs_rel,
delta<1.25 and ECE of the held-out frames through the node's pipeline at its defaults, before and after (not
counted in --minutes). --supervised fine-tunes with the trainer's loss on a recording that has depth: a folder's
depth/, or a bag's --depth-topic (a depth camera registered to the colour camera).

Exit status: 0 weights written; 1 not written (adapted weights scored no better, too few anchors to judge them,
or no step fitted in --minutes; one line says why); 2 bad input; 130 interrupted (nothing written).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import pathlib
import signal
import sys
import time
from typing import Dict, List, Optional

from dpv_sensor import params as P
from dpv_sensor.cli import tool_argv
from dpv_sensor.training.adapt_loop import DEFAULT_MINUTES, DISTILL_PIXELS, HOLDOUT_LAYOUTS, AdaptConfig
from dpv_sensor.training.adapt_poses import POSE_SOURCES
from dpv_sensor.training.anchor_judge import JUDGES
from dpv_sensor.training.config import MODULES

EXIT_WRITTEN, EXIT_REFUSED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
WEIGHTS_NAME, REPORT_JSON, REPORT_PNG = 'weights.safetensors', 'report.json', 'report.png'


def build_parser() -> argparse.ArgumentParser:
    d = AdaptConfig()
    p = argparse.ArgumentParser(prog='adapt', description=__doc__.split('\n\n')[0], epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('source', help='the recording: a rosbag2 (folder or .mcap/.db3) or a sequence folder')
    p.add_argument('--out', required=True, help='output folder (created)')
    p.add_argument('--minutes', type=float, default=d.minutes,
                   help=f'time cap of the whole run (default {DEFAULT_MINUTES:g})')
    p.add_argument('--steps', type=int, default=0, help='stop after this many steps (0: as many as --minutes allows)')
    p.add_argument('--weights', default=None, help='weights to start from (default: the packaged weights of --preset)')
    p.add_argument('--preset', default=P.default('preset'), choices=P.choices('preset'), help='network preset')
    p.add_argument('--width', type=int, default=d.width, help="processing width (the node's processing_width)")
    p.add_argument('--height', type=int, default=d.height, help="processing height (the node's processing_height)")
    p.add_argument('--holdout', type=float, default=d.holdout,
                   help='share held out: of the keyframes (spread) or of the last frames (end)')
    p.add_argument('--holdout-layout', default=d.holdout_layout, choices=HOLDOUT_LAYOUTS,
                   help="where the held-out part lies: 'spread' (default: blocks of keyframes spread evenly over the "
                        "recording, none trained on; a recording too short for one block is refused) or 'end' (the "
                        "last frames)")
    p.add_argument('--holdout-blocks', type=int, default=d.holdout_blocks,
                   help='--holdout-layout spread: at most this many held-out blocks')
    p.add_argument('--significance', type=float, default=d.significance,
                   help='write the adapted weights only when their held-out runs score better with a one-sided '
                        'sign-flip p-value at most this (needs at least 5 runs at 0.05; 1: whenever the mean is '
                        'lower)')
    p.add_argument('--gt', default='', metavar='FOLDER',
                   help='a sequence folder with depth/ matching the recording frame for frame: adds abs_rel, '
                        'delta<1.25 and ECE of the held-out frames before and after')
    p.add_argument('--supervised', action='store_true',
                   help="fine-tune with the trainer's loss on the recording's depth (a sequence folder with depth/, "
                        'or a bag with --depth-topic)')
    p.add_argument('--lr', type=float, default=d.lr, help='learning rate (AdamW)')
    p.add_argument('--unroll', type=int, default=d.unroll, help='filter steps unrolled per sample')
    p.add_argument('--penalty', type=float, default=d.penalty, help='weight of ||theta - theta_base||^2')
    p.add_argument('--distill', type=float, default=d.distill,
                   help=f'weight of KL(base DPV || adapted DPV) ({d.distill:g}; 0: no tie to the base DPV)')
    p.add_argument('--distill-pixels', choices=DISTILL_PIXELS, default=d.distill_pixels,
                   help='all: the KL on every pixel; confident: weighted by how sure the base network is there '
                        '(0 up to --distill-threshold, 1 at confidence 1)')
    p.add_argument('--distill-threshold', type=float, default=d.distill_threshold,
                   help=f"the base network's confidence where the 'confident' tie starts ({d.distill_threshold:g})")
    p.add_argument('--photometric', type=float, default=d.photometric,
                   help='weight of the photometric reprojection term')
    p.add_argument('--evidence', type=float, default=d.evidence,
                   help="weight of the plane sweep's photometric evidence term")
    p.add_argument('--sigma', type=float, default=d.sigma, help='photometric error scale of the evidence term')
    p.add_argument('--aux', type=float, default=d.aux, help="weight of the 1/4-res measurement's terms")
    p.add_argument('--readout', choices=('mean', 'median', 'relative'), default=d.readout,
                   help='the depth the photometric loss warps with (the DPV readout)')
    p.add_argument('--train-modules', nargs='+', choices=MODULES, default=list(d.train_modules), metavar='MODULE',
                   help=f'adapt only these sub-networks ({", ".join(MODULES)}; default: all)')
    p.add_argument('--poses', choices=POSE_SOURCES, default=d.poses,
                   help="odometry (default): the recording's poses as they are; window: the keyframes' poses as "
                        "the node uses them (the recording run once through the node's pipeline with its refinement "
                        'window)')
    p.add_argument('--judge', choices=JUDGES, default=d.judge,
                   help="what decides whether the weights are written: 'anchors' (default): the depth's error at "
                        "metric anchors triangulated from the held-out keyframes' own images and poses (the "
                        "photometric score beside it may veto; too few anchors: refused, exit 1); 'photometric': "
                        'the photometric score alone (blind to depth where the images have no texture)')
    p.add_argument('--anchor-loss', type=float, default=d.anchor_loss,
                   help="weight of a sparse depth loss at the training keyframes' own anchors (0: none)")
    p.add_argument('--seed', type=int, default=d.seed, help='seed of the sample order')
    p.add_argument('--threads', type=int, default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument('--image-topic', default=None, help='bag: the image topic (needed only among several)')
    p.add_argument('--camera-info-topic', default=None, help='bag: the camera_info topic')
    p.add_argument('--odom-topic', default=None, help='bag: the odometry topic')
    p.add_argument('--depth-topic', default=None,
                   help='bag, with --supervised: the depth image topic, registered to the colour camera (same size '
                        'and intrinsics, e.g. aligned_depth_to_color); each image takes the depth nearest its stamp '
                        'within 20 ms')
    p.add_argument('--T-base-camera', type=float, nargs=7, default=None,
                   metavar=('X', 'Y', 'Z', 'QX', 'QY', 'QZ', 'QW'),
                   help='bag: the camera mount in the odometry child frame (default: /tf_static, else identity)')
    p.add_argument('--quiet', action='store_true', help='no progress bar or log lines')
    return p


def _config(a) -> AdaptConfig:
    return AdaptConfig(width=a.width, height=a.height, minutes=a.minutes, max_steps=a.steps, lr=a.lr,
                       unroll=a.unroll, holdout=a.holdout, holdout_layout=a.holdout_layout,
                       holdout_blocks=a.holdout_blocks, significance=a.significance,
                       train_modules=tuple(a.train_modules), aux=a.aux,
                       penalty=a.penalty, distill=a.distill, distill_pixels=a.distill_pixels,
                       distill_threshold=a.distill_threshold, readout=a.readout, photometric=a.photometric,
                       evidence=a.evidence, sigma=a.sigma, supervised=a.supervised, poses=a.poses,
                       judge=a.judge, anchor_loss=a.anchor_loss, seed=a.seed).check()


def _file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, 'rb') as f:
        for chunk in iter(lambda: f.read(1 << 20), b''):
            h.update(chunk)
    return h.hexdigest()


def _load(a, log):
    """(recording sequence at the processing size, in memory; its source dict)."""
    from dpv_sensor.data.recording import is_bag, load_recording
    size = (a.width, a.height)
    if a.depth_topic and not a.supervised:
        raise ValueError('--depth-topic is read only with --supervised (the default never reads depth)')
    if a.supervised and not is_bag(a.source):
        from dpv_sensor.data.sequence import Sequence
        seq = Sequence(a.source)
        if not seq.has_depth:
            raise ValueError(f'--supervised needs depth: {a.source} has no depth/')
        source = {'kind': 'folder', 'path': str(pathlib.Path(a.source).resolve()), 'name': pathlib.Path(a.source).name,
                  'frames': len(seq), 'native_size': list(seq.size), 'depth_read': True}
        return seq.resized(*size).materialize(), source
    if a.supervised and not a.depth_topic:
        raise ValueError('--supervised on a bag needs --depth-topic (the depth image topic registered to the colour '
                         'camera)')
    rec = load_recording(a.source, size=size, image_topic=a.image_topic, camera_info_topic=a.camera_info_topic,
                         odom_topic=a.odom_topic, T_base_camera=a.T_base_camera, depth_topic=a.depth_topic)
    seq, source = rec.sequence, rec.source
    if source['kind'] == 'bag':
        depth = (f"; depth: {a.depth_topic} (pairs at most {source['depth_offset_ms_max']:g} ms apart)"
                 if a.depth_topic else '')
        log(f"bag topics: {source['topics_chosen']}{depth}; camera mount: {source['camera_mount']}")
    return seq.materialize(), source


def _gt_sequence(gt_folder: str, frames: int):
    """The --gt folder, checked before any work: a sequence folder with depth/ and the recording's frame count."""
    from dpv_sensor.data.sequence import Sequence
    gt = Sequence(gt_folder)
    if not gt.has_depth:
        raise ValueError(f'--gt {gt_folder} has no depth/')
    if len(gt) != frames:
        raise ValueError(f'--gt {gt_folder} has {len(gt)} frames, the recording {frames}: they must match frame for '
                         'frame')
    return gt


_GT_KEYS = ('abs_rel', 'delta1', 'ece', 'mean_confidence', 'kept_0.9', 'delta1_0.9')


def _gt_scores(gt, ranges: List[List[int]], models: Dict, cfg: AdaptConfig, log) -> Dict:
    """abs_rel, delta1 and ECE of the held-out frames of the --gt sequence through the pipeline at the node's
    defaults (GT poses), per model: each held-out range [first, last] run on its own, the figures their means
    weighted by scored keyframes."""
    from dpv_sensor.evaluation.offline import EvalOptions, evaluate_sequence
    overrides = {'processing_width': cfg.width, 'processing_height': cfg.height}
    out = {}
    for name, model in models.items():
        t0 = time.time()
        parts = []
        for first, last in ranges:
            s = evaluate_sequence(gt.subset(range(first, last + 1)), overrides,
                                  options=EvalOptions(progress=False, consumer_odometry=False), model=model)
            fm = s['metric']['frame_mean']
            cal = s.get('calibration') or {}
            kept = (cal.get('kept') or {}).get('0.9') or {}
            parts.append((s['num_keyframes'], {'abs_rel': fm['abs_rel'], 'delta1': fm['delta1'], 'ece': cal.get('ece'),
                                               'mean_confidence': cal.get('mean_confidence'),
                                               'kept_0.9': kept.get('share'), 'delta1_0.9': kept.get('delta1')}))
        parts = [(k, f) for k, f in parts if k > 0]          # a range with no keyframe output has no figures
        n = sum(k for k, _ in parts)
        out[name] = {key: (sum(k * f[key] for k, f in parts) / n if n and all(f[key] is not None for _, f in parts)
                           else None) for key in _GT_KEYS}
        out[name].update(keyframes=n, seconds=round(time.time() - t0, 1))
        shown = {key: float('nan') if v is None else v for key, v in out[name].items()}
        log(f"GT on the held-out frames, {name}: abs_rel {shown['abs_rel']:.4f}, delta1 {shown['delta1']:.3f}, "
            f"ECE {shown['ece']:.3f}")
    return {'folder': str(pathlib.Path(gt.folder).resolve()), 'frames': ranges,
            'how': 'the pipeline at the node defaults, GT poses, each held-out range of frames', **out}


def _atomic_json(path: pathlib.Path, data: Dict) -> None:
    from dpv_sensor.common import to_jsonable
    tmp = path.with_name(f'.{path.name}.tmp-{os.getpid()}')
    try:
        tmp.write_text(json.dumps(to_jsonable(data), indent=1, allow_nan=True))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _metadata(a, cfg: AdaptConfig, base_path: pathlib.Path, base_meta: Dict, source: Dict, result, minutes: float,
              gt: Optional[Dict], argv: List[str]) -> Dict:
    from dpv_sensor.training.adapt_loop import LOSS_DESCRIPTION
    base_steps = int(base_meta.get('steps') or 0)
    adaptation = {
        'base_weights': {'file': str(base_path), 'sha256': _file_sha256(base_path),
                         'tensors_sha256': base_meta.get('tensors_sha256'), 'steps': base_steps},
        'recording': {**source, 'keyframes': result.keyframes},
        'processing_size': [cfg.width, cfg.height],
        'steps': result.steps, 'minutes': round(minutes, 2), 'stop_reason': result.stop_reason,
        'loss': "the trainer's loss on the recording's depth" if cfg.supervised else LOSS_DESCRIPTION,
        'config': cfg.to_json(),
        'held_out': {'score': result.score_kind, 'base': result.base_score, 'adapted': result.adapted_score,
                     'runs': result.verdict.runs, 'runs_better': result.verdict.runs_better,
                     'p_value': result.verdict.p_value, 'significance': result.verdict.significance,
                     'beside': {k: {'base': v['base'], 'adapted': v['adapted']} for k, v in result.beside.items()}},
        'ground_truth': gt,
        'command': ' '.join(['adapt'] + argv),
    }
    return {'adaptation': adaptation, 'steps': base_steps + result.steps, 'input_size': [cfg.width, cfg.height],
            'training_data': {'base': base_meta.get('training_data'), 'adapted_on': source.get('name')},
            'validation_metrics': adaptation['held_out'], 'loss': adaptation['loss']}


def _sigterm(signum, frame):
    raise KeyboardInterrupt(f'signal {signum}')


def run(a, argv: List[str], log) -> int:
    import torch

    from dpv_sensor.core.nets.checkpoint import default_weights_path, load_checkpoint, save_checkpoint
    from dpv_sensor.training.adapt_loop import Adapter
    from dpv_sensor.training.plots import save_adapt_report
    t0 = time.time()
    cfg = _config(a)
    deadline = t0 + cfg.minutes * 60.0
    if a.threads:
        torch.set_num_threads(a.threads)
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    base_path = pathlib.Path(a.weights) if a.weights else default_weights_path(a.preset)
    model, base_meta = load_checkpoint(base_path, preset=a.preset)
    seq, source = _load(a, log)
    gt_seq = _gt_sequence(a.gt, len(seq)) if a.gt else None
    log(f'{source["name"]}: {len(seq)} frames at {cfg.width}x{cfg.height} ({time.time() - t0:.0f} s to load)')
    adapter = Adapter(cfg, model, seq, log=log, progress=not a.quiet)
    held = adapter.held_frames()
    log(f'keyframes: {len(adapter.train_kf)} to adapt on, {len(adapter.held_kf)} held out (frames '
        f'{", ".join(f"{a}..{b}" for a, b in held)})')
    result = adapter.run(deadline, progress=not a.quiet)
    minutes = (time.time() - t0) / 60.0
    gt = None
    if gt_seq is not None:
        base_model, _ = load_checkpoint(base_path, preset=a.preset)
        gt = _gt_scores(gt_seq, held, {'base': base_model, 'adapted': model.eval()}, cfg, log)
    report = {'source': source, 'config': cfg.to_json(), 'base_weights': str(base_path), 'steps': result.steps,
              'stop_reason': result.stop_reason, 'minutes': round(minutes, 2), 'seconds': result.seconds,
              'held_out': {'score': result.score_kind, 'base': result.base_score, 'adapted': result.adapted_score,
                           'verdict': result.verdict.to_json(), 'keyframes': result.keyframes,
                           'runs': result.runs, 'beside': result.beside, 'anchors': result.anchors},
              'poses': {'source': cfg.poses, **(adapter.pose_stats or {})},
              'ground_truth': gt, 'history': result.history}
    if result.refused:
        reason = result.refused
    elif result.steps == 0:
        reason = f'no adaptation step fitted in --minutes {cfg.minutes:g}'
    elif not result.improved:
        reason = result.verdict.reason
    else:
        reason = ''
    report['written'] = not reason
    report['refused'] = reason or None
    if not reason:
        from dpv_sensor.common import to_jsonable
        # strict JSON: a score no run could give (NaN) is None
        meta = to_jsonable(_metadata(a, cfg, base_path, base_meta, source, result, minutes, gt, argv))
        save_checkpoint(out / WEIGHTS_NAME, model, meta)            # atomic: temp file + rename
        report['weights'] = str(out / WEIGHTS_NAME)
    _atomic_json(out / REPORT_JSON, report)
    save_adapt_report(str(out / REPORT_PNG), result, gt, model.d_min, model.d_max,
                      title=f'{source["name"]}: {result.steps} steps, {minutes:.1f} min')
    print(f'adapt: {result.steps} steps in {minutes:.1f} min (limit {cfg.minutes:g}); held-out {result.score_kind} '
          f'{result.base_score:.5f} -> {result.adapted_score:.5f}'
          + ''.join(f"; {k} {b['base']:.5f} -> {b['adapted']:.5f}" for k, b in result.beside.items()), flush=True)
    if reason:
        print(f'adapt: weights not written: {reason}', file=sys.stderr, flush=True)
        return EXIT_REFUSED
    print(f'adapt: wrote {out / WEIGHTS_NAME}; run the node with -p weights:={out / WEIGHTS_NAME}', flush=True)
    return EXIT_WRITTEN


def main(argv: Optional[List[str]] = None) -> int:
    argv = tool_argv(argv)
    a = build_parser().parse_args(argv)

    def log(msg: str) -> None:
        if not a.quiet:
            print(f'[adapt {time.strftime("%H:%M:%S")}] {msg}', flush=True)

    previous = signal.signal(signal.SIGTERM, _sigterm)
    try:
        return run(a, argv, log)
    except KeyboardInterrupt:
        print('adapt: interrupted; no weights written', file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    except (ValueError, OSError) as e:
        print(f'adapt: {e}', file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    except Exception as e:
        if type(e).__name__ in ('BagError', 'SequenceFormatError', 'CheckpointError'):
            print(f'adapt: {e}', file=sys.stderr, flush=True)
            return EXIT_BAD_INPUT
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)


if __name__ == '__main__':
    sys.exit(main())
