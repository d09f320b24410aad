"""``ros2 run dpv_sensor fuse``: TSDF-fuse the virtual depth camera's keyframes into a mesh and score it.

Examples::

    fuse sequence DATA/sun3d_3dmatch_frag1 --out fuse/frag1 --voxel 0.02 --min-confidence 0.5
    fuse sequence synthetic:3:60 --width 160 --height 120 --config measurement=classical --out fuse/syn
    fuse bag run.mcap --gt DATA/sun3d_3dmatch_frag1 --out fuse/bag

Every keyframe depth map is integrated (Open3D TSDF, marching cubes) twice - all pixels, and only pixels
with confidence >= --min-confidence - and the GT depth maps of the same frames once, all with the same
poses (--poses gt, default: GT poses, so only the depth differs; or the poses the estimator used). Written
to --out: mesh_pred.ply, mesh_pred_masked.ply, mesh_gt.ply and fusion.json with accuracy (predicted
vertices -> GT surface: mean / median distance, fraction within --threshold) and completeness (GT vertices
-> predicted surface), and the F-score, for both predicted meshes. --max-depth drops depths beyond it before
integration (predicted and GT alike). SOURCE, --config, --width/--height as for ``evaluate sequence``.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
from typing import List, Optional

from dpv_sensor.cli import add_config
from dpv_sensor.cli import tool_argv


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='fuse', description=__doc__.split('\n\n')[0],
                                epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest='command', required=True)

    def common(q):
        q.add_argument('--out', required=True, help='output directory')
        q.add_argument('--voxel', type=float, default=0.02, help='TSDF voxel size (m)')
        q.add_argument('--trunc', type=float, default=None, help='TSDF truncation (m; default 4 voxels)')
        q.add_argument('--min-confidence', type=float, default=0.5, help='confidence mask of the masked mesh')
        q.add_argument('--max-depth', type=float, default=None, help='depths beyond this are not integrated (m)')
        q.add_argument('--threshold', type=float, default=0.05, help='distance for the within-fractions (m)')
        q.add_argument('--poses', choices=('gt', 'estimated'), default='gt', help='poses used for both meshes')
        q.add_argument('--no-color', action='store_true', help='do not colour the meshes')
        q.add_argument('--consumer-odometry', action='store_true',
                       help='also run the consumer check of `evaluate` (Open3D RGB-D odometry between consecutive '
                            'depth maps, predicted vs GT depth) into fusion.json')
        q.add_argument('--quiet', action='store_true', help='no progress bars')

    s = sub.add_parser('sequence', help='run the estimator over a sequence, then fuse')
    s.add_argument('source', help='sequence folder, or synthetic:SEED[:FRAMES]')
    add_config(s)
    s.add_argument('--width', type=int, default=None)
    s.add_argument('--height', type=int, default=None)
    s.add_argument('--start', type=int, default=0)
    s.add_argument('--max-frames', type=int, default=None)
    s.add_argument('--threads', type=int, default=None, help='torch CPU threads')
    common(s)

    b = sub.add_parser('bag', help='fuse depth outputs recorded in a rosbag2 (GT poses and depth from --gt)')
    b.add_argument('bag')
    b.add_argument('--gt', required=True)
    b.add_argument('--stamp-offset', default='auto')
    b.add_argument('--image-topic', default=None, help='camera images for --stamp-offset auto (see evaluate)')
    common(b)

    e = sub.add_parser('export', help='fuse a folder written by `bag export` (GT from --gt)')
    e.add_argument('folder')
    e.add_argument('--gt', required=True)
    e.add_argument('--stamp-offset', type=float, default=0.0)
    common(e)
    return p


def _print_report(report) -> None:
    rows = [('unmasked', report['unmasked'])]
    if report.get('masked'):
        rows.append((f"conf >= {report['config']['min_confidence']:g}", report['masked']))
    print('| mesh | accuracy mean (m) | accuracy within | completeness mean (m) | completeness within '
          '| F-score | vertices |')
    print('|---|---|---|---|---|---|---|')
    for name, r in rows:
        print(f"| {name} | {r['accuracy_mean']:.4f} | {r['accuracy_within']:.3f} | {r['completeness_mean']:.4f} | "
              f"{r['completeness_within']:.3f} | {r['fscore']:.3f} | {r['num_vertices']} |")


def main(argv: Optional[List[str]] = None) -> int:
    argv = tool_argv(argv)
    a = build_parser().parse_args(argv)
    from dpv_sensor.evaluation import offline as E
    from dpv_sensor.evaluation import fusion as F
    from dpv_sensor.data.bag_export import export_topics_line
    from dpv_sensor.data.rosbag_io import BagError
    out = pathlib.Path(a.out)
    try:
        if a.command == 'sequence':
            if a.threads:
                import torch
                torch.set_num_threads(a.threads)
            overrides = E.parse_overrides(a.config)
            synthetic = a.source.startswith('synthetic:')
            options = E.EvalOptions(width=None if synthetic else a.width, height=None if synthetic else a.height,
                                    start=a.start, max_frames=a.max_frames, progress=not a.quiet,
                                    pose_source=overrides.get('pose_source', 'gt')).validate()
            config, values = E.build_config(overrides)
            records, status = E.run_sequence(E.load_source(a.source, a.width, a.height), config, options)
            info = {'source': a.source, 'overrides': overrides, 'estimator_status': E.status_json(status)}
        elif a.command == 'bag':
            offset = a.stamp_offset if a.stamp_offset == 'auto' else float(a.stamp_offset)
            records, info = E.records_from_bag(a.bag, a.gt, image_topic=a.image_topic, stamp_offset=offset)
            print(export_topics_line(info), flush=True)
        else:
            records, info = E.records_from_export(a.folder, a.gt, stamp_offset=a.stamp_offset)
        if not records:
            print('fuse: no depth maps to fuse', file=sys.stderr)
            return 1
        cfg = F.FusionConfig(voxel_size=a.voxel, sdf_trunc=a.trunc, max_depth=a.max_depth,
                             min_confidence=a.min_confidence, threshold=a.threshold, use_color=not a.no_color)
        pred, gt = F.frames_from_records(records, poses=a.poses)
        report = F.fusion_report(pred, gt, cfg, out_dir=out, progress=not a.quiet)
        report['input'] = E.to_jsonable(info)
        if a.consumer_odometry:
            report['consumer_odometry'] = E.consumer_odometry(records, progress=not a.quiet)
        with open(out / 'fusion.json', 'w') as f:
            json.dump(E.to_jsonable(report), f, indent=1)
    except (ValueError, FileNotFoundError, ImportError, BagError) as exc:
        print(f'fuse: {exc}', file=sys.stderr)
        return 2
    _print_report(report)
    if 'consumer_odometry' in report:
        print(E.consumer_odometry_text(report), end='')
    print(f'\n{len(pred)} depth maps fused; written: {out}/mesh_pred.ply, mesh_pred_masked.ply, mesh_gt.ply, '
          'fusion.json')
    return 0


if __name__ == '__main__':
    sys.exit(main())
