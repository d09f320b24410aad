"""``ros2 run dpv_sensor calibrate``: a confidence calibration for a camera, from a recording with depth ground truth.

Examples::

    calibrate DATA/tum_fr1_rpy --out calib/tum                   # a sequence folder (GT depth and poses)
    calibrate synthetic:7:80 --out calib/render                  # a rendered scene
    calibrate --bag run.mcap --gt SEQUENCE_FOLDER --out calib/run  # your recording, replayed through the node
    ros2 run dpv_sensor node --ros-args -p confidence_calibration:=calib/tum/calibration.json

The published confidence is meant to be the probability that the true depth lies within x1.25 of the published
one. On a given camera and kind of scene it can be too high or too low; this tool measures by how much and writes a
map that corrects it. It runs the estimator at the node's defaults (plus --config) over the recording, fits a
monotone map from the confidence to the share of pixels within x1.25 on the first --fit-fraction of the keyframes
(equal-count bins and pool-adjacent-violators: dpv_sensor.evaluation.calibration_fit) and scores it on the rest,
which it never saw. A sequence folder or a synthetic scene runs through the node's own pipeline in this process;
--bag replays the recording through the node process in lockstep, as the demo does (topics found by message type),
and matches its depth images to the GT folder's frames by stamp.

Written to --out: calibration.json (the map, with the settings it was fitted with and what it was fitted on: the
node refuses it with other weights, processing size or depth planes), report.json (ECE, mean confidence, share
and delta1 at the min_confidence thresholds, reliability bins: raw and calibrated, fit part and held-out part) and
reliability.png (the held-out reliability diagram, raw and calibrated). A monotone map keeps the order of the
pixels: it moves the confidence to the measured probability but cannot make it rank errors better. The map is only
as good as the recording is like what the camera will see; fit it on a few minutes of typical motion and scenes.
"""
from __future__ import annotations

import argparse
import logging
import pathlib
import sys
from typing import Any, Dict, List, Optional, Tuple

from dpv_sensor.cli import add_config, tool_argv

# how long the replay waits for the node to start and for each image (s)
REPLAY_TIMEOUT_S = 180.0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='calibrate', description=__doc__.split('\n\n')[0],
                                epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('source', nargs='?', help='sequence folder, or synthetic:SEED[:FRAMES] (not with --bag)')
    p.add_argument('--bag', help='a rosbag2 with camera images, camera_info and odometry, replayed through the node')
    p.add_argument('--gt', help='with --bag: the sequence folder of the recording (GT depth; stamps matched, or the '
                                "bag's first image is frame 0)")
    p.add_argument('--out', default='out/calibration', help='output folder (default out/calibration)')
    p.add_argument('--fit-fraction', type=float, default=None,
                   help='share of the keyframes, the first ones, to fit on; the map is scored on the rest '
                        '(default 0.5)')
    p.add_argument('--bins', type=int, default=None, help='equal-count bins of the fit (default 24)')
    add_config(p, '; the node must then run with the same values')
    p.add_argument('--max-frames', type=int, default=None, help='use at most this many frames (images with --bag)')
    p.add_argument('--width', type=int, default=None, help='synthetic: rendered width (default 320)')
    p.add_argument('--height', type=int, default=None, help='synthetic: rendered height (default 240)')
    p.add_argument('--threads', type=int, default=None, help='torch CPU threads')
    b = p.add_argument_group('--bag')
    b.add_argument('--image-topic', default=None, help='choose among several image topics')
    b.add_argument('--camera-info-topic', default=None, help='choose among several camera_info topics')
    b.add_argument('--odom-topic', default=None, help='choose among several odometry topics')
    b.add_argument('--domain-id', type=int, default=None,
                   help='ROS_DOMAIN_ID of the replay (default: a private random one)')
    p.add_argument('--quiet', action='store_true', help='no progress bars')
    return p


def _check_args(p: argparse.ArgumentParser, a) -> None:
    if (a.source is None) == (a.bag is None):
        p.error('give a SOURCE (sequence folder or synthetic:SEED) or --bag BAG --gt GT')
    if a.bag is not None and a.gt is None:
        p.error('--bag needs --gt (the sequence folder with the ground-truth depth)')
    if a.bins is not None and a.bins < 2:
        p.error('--bins must be at least 2')


def _sequence_records(a, overrides: Dict[str, Any], progress: bool) -> Tuple[list, Any, str]:
    """Run the pipeline over a sequence folder or a rendered scene: (records, status, source)."""
    from dpv_sensor.evaluation import offline as E
    synthetic = a.source.startswith('synthetic:')
    if not synthetic and (a.width or a.height):
        raise ValueError('--width/--height are for synthetic scenes (the estimator resizes to its processing size)')
    seq = E.load_source(a.source, a.width, a.height)
    config, _values = E.build_config(overrides)
    options = E.EvalOptions(max_frames=a.max_frames, progress=progress, consumer_odometry=False).validate()
    records, status = E.run_sequence(seq, config, options, keep_images=False)
    return records, status, a.source if synthetic else str(pathlib.Path(a.source).resolve())


def _bag_records(a, overrides: Dict[str, Any], out: pathlib.Path, progress: bool) -> Tuple[list, Any, str]:
    """Replay the bag through the node at its defaults plus ``overrides`` and match its outputs to the GT frames:
    (records, the status of an estimator built with the same settings, source)."""
    from dpv_sensor.client import replay as D
    from dpv_sensor.client.ros_io import private_ros_env
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.evaluation import offline as E
    from dpv_sensor.stream.estimator import Estimator
    bag, gt = pathlib.Path(a.bag), pathlib.Path(a.gt)
    if not bag.exists():
        raise ValueError(f'{bag}: no such bag')
    if not gt.is_dir():
        raise ValueError(f'{gt} is not a sequence folder')
    config, values = E.build_config(overrides)
    status = Estimator(config).status           # what the node builds from the same settings
    topics, _how = D.bag_input_topics(R.bag_topics(bag), values, image=a.image_topic,
                                      camera_info=a.camera_info_topic, odom=a.odom_topic)
    private_ros_env(out, a.domain_id)
    work = out / 'replay'
    (work / 'logs').mkdir(parents=True, exist_ok=True)
    D.run_node_replay(D.Steps(3), bag, work / 'output_bag', topics=topics, params={**D.DEMO_NODE_PARAMS, **overrides},
                      log_dir=work / 'logs', lockstep=True, rate=1.0, start_timeout=REPLAY_TIMEOUT_S,
                      frame_timeout=REPLAY_TIMEOUT_S, max_images=a.max_frames or 0, progress=progress)
    offset = E.gt_stamp_offset(E.first_image_stamp(bag, topics['image']), E.load_sequence(gt))
    records, info = E.records_from_bag(work / 'output_bag', gt, stamp_offset=offset)
    if not records:
        raise ValueError(f'no depth image of the replay matched a frame of {gt} ({info})')
    return records, status, f'{bag.resolve()} (GT {gt.resolve()})'


def _fmt(x: Optional[float], spec: str = '.3f') -> str:
    return '-' if x is None or x != x else format(x, spec)


def report_table(report: Dict[str, Any]) -> str:
    """The fit and held-out parts as a markdown table: ECE, mean confidence against the share within x1.25, and
    the share of pixels at a confidence >= 0.9 with their delta1, raw -> calibrated."""
    lines = ['| part | keyframes (frames) | pixels | ECE raw -> calibrated | mean conf raw -> calibrated (delta1) '
             '| conf >= 0.9 raw -> calibrated: share (delta1) |', '|---|---|---|---|---|---|']
    for name in ('fit', 'held_out'):
        part = report[name]
        raw, cal = part['raw'], part['calibrated']
        k_raw, k_cal = raw['kept']['0.9'], cal['kept']['0.9']
        lines.append(
            f"| {name.replace('_', '-')} | {part['keyframes']} ({part['frames'][0]}-{part['frames'][1]}) "
            f"| {part['pixels'] / 1e6:.2f} M | {_fmt(raw['ece'])} -> {_fmt(cal['ece'])} "
            f"| {_fmt(raw['mean_confidence'])} -> {_fmt(cal['mean_confidence'])} ({_fmt(raw['hit_rate'])}) "
            f"| {_fmt(k_raw['share'], '.1%')} ({_fmt(k_raw['delta1'], '.2f')}) -> "
            f"{_fmt(k_cal['share'], '.1%')} ({_fmt(k_cal['delta1'], '.2f')}) |")
    return '\n'.join(lines)


def run(a) -> Dict[str, Any]:
    """Run, fit, score and write; returns the report (with ``files``)."""
    from dpv_sensor.evaluation import calibration_fit as F
    from dpv_sensor.evaluation import offline as E
    from dpv_sensor.stream.estimator_config import calibration_signature
    out = pathlib.Path(a.out)
    overrides = E.parse_overrides(a.config)
    if 'confidence_calibration' in overrides:
        raise ValueError('confidence_calibration: the calibration is fitted on the raw confidence; leave it unset')
    E.build_config(overrides)                   # a bad value stops here, before the long run
    if a.threads:
        import torch
        torch.set_num_threads(a.threads)
    progress = not a.quiet
    if a.bag is not None:
        records, status, source = _bag_records(a, overrides, out, progress)
    else:
        records, status, source = _sequence_records(a, overrides, progress)
    lo, hi = E.depth_limits(E.EvalOptions(), status)
    fit_fraction = F.FIT_FRACTION if a.fit_fraction is None else a.fit_fraction
    calibration, report = F.calibrate_records(
        records, calibration_signature(status), min_depth=lo, max_depth=hi, fit_fraction=fit_fraction,
        bins=F.FIT_BINS if a.bins is None else a.bins, source=source, extra={'parameters': overrides})
    name = pathlib.Path(a.source).name if a.source else pathlib.Path(a.bag).name
    report['files'] = {k: str(v) for k, v in F.write_calibration(out, calibration, report, title=name).items()}
    return report


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    a = parser.parse_args(tool_argv(argv))
    _check_args(parser, a)
    logging.basicConfig(level=logging.WARNING, format='%(name)s: %(message)s')
    try:
        report = run(a)
    except (ValueError, FileNotFoundError) as exc:       # ParameterError and CalibrationError are ValueErrors
        print(f'calibrate: {exc}', file=sys.stderr)
        return 2
    except Exception as exc:
        if type(exc).__name__ in ('BagError', 'SequenceFormatError', 'CheckpointError'):
            print(f'calibrate: {exc}', file=sys.stderr)
            return 2
        if type(exc).__name__ == 'ReplayError':
            print(f'calibrate: {exc}', file=sys.stderr)
            return 1
        raise
    print(report_table(report))
    files = report['files']
    print(f"\nwritten: {files['calibration']}, {files['report']}, {files['reliability']}")
    print('use it: ros2 run dpv_sensor node --ros-args -p confidence_calibration:='
          f"{pathlib.Path(files['calibration']).resolve()}")
    return 0


if __name__ == '__main__':
    sys.exit(main())
