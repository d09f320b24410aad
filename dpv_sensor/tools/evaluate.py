"""``ros2 run dpv_sensor evaluate``: score the virtual depth camera against ground truth.

Examples::

    # run the estimator over a sequence folder (GT poses) and score every keyframe
    evaluate sequence DATA/sun3d_3dmatch_frag1 --out eval/frag1
    # node parameters with --config, a comparison table with --compare (cartesian product)
    evaluate sequence DATA/tartanair_hospital --config measurement=classical \\
        --compare filter_mode=none,global,knet --out eval/filters
    evaluate sequence synthetic:3:40 --width 160 --height 120 --compare pose_source=gt,noisy --out eval/poses
    # outputs recorded from the node (a rosbag2), or a folder written by `bag export`
    evaluate bag run.mcap --gt DATA/sun3d_3dmatch_frag1 --out eval/bag
    evaluate export exported/ --gt DATA/sun3d_3dmatch_frag1 --out eval/export

(DATA: the shared development data folder, or any sequence folders.) SOURCE for ``sequence`` is a sequence
folder or ``synthetic:SEED[:FRAMES]`` (the synthetic renderer, rendered at --width x --height, default
320x240, 60 frames).

Depth range: GT pixels outside [--min-depth, --max-depth] are not scored and predictions are clipped to
that range. The default is the estimator's depth planes [d_min, d_max] (for ``bag``/``export``: every
valid GT pixel). Resizing: --width/--height resize the input sequence first (images area-averaged, GT
depth nearest, K scaled); the estimator then works at processing_width x processing_height and, with
output_resolution=input (default), scoring happens at the (resized) input size; with
output_resolution=processing at the processing size (GT resized with nearest neighbour).

Writes to --out: frames.csv, summary.json, montage.png, sparsification.png (per configuration, in
numbered sub-folders when comparing, plus compare.md / compare.json / compare_sparsification.png) and
prints a short markdown table. Headline numbers are means over keyframes; ``ms`` = per-frame median-scaled.

Consumer check (summary.json ``consumer_odometry``, columns ``odo t×`` / ``odo r×``): Open3D's RGB-D odometry
between consecutive outputs, on the predicted depth and on the GT depth of the same frames (same colour images),
scored against the GT relative poses; the ratio of the median translation / rotation errors (hybrid Jacobian,
Open3D's default; the photometric-only 'color' Jacobian is reported too). ``--no-consumer-odometry`` skips it.
"""
from __future__ import annotations

import argparse
import json
import logging
import pathlib
import sys
from typing import List, Optional

from dpv_sensor.cli import add_config
from dpv_sensor.cli import tool_argv


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument('--out', required=True, help='output directory (created)')
    p.add_argument('--min-depth', type=float, default=None, help='smallest GT depth scored (m)')
    p.add_argument('--max-depth', type=float, default=None, help='largest GT depth scored (m), e.g. 10')
    p.add_argument('--montage-frames', type=int, default=4, help='rows of montage.png')
    p.add_argument('--occlusion-tol', type=float, default=0.05,
                   help='relative GT agreement for "visible in both frames" (temporal consistency)')
    p.add_argument('--no-consumer-odometry', action='store_true',
                   help='skip the consumer check (Open3D RGB-D odometry between consecutive outputs on the predicted '
                        'and on the GT depth; columns odo t× / odo r× = ratio of the median translation / rotation '
                        'error)')
    p.add_argument('--quiet', action='store_true', help='no progress bars')


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='evaluate', description=__doc__.split('\n\n')[0],
                                epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest='command', required=True)

    s = sub.add_parser('sequence', help='run the estimator over a posed RGB-D sequence and score it')
    s.add_argument('source', help='sequence folder, or synthetic:SEED[:FRAMES]')
    add_config(s, '; also pose_source=gt|noisy')
    s.add_argument('--compare', nargs='*', default=[], metavar='KEY=V1,V2',
                   help='evaluate every combination of these values, e.g. filter_mode=none,global,knet '
                        'measurement=classical,network preset=lite,paper pose_source=gt,noisy')
    s.add_argument('--width', type=int, default=None, help='resize the input sequence to this width first')
    s.add_argument('--height', type=int, default=None, help='... and this height')
    s.add_argument('--start', type=int, default=0, help='first frame')
    s.add_argument('--max-frames', type=int, default=None, help='number of frames used')
    s.add_argument('--pose-source', choices=('gt', 'noisy'), default='gt',
                   help='poses fed to the estimator: GT, or GT with odometry-like drift')
    s.add_argument('--pose-noise', type=float, nargs=2, default=(0.03, 0.5), metavar=('REL_T', 'ROT_DEG'),
                   help='noisy poses: relative translation noise per step and rotation noise (deg) per step')
    s.add_argument('--seed', type=int, default=0, help='seed of the pose noise')
    s.add_argument('--threads', type=int, default=None, help='torch CPU threads')
    _add_common(s)

    b = sub.add_parser('bag', help='score depth outputs recorded in a rosbag2 against a GT sequence')
    b.add_argument('bag', help='bag directory or file')
    b.add_argument('--gt', required=True, help='GT sequence folder the bag was made from')
    b.add_argument('--depth-topic', default=None)
    b.add_argument('--confidence-topic', default=None)
    b.add_argument('--info-topic', default=None)
    b.add_argument('--image-topic', default=None,
                   help='camera images for --stamp-offset auto (default: the only sensor_msgs/Image topic that is '
                        'not a node output, else the only image_transport CompressedImage topic)')
    b.add_argument('--stamp-offset', default='auto',
                   help="seconds subtracted from the bag stamps before matching, or 'auto' (the bag's first "
                        "camera image is GT frame 0)")
    b.add_argument('--tolerance', type=float, default=1e-3, help='stamp matching tolerance (s)')
    _add_common(b)

    e = sub.add_parser('export', help='score a folder written by `bag export` against a GT sequence')
    e.add_argument('folder')
    e.add_argument('--gt', required=True, help='GT sequence folder')
    e.add_argument('--stamp-offset', type=float, default=0.0)
    e.add_argument('--tolerance', type=float, default=1e-3)
    _add_common(e)
    return p


def _print_table(rows) -> None:
    from dpv_sensor.evaluation.offline import markdown_table
    print(markdown_table(rows))


def main(argv: Optional[List[str]] = None) -> int:
    argv = tool_argv(argv)
    a = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format='%(name)s: %(message)s')
    from dpv_sensor.evaluation import offline as E
    from dpv_sensor.data.bag_export import export_topics_line
    out = pathlib.Path(a.out)
    try:
        if a.command == 'sequence':
            if a.threads:
                import torch
                torch.set_num_threads(a.threads)
            overrides = E.parse_overrides(a.config)
            variants = E.variants_from_specs(a.compare)
            synthetic = a.source.startswith('synthetic:')
            options = E.EvalOptions(
                min_depth=a.min_depth, max_depth=a.max_depth,
                width=None if synthetic else a.width, height=None if synthetic else a.height,
                start=a.start, max_frames=a.max_frames, pose_source=a.pose_source,
                pose_noise=tuple(a.pose_noise), seed=a.seed, montage_frames=a.montage_frames,
                occlusion_tol=a.occlusion_tol, progress=not a.quiet,
                consumer_odometry=not a.no_consumer_odometry).validate()
            for v in variants:                   # fail early on a bad parameter value
                E.build_config({**overrides, **v})
            seq = E.load_source(a.source, a.width, a.height)
            if a.compare:
                result = E.compare(seq, overrides, variants, out, options)
                print(result['markdown'])
                print(f'\nwritten: {out / "compare.md"}, {out / "compare.json"}')
            else:
                summary = E.evaluate_sequence(seq, overrides, out, options, name=pathlib.Path(a.source).name)
                _print_table([E.table_row('config', summary)])
                print(E.consumer_odometry_text(summary), end='')
                print(f'\nwritten: {out}/summary.json, frames.csv, montage.png, sparsification.png')
        else:
            options = E.EvalOptions(min_depth=a.min_depth, max_depth=a.max_depth, montage_frames=a.montage_frames,
                                    occlusion_tol=a.occlusion_tol, progress=not a.quiet,
                                    consumer_odometry=not a.no_consumer_odometry).validate()
            if a.command == 'bag':
                offset = a.stamp_offset if a.stamp_offset == 'auto' else float(a.stamp_offset)
                records, info = E.records_from_bag(a.bag, a.gt, depth_topic=a.depth_topic,
                                                   confidence_topic=a.confidence_topic, info_topic=a.info_topic,
                                                   image_topic=a.image_topic, stamp_offset=offset,
                                                   tolerance=a.tolerance)
                source = a.bag
                print(export_topics_line(info), flush=True)
            else:
                records, info = E.records_from_export(a.folder, a.gt, stamp_offset=a.stamp_offset,
                                                      tolerance=a.tolerance)
                source = a.folder
            if not records:
                print(f'evaluate: no depth image matched a GT frame ({json.dumps(info)}); check --stamp-offset',
                      file=sys.stderr)
                return 1
            summary = E.evaluate_records(records, out, options, source=str(source), extra={'input': info},
                                         name=pathlib.Path(source).name)
            _print_table([E.table_row(pathlib.Path(source).name, summary)])
            print(E.consumer_odometry_text(summary), end='')
            print(f'\nmatched {info["matched"]} depth images ({info["unmatched"]} unmatched); written: {out}')
    except (ValueError, FileNotFoundError) as exc:
        print(f'evaluate: {exc}', file=sys.stderr)
        return 2
    except Exception as exc:  # BagError, SequenceFormatError, ParameterError ...
        if type(exc).__name__ in ('BagError', 'SequenceFormatError', 'ParameterError', 'CheckpointError'):
            print(f'evaluate: {exc}', file=sys.stderr)
            return 2
        raise
    return 0


if __name__ == '__main__':
    sys.exit(main())
