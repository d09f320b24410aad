"""`make demo` / `ros2 run dpv_sensor demo`: the whole virtual depth camera end to end, in one output folder.

    python -m dpv_sensor.tools.demo --out out/demo                       # synthetic scene (the default)
    python -m dpv_sensor.tools.demo --out out/mine --bag my_run.mcap \\
        [--image-topic /camera/color/image_raw --camera-info-topic /camera/color/camera_info --odom-topic /odom] \\
        [--gt SEQUENCE_FOLDER] [--params T_base_camera=[0,0,0,-0.5,0.5,-0.5,0.5] preset=lite ...]

Steps (each prints a progress line and its time):

1. render  a synthetic room (data.synthetic.render_sequence) with a fixed seed that training never sees (seed 42:
           in the validation range 0..99 that training refuses, and not among the seeds 0..3 the packaged
           checkpoint was validated on) and save it as a sequence folder: OUT/sequence (the ground truth:
           images as lossless PNG, depth PNG in mm, poses, K, stamps).
2. bag     write it as a rosbag2 (MCAP): OUT/input_bag with /image, /camera_info and /odom
           (odometry at 100 Hz, interpolated between the frames; the stamps are the sequence's).
3. node    start the node as its own process (`python -m dpv_sensor.ros.node --ros-args -p ... -r ...`) with a private
           ROS_DOMAIN_ID (localhost only) and ROS_LOG_DIR under OUT/logs; wait until its estimator is built and its
           subscriptions match the player's publishers.
4. replay  play the bag into the node with dpv_sensor.client.ros_io.BagPlayer and record the node's outputs
           (depth/image, depth/camera_info, confidence/image, /diagnostics) with BagRecorder into OUT/output_bag.
           Pacing ("lockstep", the default): real time at most, and each image is held back until the node has
           finished every earlier one (its /diagnostics counters frames_processed + dropped_total, published every
           0.1 s, say so). The node's one-slot mailbox then never has to drop an image, so every keyframe of the
           sequence is estimated and evaluated whatever the CPU speed; odometry and camera_info flow freely. This
           needs odometry at least as often as images (an odometry message at or after each image's stamp before
           the next image), as in any bag `bag write` produces. `--realtime` plays at --rate x real time without
           waiting instead, like a live camera: the node then drops what it cannot keep up with.
5. stop    SIGINT to the node; its exit code must be 0.
6. eval    score the recorded bag against the ground truth with the `evaluate bag` tool itself (same code, same
           options, in-process): OUT/eval/summary.json, frames.csv, montage.png, sparsification.png. The summary
           prints the exact command that reproduces the numbers.
7. fuse    TSDF-fuse the recorded depth (all pixels, and confidence-masked) and the GT depth with the GT poses, and
           score the meshes (accuracy / completeness / F-score) with the `fuse bag` tool: OUT/fusion/*.ply,
           fusion.json.
8. summary what ran (measurement model, weights, preset, filter, frames, keyframes), the headline metrics, the
           fusion figures and where the pictures are; also OUT/summary.json.

With --bag (a user's own recording): steps 1-2 are skipped; /tf_static and /tf are replayed too when the bag has
them (the node then takes the camera mount from TF: no T_base_camera to type); the image, camera_info and odometry
topics are found by message type (the only sensor_msgs/Image, CameraInfo and nav_msgs/Odometry topic; the
camera_info next to the image among several) and printed; --image-topic / --camera-info-topic / --odom-topic
choose among several (all are remapped onto the node's `image`, `camera_info`, `odom`). A camera recorded as
image_transport's compressed sensor_msgs/CompressedImage (JPEG or PNG; a bag holding raw Image too plays the raw one
unless --image-topic names the compressed one) is remapped onto `image/compressed` and the node runs with
image_transport=compressed. Camera settings and everything else go in as node parameters with --params (e.g.
camera_info_source=parameters fx=... fy=... cx=... cy=..., odometry=none, T_base_camera=[x,y,z,qx,qy,qz,qw]).
Without --gt there is nothing to score against: the outputs are still recorded, and OUT/montage.png shows image |
depth | confidence for a few keyframes, with
coverage and confidence statistics in the summary. With --gt (a sequence folder whose stamps match the bag's, or
whose frame 0 is the bag's first image) steps 6 and 7 run as for the synthetic scene.

Everything that is written lives under --out (existing demo outputs there are replaced). Exit code 0 when every
step ran (warnings, e.g. dropped images, are listed in the summary); 1 when a step failed; 2 for bad arguments.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import pathlib
import shlex
import shutil
import sys
import time
from typing import Any, Dict, List, Optional

from dpv_sensor.client.ros_io import private_ros_env
from dpv_sensor.cli import tool_argv
from dpv_sensor.client.replay import (  # noqa: F401  (the replay machinery the demo drives)
    DEMO_NODE_PARAMS, DIAGNOSTICS_SUFFIX, ODOM_RATE_HZ, OUTPUT_TOPICS, GatedPublisher, NodeMonitor,
    ReplayError as DemoError, ReplayResult, Steps, _as_number, _rel, end_to_end_latency, parse_params, render_scene,
    run_node_replay)

REPO = pathlib.Path(__file__).resolve().parents[2]
NS = 1_000_000_000

# Seed 42 is in VAL_SEEDS (0..99): dpv_sensor.training.dataset refuses to train on it; the packaged checkpoint's
# validation used seeds 0..3 only. So the demo scene is one no weights have seen in any role.
DEFAULT_SEED = 42
DEFAULT_FRAMES = 60
DEFAULT_WIDTH = 320
DEFAULT_HEIGHT = 240
# what the demo writes under OUT (removed first when they exist)
OUT_ITEMS = ('sequence', 'input_bag', 'output_bag', 'eval', 'fusion', 'logs', 'montage.png', 'summary.json')


def _run_tool(main, argv: List[str], log_path: pathlib.Path) -> tuple:
    """Run a tool's main(argv) in-process with its stdout/stderr captured into log_path; (code, stdout)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    text = out.getvalue()
    log_path.write_text(f'$ {" ".join(shlex.quote(a) for a in argv)}\n{text}\n{err.getvalue()}')
    return code, text


def _table_lines(text: str) -> List[str]:
    return [ln for ln in text.splitlines() if ln.startswith('|')]


def montage_without_gt(input_bag, output_bag, image_topic: str, path: pathlib.Path, rows: int = 4) -> Dict[str, Any]:
    """image | depth | confidence for a few recorded outputs (no ground truth); returns output statistics."""
    import numpy as np
    from dpv_sensor.ros import msgs as M
    from dpv_sensor.ros.compressed_image import image_message_to_rgb
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.data.topic_detection import find_topic
    from dpv_sensor.evaluation.plots import _plt, depth_range
    topics = R.bag_topics(output_bag)
    d_topic = find_topic(topics, R.DEPTH_TOPIC, 'depth/image', R.IMAGE)
    c_topic = find_topic(topics, R.CONFIDENCE_TOPIC, 'confidence/image', R.IMAGE)
    if d_topic is None:
        raise DemoError(f'{output_bag} holds no depth images')
    depth = R.read_depth_images(output_bag, d_topic)
    conf = {s.stamp_ns: s.data for s in R.read_depth_images(output_bag, c_topic)} if c_topic else {}
    stats = {'outputs': len(depth)}
    if not depth:
        return stats
    cov = [float(np.isfinite(s.data).mean()) for s in depth]
    confs = [float(np.nanmean(conf[s.stamp_ns][np.isfinite(s.data)])) for s in depth
             if s.stamp_ns in conf and np.isfinite(s.data).any()]
    vals = np.concatenate([s.data[np.isfinite(s.data)] for s in depth]) if any(c > 0 for c in cov) else np.zeros(0)
    stats.update({'coverage_mean': float(np.mean(cov)),
                  'confidence_mean': float(np.mean(confs)) if confs else float('nan'),
                  'depth_m_p5_p50_p95': [float(x) for x in np.percentile(vals, [5, 50, 95])] if vals.size else None,
                  'size': [int(depth[0].data.shape[1]), int(depth[0].data.shape[0])]})
    pick = sorted(set(np.linspace(0, len(depth) - 1, min(rows, len(depth))).round().astype(int).tolist()))
    wanted = {depth[k].stamp_ns for k in pick}
    images = {}
    for _t, _ty, _log, msg in R.read_messages(input_bag, [image_topic]):
        s = M.stamp_to_ns(msg.header.stamp)
        if s in wanted:
            images[s] = image_message_to_rgb(msg)
            if len(images) == len(wanted):
                break
    plt = _plt()
    vmin, vmax = depth_range([depth[k].data for k in pick])
    h, w = depth[pick[0]].data.shape
    fig, axes = plt.subplots(len(pick), 3, figsize=(3 * 2.6 + 1.0, 2.6 * len(pick) * h / w + 0.8), squeeze=False)
    cm_d = plt.get_cmap('turbo').with_extremes(bad='0.5')
    cm_c = plt.get_cmap('viridis').with_extremes(bad='0.5')
    for r, k in enumerate(pick):
        s = depth[k]
        img = images.get(s.stamp_ns)
        ax = axes[r]
        ax[0].imshow(img if img is not None else np.full((h, w, 3), 128, np.uint8))
        ax[0].set_ylabel(f't = {s.stamp_ns / NS:.3f} s', fontsize=8)
        d = np.ma.masked_invalid(s.data)
        im_d = ax[1].imshow(d, cmap=cm_d, vmin=vmin, vmax=vmax, interpolation='nearest')
        c = conf.get(s.stamp_ns)
        im_c = ax[2].imshow(np.ma.masked_where(~np.isfinite(s.data), c) if c is not None else np.zeros((h, w)),
                            cmap=cm_c, vmin=0, vmax=1, interpolation='nearest')
        for a in ax:
            a.set_xticks([])
            a.set_yticks([])
    for c, name in enumerate(['image', 'depth', 'confidence']):
        axes[0][c].set_title(name, fontsize=9)
    fig.subplots_adjust(left=0.04, right=0.84, top=0.95, bottom=0.02, wspace=0.04, hspace=0.06)
    for j, (im, label) in enumerate([(im_d, 'depth (m)'), (im_c, 'confidence')]):
        cb = fig.colorbar(im, cax=fig.add_axes([0.86 + 0.06 * j, 0.1, 0.012, 0.8]))
        cb.set_label(label, fontsize=7)
        cb.ax.tick_params(labelsize=6)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    stats['montage'] = str(path)
    return stats


def _weights_info(diag: Dict[str, str]) -> Dict[str, Any]:
    """Which measurement model ran, and for the network the weights file and its training steps."""
    info: Dict[str, Any] = {'measurement_model': diag.get('measurement_model'),
                            'measurement_reason': diag.get('measurement_reason')}
    reason = diag.get('measurement_reason') or ''
    marker = 'network weights loaded from '
    if info['measurement_model'] == 'network' and marker in reason:
        path = reason.split(marker, 1)[1].strip()
        info['weights'] = path
        try:
            from dpv_sensor.core.nets.checkpoint import read_metadata
            meta = read_metadata(path)
            info['weights_steps'] = meta.get('steps')
            info['weights_preset'] = meta.get('preset')
        except Exception as exc:   # the node loaded it; a metadata hiccup here is not worth failing for
            info['weights_metadata_error'] = str(exc)
    return info


def _fmt(v, f='{:.4f}'):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return '-'
    try:
        return f.format(v)
    except (ValueError, TypeError):
        return str(v)


# --------------------------------------------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------------------------------------------
def _bag_inputs(a, values: Dict[str, Any], input_bag: pathlib.Path):
    """(topics, how they were chosen, bag topics) of the user's bag; DemoError naming what is missing."""
    from dpv_sensor.client.replay import bag_input_topics
    from dpv_sensor.data import rosbag_io as R
    if not input_bag.exists():
        raise DemoError(f'{input_bag}: no such bag')
    bt = R.bag_topics(input_bag)
    hints = {'image': '--image-topic (IMAGE_TOPIC= with make)',
             'camera_info': '--camera-info-topic (CAMERA_INFO_TOPIC= with make; or --params '
                            'camera_info_source=parameters fx=.. fy=.. cx=.. cy=..)',
             'odom': '--odom-topic (ODOM_TOPIC= with make; or --params odometry=none for visual odometry)'}
    try:
        topics, how = bag_input_topics(bt, values, image=a.image_topic, camera_info=a.camera_info_topic,
                                       odom=a.odom_topic, hints=hints)
    except R.BagError as exc:
        raise DemoError(f'{input_bag}: {exc}') from None
    return topics, how, bt


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='demo', description=__doc__.split('\n\n')[0],
                                epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--out', default='out/demo', help='output folder (default out/demo)')
    g = p.add_argument_group('synthetic scene (default)')
    g.add_argument('--seed', type=int, default=DEFAULT_SEED,
                   help=f'scene seed (default {DEFAULT_SEED}, never trained on)')
    g.add_argument('--frames', type=int, default=None,
                   help=f'frames to render (default {DEFAULT_FRAMES}); with --bag: replay at most this many images')
    g.add_argument('--width', type=int, default=DEFAULT_WIDTH, help=f'rendered width (default {DEFAULT_WIDTH})')
    g.add_argument('--height', type=int, default=DEFAULT_HEIGHT, help=f'rendered height (default {DEFAULT_HEIGHT})')
    b = p.add_argument_group('your own bag')
    b.add_argument('--bag', help='a rosbag2 (directory or .mcap/.db3) with images, camera_info and odometry')
    b.add_argument('--image-topic', default=None,
                   help='sensor_msgs/Image topic (default: the only one in the bag; needed to choose among several)')
    b.add_argument('--camera-info-topic', default=None,
                   help='sensor_msgs/CameraInfo topic (default: the only one, or the one next to the image)')
    b.add_argument('--odom-topic', default=None, help='nav_msgs/Odometry topic (default: the only one in the bag)')
    b.add_argument('--gt', help='ground-truth sequence folder for --bag (enables evaluation and fusion)')
    b.add_argument('--stamp-offset', default='auto', help='passed to `evaluate bag` / `fuse bag` (default auto)')
    n = p.add_argument_group('node and replay')
    n.add_argument('--params', nargs='*', default=[], metavar='KEY=VALUE',
                   help='node parameters (config/dpv_sensor.yaml names), e.g. measurement=classical preset=lite '
                        'processing_width=160 fx=525 T_base_camera=[0,0,0,0,0,0,1]')
    n.add_argument('--realtime', action='store_true',
                   help='play at --rate x real time without waiting for the node (it drops what it cannot keep up '
                        'with); default: lockstep, no image dropped')
    n.add_argument('--rate', type=float, default=1.0, help='playback speed cap / factor (default 1 = real time)')
    n.add_argument('--start-timeout', type=float, default=180.0,
                   help='seconds to wait for the node to start and subscribe (default 180; >= 10)')
    n.add_argument('--frame-timeout', type=float, default=180.0,
                   help='lockstep: longest wait for the node to finish one image (default 180 s)')
    n.add_argument('--domain-id', type=int, default=None,
                   help='ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID when set, else a random private one)')
    f = p.add_argument_group('fusion')
    f.add_argument('--voxel', type=float, default=0.03, help='TSDF voxel size in m (default 0.03)')
    f.add_argument('--fuse-min-confidence', type=float, default=0.9,
                   help='confidence threshold of the masked mesh (default 0.9: with the default ratio confidence, '
                        "pixels 90 %% sure to be within a factor 1.25; about a third of the demo's pixels)")
    f.add_argument('--no-fusion', action='store_true', help='skip step 7')
    p.add_argument('--quiet', action='store_true', help='no progress bars')
    return p


def _stamp_offset_argv(a, gt_dir, input_bag: pathlib.Path, image_topic: str, summary: Dict[str, Any]) -> List[str]:
    """The ``--stamp-offset`` arguments of evaluate and fuse. ``auto``: from the input bag's first image (the
    recorded outputs hold no camera image): GT frame 0 unless the GT's own stamps are the bag's."""
    if a.stamp_offset != 'auto':
        return ['--stamp-offset', str(a.stamp_offset)]
    if gt_dir is None:
        return []
    from dpv_sensor.evaluation.offline import first_image_stamp, gt_stamp_offset, load_sequence
    auto = gt_stamp_offset(first_image_stamp(input_bag, image_topic), load_sequence(gt_dir))
    summary['stamp_offset_s'] = auto
    return ['--stamp-offset', f'{auto:.9f}']


def _evaluate_step(steps: Steps, output_bag: pathlib.Path, gt_dir: pathlib.Path, out: pathlib.Path,
                   offset: List[str], summary: Dict[str, Any]) -> None:
    """Step 6: score the recorded outputs against the ground truth with ``evaluate``."""
    from dpv_sensor.tools import evaluate as EV
    eval_dir, logs = out / 'eval', out / 'logs'
    eval_argv = ['bag', str(output_bag), '--gt', str(gt_dir), '--out', str(eval_dir)] + offset
    summary['evaluate_command'] = ('python -m dpv_sensor.tools.evaluate bag ' + _rel(output_bag) +
                                   ' --gt ' + _rel(gt_dir) + ' --out ' + _rel(out / 'eval_by_hand') +
                                   ''.join(' ' + x for x in offset))
    with steps.step('eval', f'evaluate the recorded outputs against {_rel(gt_dir)} -> {_rel(eval_dir)}') as rec:
        code, text = _run_tool(EV.main, eval_argv + ['--quiet'], logs / 'evaluate.txt')
        if code != 0:
            raise DemoError(f'evaluate failed (exit code {code}); see {_rel(logs / "evaluate.txt")}')
        with open(eval_dir / 'summary.json') as fh:
            ev = json.load(fh)
        summary['evaluation'] = {'table': _table_lines(text), 'summary_json': str(eval_dir / 'summary.json'),
                                 'num_keyframes': ev.get('num_keyframes'),
                                 'metric': (ev.get('metric') or {}).get('frame_mean'),
                                 'median_scaled': (ev.get('median_scaled') or {}).get('frame_mean'),
                                 'coverage': (ev.get('coverage') or {}).get('frame_mean'),
                                 'temporal': (ev.get('temporal_consistency') or {}).get('pair_mean'),
                                 'ause': (ev.get('confidence') or {}).get('ause_frame_mean'),
                                 'input': (ev.get('configuration') or {}).get('input'),
                                 'files': {k: v for k, v in (ev.get('files') or {}).items()}}
        rec['note'] = f"{ev.get('num_keyframes')} keyframes scored"
        unmatched = ((ev.get('configuration') or {}).get('input') or {}).get('unmatched')
        if unmatched:
            summary['warnings'].append(f'{unmatched} recorded depth images matched no ground-truth frame '
                                       '(stamps; see --stamp-offset)')


def _fuse_step(steps: Steps, a, output_bag: pathlib.Path, gt_dir: pathlib.Path, out: pathlib.Path,
               offset: List[str], summary: Dict[str, Any]) -> None:
    """Step 7: TSDF-fuse the recorded depth with ``fuse`` and score the mesh."""
    from dpv_sensor.tools import fuse as FU
    fusion_dir, logs = out / 'fusion', out / 'logs'
    fuse_argv = ['bag', str(output_bag), '--gt', str(gt_dir), '--out', str(fusion_dir), '--voxel',
                 f'{a.voxel:g}', '--min-confidence', f'{a.fuse_min_confidence:g}']
    fuse_argv += offset
    summary['fuse_command'] = ('python -m dpv_sensor.tools.fuse bag ' + _rel(output_bag) + ' --gt ' +
                               _rel(gt_dir) + ' --out ' + _rel(out / 'fusion_by_hand') +
                               f' --voxel {a.voxel:g} --min-confidence {a.fuse_min_confidence:g}' +
                               ''.join(' ' + x for x in offset))
    with steps.step('fuse', f'TSDF-fuse the recorded depth (voxel {a.voxel:g} m) and score the mesh -> '
                    f'{_rel(fusion_dir)}') as rec:
        code, text = _run_tool(FU.main, fuse_argv + ['--quiet'], logs / 'fuse.txt')
        if code != 0:
            raise DemoError(f'fuse failed (exit code {code}); see {_rel(logs / "fuse.txt")}')
        with open(fusion_dir / 'fusion.json') as fh:
            fu = json.load(fh)
        summary['fusion'] = {'unmasked': fu.get('unmasked'), 'masked': fu.get('masked'),
                             'num_frames': fu.get('num_frames'), 'config': fu.get('config'),
                             'files': fu.get('files'), 'table': _table_lines(text)}
        un = fu.get('unmasked') or {}
        rec['note'] = f"F-score {_fmt(un.get('fscore'), '{:.3f}')} (all pixels)"


def _node_summary(replay, values: Dict[str, Any], logs: pathlib.Path) -> Dict[str, Any]:
    """What ran in the node and what it reported (its final diagnostics), for the summary."""
    d = replay.diagnostics
    return {
        'command': ' '.join(shlex.quote(x) for x in replay.node_command),
        **_weights_info(d),
        'preset': values['preset'], 'filter_mode': d.get('filter_mode'), 'filter_mode_requested':
        values['filter_mode'], 'window_mode': values['window_mode'], 'device': d.get('device'),
        'precision': d.get('precision'),
        'processing_size': [values['processing_width'], values['processing_height']],
        'images_in_bag': replay.images_in_bag, 'images_sent': replay.images_sent,
        'image_transport': replay.image_transport, 'image_decode_ms_median': d.get('image_decode_ms_median'),
        'frames_received': d.get('frames_received'), 'frames_processed': d.get('frames_processed'),
        'keyframes': d.get('estimator_keyframes'), 'outputs_published': d.get('outputs_published'),
        'recorded': replay.recorded, 'dropped_total': d.get('dropped_total'),
        'dropped': {k[8:]: v for k, v in d.items() if k.startswith('dropped.')},
        'faults': {k[7:]: v for k, v in d.items() if k.startswith('faults.')},
        'filter_resets': d.get('filter_resets'), 'output_resets': d.get('output_resets'),
        'pose_uncertainty': d.get('pose_uncertainty'),
        'camera_mount': {'source': d.get('extrinsic_source'), 'mount': d.get('extrinsic')},
        'processing_ms_median_all_images': d.get('processing_ms_median'),
        'receipt_to_publish_ms_median': d.get('latency_ms_median'),
        'sent_to_recorded_ms': replay.e2e_ms,
        'pacing': 'lockstep' if replay.lockstep else f'{replay.rate:g}x real time',
        'replay_wall_s': replay.wall_s, 'lockstep_wait_s': replay.wait_s, 'node_start_s': replay.node_start_s,
        'node_stop_s': replay.node_stop_s, 'exit_code': replay.node_exit_code,
        'peak_rss_mib': replay.node_peak_rss_mib, 'log': str(logs / 'node.log')}


def _node_params(items: List[str]):
    """The node's parameters: the demo's, overridden by ``--params`` (a weights path made absolute), and all
    settings validated; raises ValueError or ParameterError naming a bad one."""
    from dpv_sensor import params as P
    user_params = parse_params(items)
    params = dict(DEMO_NODE_PARAMS)
    params.update(user_params)
    if 'weights' in params and params['weights'] and pathlib.Path(params['weights']).exists():
        params['weights'] = str(pathlib.Path(params['weights']).resolve())
    return params, P.validate({**P.defaults(), **params})


def _clear_out(out: pathlib.Path) -> pathlib.Path:
    """The output folder without the previous run's results, with an empty ``logs/``."""
    out.mkdir(parents=True, exist_ok=True)
    for item in OUT_ITEMS:
        p = out / item
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    (out / 'logs').mkdir(parents=True, exist_ok=True)
    return out


def _input_steps(steps: Steps, a, seq_dir: pathlib.Path, input_bag: pathlib.Path, bag_inputs, gt_dir,
                 progress: bool, summary: Dict[str, Any]) -> Dict[str, str]:
    """Steps 1 and 2: render the synthetic scene and write its bag, or (``bag_inputs``: the user's bag's topics,
    as :func:`_bag_inputs` chose them) take the user's bag; returns the topics."""
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.data.topic_detection import describe_choice, image_topic_line, image_transport_of
    if bag_inputs is None:
        frames = a.frames or DEFAULT_FRAMES
        topics = {'image': R.IMAGE_TOPIC, 'camera_info': R.CAMERA_INFO_TOPIC, 'odom': R.ODOM_TOPIC}
        with steps.step('render', f'render synthetic scene seed {a.seed}: {frames} frames at {a.width}x{a.height}'
                        f' -> {_rel(seq_dir)}') as rec:
            seq = render_scene(seq_dir, a.seed, frames, a.width, a.height, progress)
            rec['note'] = f'{len(seq)} frames, {seq.stamp(len(seq) - 1) - seq.stamp(0):.2f} s of camera motion'
        with steps.step('bag', f'write the rosbag2 {_rel(input_bag)} (odometry {ODOM_RATE_HZ:g} Hz)') as rec:
            bs = R.write_sequence_bag(input_bag, seq, odom_rate=ODOM_RATE_HZ, progress=progress)
            rec['note'] = f'{bs.frames} images, {bs.odometry} odometry messages, {bs.duration_s:.2f} s'
        summary['input'] = {'kind': 'synthetic', 'seed': a.seed, 'frames': frames, 'size': [a.width, a.height],
                            'odom_rate_hz': ODOM_RATE_HZ, 'sequence': str(seq_dir), 'bag': str(input_bag)}
        del seq
    else:
        topics, how, bt = bag_inputs
        print(f'demo: input topics: {describe_choice(topics, how)}', flush=True)
        print(f"demo: {image_topic_line(input_bag, bt, topics['image'])}", flush=True)
        steps.skip('render', f'using your bag {_rel(input_bag)}')
        steps.skip('bag', f"{bt[topics['image']][1]} images on {topics['image']}")
        summary['input'] = {'kind': 'bag', 'bag': str(input_bag), 'topics': topics, 'topics_chosen_by': how,
                            'image_transport': image_transport_of(bt, topics['image']),
                            'gt': str(gt_dir) if gt_dir else None}
    return topics


def main(argv: Optional[List[str]] = None) -> int:
    argv = tool_argv(argv)
    a = build_parser().parse_args(argv)
    t_total = time.perf_counter()
    progress = not a.quiet
    from dpv_sensor import params as P
    try:
        params, values = _node_params(a.params)
    except (ValueError, P.ParameterError) as exc:
        print(f'demo: {exc}', file=sys.stderr)
        return 2
    if a.start_timeout < 10:
        print('demo: --start-timeout must be at least 10 s', file=sys.stderr)
        return 2

    user_bag = a.bag is not None
    input_bag = pathlib.Path(a.bag).resolve() if user_bag else None
    bag_inputs = None
    try:        # the arguments are checked before the previous run's results are removed
        if a.gt and not pathlib.Path(a.gt).is_dir():
            raise DemoError(f'{a.gt}: no such ground-truth sequence folder')
        if user_bag:
            bag_inputs = _bag_inputs(a, values, input_bag)
    except Exception as exc:    # DemoError, BagError
        print(f'demo: {exc}', flush=True)
        return 1

    out = _clear_out(pathlib.Path(a.out).resolve())
    logs = out / 'logs'
    domain_id = a.domain_id
    if domain_id is None and os.environ.get('ROS_DOMAIN_ID', '').isdigit():
        domain_id = int(os.environ['ROS_DOMAIN_ID'])
    ros_env = private_ros_env(out, domain_id)

    seq_dir = out / 'sequence'
    input_bag = input_bag if user_bag else out / 'input_bag'
    output_bag = out / 'output_bag'
    gt_dir = pathlib.Path(a.gt).resolve() if a.gt else (None if user_bag else seq_dir)
    steps = Steps(8)
    summary: Dict[str, Any] = {'ok': False, 'out': str(out), 'ros_env': ros_env, 'node_parameters': params,
                               'warnings': []}
    failure = None
    replay = None
    try:
        # ---------------------------------------------------------------- 1 + 2: input
        topics = _input_steps(steps, a, seq_dir, input_bag, bag_inputs, gt_dir, progress, summary)

        # ---------------------------------------------------------------- 3-5: node
        replay = run_node_replay(steps, input_bag, output_bag, topics=topics, params=params, log_dir=logs,
                                 lockstep=not a.realtime, rate=a.rate, start_timeout=a.start_timeout,
                                 frame_timeout=a.frame_timeout, max_images=(a.frames or 0) if user_bag else 0,
                                 progress=progress)
        summary['warnings'] += replay.warnings
        if replay.recorded.get('/depth/image', 0) == 0:
            raise DemoError(f'the node published no depth image (log: {_rel(logs / "node.log")}); '
                            'too few keyframes (the camera must move), or every image was dropped')

        # ---------------------------------------------------------------- 6: evaluate
        offset = _stamp_offset_argv(a, gt_dir, input_bag, topics['image'], summary)
        if gt_dir is not None:
            _evaluate_step(steps, output_bag, gt_dir, out, offset, summary)
        else:   # no ground truth: step 6 is a picture of the outputs instead of a score
            with steps.step('montage', 'no ground truth (--gt): montage of image | depth | confidence -> '
                            f'{_rel(out / "montage.png")}') as rec:
                summary['outputs'] = montage_without_gt(input_bag, output_bag, topics['image'], out / 'montage.png')
                rec['note'] = f"{summary['outputs'].get('outputs')} outputs"

        # ---------------------------------------------------------------- 7: fuse
        if gt_dir is None:
            steps.skip('fuse', 'no ground-truth poses (--gt) to fuse with')
        elif a.no_fusion:
            steps.skip('fuse', '--no-fusion')
        else:
            _fuse_step(steps, a, output_bag, gt_dir, out, offset, summary)
        summary['ok'] = True
    except DemoError as exc:
        failure = str(exc)
    except KeyboardInterrupt:
        failure = 'interrupted'
    except Exception as exc:   # BagError, SequenceFormatError, ... : report it with the traceback in the logs
        import traceback
        (logs / 'demo_error.txt').write_text(traceback.format_exc())
        failure = f'{type(exc).__name__}: {exc} (traceback: {_rel(logs / "demo_error.txt")})'
    summary['failure'] = failure
    summary['steps'] = steps.records
    summary['total_seconds'] = round(time.perf_counter() - t_total, 1)
    if replay is not None:
        summary['node'] = _node_summary(replay, values, logs)
    with open(out / 'summary.json', 'w') as fh:
        from dpv_sensor.evaluation.offline import to_jsonable
        json.dump(to_jsonable(summary), fh, indent=1)
    print_summary(summary)
    return 0 if summary['ok'] else 1


def print_summary(s: Dict[str, Any]) -> None:
    """The short report at the end of the demo."""
    out = pathlib.Path(s['out'])
    print()
    head = 'dpv_sensor demo finished' if s['ok'] else 'dpv_sensor demo FAILED'
    print(f"=== {head} in {s['total_seconds']:.0f} s (output: {_rel(out)}) ===")
    if s.get('failure'):
        print(f"error      {s['failure']}")
    inp = s.get('input') or {}
    if inp.get('kind') == 'synthetic':
        print(f"input      synthetic room, seed {inp['seed']} (never trained on), {inp['frames']} frames "
              f"{inp['size'][0]}x{inp['size'][1]} @ 30 Hz, odometry {inp['odom_rate_hz']:g} Hz (exact poses)")
    elif inp:
        print(f"input      {inp['bag']} (topics {', '.join(t for t in inp['topics'].values() if t)})")
    nd = s.get('node')
    if nd:
        _print_node(nd)
    ev = s.get('evaluation')
    if ev:
        m, ms = ev.get('metric') or {}, ev.get('median_scaled') or {}
        print(f"metrics    {ev.get('num_keyframes')} keyframes, frame means: abs_rel {_fmt(m.get('abs_rel'))}, "
              f"rmse {_fmt(m.get('rmse'), '{:.3f}')} m, d1 {_fmt(m.get('delta1'), '{:.3f}')}, median-scaled "
              f"abs_rel {_fmt(ms.get('abs_rel'))}, coverage {_fmt(ev.get('coverage'), '{:.3f}')}, AUSE "
              f"{_fmt(ev.get('ause'))}")
        for line in ev.get('table') or []:
            print(f'           {line}')
        print(f"           same numbers: {s.get('evaluate_command')}")
    outs = s.get('outputs')
    if outs:
        print(f"outputs    {outs.get('outputs')} depth images, mean coverage "
              f"{_fmt(outs.get('coverage_mean'), '{:.3f}')}, "
              f"mean confidence {_fmt(outs.get('confidence_mean'), '{:.3f}')}, depth p5/p50/p95 "
              f"{outs.get('depth_m_p5_p50_p95') and ' / '.join(f'{x:.2f}' for x in outs['depth_m_p5_p50_p95'])} m")
    fu = s.get('fusion')
    if fu:
        _print_fusion(fu)
    pics = []
    if ev:
        pics += [ev['files'].get('montage'), ev['files'].get('sparsification')]
    if outs and outs.get('montage'):
        pics.append(outs['montage'])
    pics = [_rel(p) for p in pics if p]
    if pics:
        print(f"pictures   {', '.join(pics)}")
    if fu and fu.get('files'):
        print(f"meshes     {', '.join(_rel(p) for p in fu['files'].values())}")
    files = ['summary.json', 'sequence/', 'input_bag/', 'output_bag/', 'logs/node.log']
    print(f"files      {_rel(out)}/{{{','.join(f for f in files if (out / f.rstrip('/')).exists())}}}")
    st = ' | '.join(f"{r['step']} {r['seconds']:.1f} s" + ('' if r['ok'] else ' (failed)')
                    for r in s.get('steps', []) if not r.get('skipped'))
    print(f'steps      {st}')
    for w in s.get('warnings') or []:
        print(f'warning    {w}')



def _print_node(nd: Dict[str, Any]) -> None:
    """The summary's lines on what ran in the node and how it did."""
    if nd.get('measurement_model') == 'network':
        steps = nd.get('weights_steps')
        model = (f"network, preset {nd.get('weights_preset') or nd['preset']}, weights {_rel(nd['weights'])}"
                 + (f' ({steps} training steps)' if steps is not None else ''))
    else:
        model = f"classical NCC plane sweep ({nd.get('measurement_reason')})"
    where = str(nd.get('device')) + (f', {nd["precision"]}' if nd.get('precision') else '')
    print(f'what ran   python -m dpv_sensor.ros.node (its own process, {where}): {model}')
    print(f"           filter {nd.get('filter_mode')}, {nd.get('window_mode')} window, processing "
          f"{nd['processing_size'][0]}x{nd['processing_size'][1]}; {nd.get('images_sent')} images replayed "
          f"({nd['pacing']}), {nd.get('keyframes')} keyframes, {nd.get('outputs_published')} depth outputs "
          f"({nd['recorded'].get('/depth/image', 0)} recorded), {nd.get('dropped_total')} images dropped")
    mount = nd.get('camera_mount') or {}
    if mount.get('source'):
        print(f"           camera mount from {mount['source']}: {mount.get('mount')}")
    e2e = nd.get('sent_to_recorded_ms') or {}
    print(f"node       per depth output: image sent -> depth recorded {_fmt(e2e.get('median'), '{:.0f}')} ms "
          f"median (p95 {_fmt(e2e.get('p95'), '{:.0f}')}), node receipt -> publish "
          f"{nd.get('receipt_to_publish_ms_median')} ms; peak RSS {nd.get('peak_rss_mib')} MiB; "
          f"SIGINT -> exit code {nd.get('exit_code')}")


def _print_fusion(fu: Dict[str, Any]) -> None:
    """The summary's lines on the fused mesh (all pixels, and confident pixels only)."""
    def line(r):
        return (f"accuracy {_fmt(r.get('accuracy_mean'), '{:.3f}')} m (median "
                f"{_fmt(r.get('accuracy_median'), '{:.3f}')}), completeness "
                f"{_fmt(r.get('completeness_mean'), '{:.3f}')} m (median "
                f"{_fmt(r.get('completeness_median'), '{:.3f}')}), "
                f"F-score@{fu['config']['threshold'] * 100:g}cm {_fmt(r.get('fscore'), '{:.3f}')}")
    print(f"fusion     {fu.get('num_frames')} depth maps, voxel {fu['config']['voxel_size']:g} m, vs the GT-depth "
          f"mesh: all pixels {line(fu['unmasked'] or {})}")
    if fu.get('masked'):
        mk = fu['masked']
        kept = _fmt(mk.get('kept_pixel_fraction'), '{:.0%}')
        print(f"           confidence >= {fu['config']['min_confidence']:g} ({kept} of pixels): {line(mk)}")


if __name__ == '__main__':
    sys.exit(main())
