"""``ros2 run dpv_sensor calibrate_mount``: the camera mount and the camera-odometry time offset a recording's images
say, and the parameter line to set.

Examples::

    calibrate_mount run.mcap                                    # a rosbag2: images, camera_info, odometry
    calibrate_mount run.mcap --T-base-camera 0.1 0 0.2 0 0 0 1  # the mount the node is given
    calibrate_mount DATA/tum_fr1_rpy                            # a sequence folder (images, poses.txt, K.txt)
    calibrate_mount DATA/tum_fr1_rpy --simulate mount1          # the same with a mount error put in on purpose

The node composes each image's odometry pose with the camera mount (``T_base_camera`` or TF) and pairs it with the
odometry at the image's stamp. This tool reads the recording as the node would (a bag's odometry interpolated at
each image stamp and composed with ``--T-base-camera``, else the bag's /tf_static, else the identity; a folder's
poses.txt), pairs each image with the next one that turned 5 deg, moved 5 cm or is 5 frames on (every
``--every`` frames, as the keyframes of the node's window are paired), matches each pair with the window's dense
flow (kept where the flow back returns within half a pixel), and fits the mount's rotation and translation and the
time offset that best explain every match with the odometry's motion (dpv_sensor.core.mount_calibration; the same
fit the node's ``mount_check`` runs live). It prints each with its sigma, whether it is confidently off, and the
``T_base_camera`` to set. The rotation needs the camera to turn about two axes or to move sideways; the translation
needs it to turn while it moves; the time offset needs the motion to speed up and slow down: a sigma says how well
each was seen (a few minutes of handheld or robot motion usually see all three).

``--simulate``: the folder's or bag's poses corrupted as the stream table's pose sources are (``mount<k>``: a mount
1-3 deg and 2-5 cm off; ``offset<ms>ms``: the pose ms after each image's stamp), to see what the check finds on a
recording you trust. ``--json``: the estimate as JSON. Exit code 0 with an estimate, 1 when the recording cannot
give one (the reason is printed), 2 for bad input.
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
from typing import Any, Dict, List, Optional

import numpy as np

from dpv_sensor.cli import tool_argv

EXIT_OK, EXIT_NO_ESTIMATE, EXIT_BAD_INPUT = 0, 1, 2


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='calibrate_mount', description=__doc__.split('\n\n')[0],
                                epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('source', help='a rosbag2 (folder or .mcap/.db3) or a sequence folder (images/, poses.txt, K.txt)')
    p.add_argument('--T-base-camera', type=float, nargs=7, default=None,
                   metavar=('X', 'Y', 'Z', 'QX', 'QY', 'QZ', 'QW'),
                   help="the mount the node is given (a bag's /tf_static, else the identity, when not given)")
    p.add_argument('--image-topic', default=None, help='a bag: the image topic (found by type when there is one)')
    p.add_argument('--odom-topic', default=None, help='a bag: the odometry topic (found by type when there is one)')
    p.add_argument('--every', type=int, default=2, help='start a pair every this many frames (default 2)')
    p.add_argument('--max-offset-ms', type=float, default=100.0,
                   help='time offsets searched, +- (ms; default 100; 0: not fitted)')
    p.add_argument('--simulate', default=None, metavar='SOURCE',
                   help="corrupt the poses first: mount<k> or offset<ms>ms (the stream table's pose sources)")
    p.add_argument('--json', default=None, metavar='FILE', help='also write the estimate as JSON')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    return p


def _load(a, ap: argparse.ArgumentParser):
    from dpv_sensor.data.recording import load_recording
    from dpv_sensor.data.sequence import SequenceFormatError
    mount = None
    if a.T_base_camera is not None:
        from dpv_sensor.stream.pose_buffer import pose7_to_matrix
        q = np.asarray(a.T_base_camera[3:])
        if abs(float(np.linalg.norm(q)) - 1.0) > 1e-3:
            ap.error(f'--T-base-camera quaternion {q.tolist()} is not unit length')
        mount = pose7_to_matrix(a.T_base_camera)
    try:
        rec = load_recording(a.source, image_topic=a.image_topic, odom_topic=a.odom_topic,
                             T_base_camera=None if mount is None else a.T_base_camera)
    except (FileNotFoundError, SequenceFormatError) as exc:
        raise SystemExit(f'calibrate_mount: {exc}') from exc
    return rec, (np.eye(4) if mount is None else mount)


def report(fit, mount_44: np.ndarray) -> Dict[str, Any]:
    """The estimate as JSON-ready numbers, with the mount to set and whether each part is confidently off."""
    from dpv_sensor.core.mount_calibration import corrected_mount
    from dpv_sensor.stream.mount_check import MountCheck, MountCheckConfig, fit_dict
    from dpv_sensor.stream.pose_buffer import matrix_to_pose7
    out = {'fit': fit_dict(fit)}
    if fit.ok:
        judge = MountCheck(MountCheckConfig(background=False), logger=_Silent())
        judge._judge(fit)
        out.update(rotation_off=judge.status.rotation_off, translation_off=judge.status.translation_off,
                   offset_off=judge.status.offset_off,
                   mount_in_use=[float(v) for v in matrix_to_pose7(mount_44)],
                   mount_estimate=[float(v) for v in matrix_to_pose7(corrected_mount(mount_44, fit))])
    return out


class _Silent:
    def warning(self, *_args, **_kw):
        pass


def _print(rep: Dict[str, Any], fit) -> None:
    from dpv_sensor.stream.mount_check import mount_text, offset_text
    print(f'{fit.pairs} image pairs, {fit.matches} matches (median distance {fit.median_px:.2f} px)')
    print(('OFF: ' if rep['rotation_off'] or rep['translation_off'] else 'ok:  ') + mount_text(fit))
    if math.isfinite(fit.sigma_time_s):
        print(('OFF: ' if rep['offset_off'] else 'ok:  ') + offset_text(fit))
    v = ', '.join(f'{x:.6g}' for x in rep['mount_estimate'])
    print(f'the mount the images say (odometry child frame -> camera): -p T_base_camera:="[{v}]"')
    if rep['offset_off']:
        print(f"the odometry's stamps: -p odom_time_offset_ms:={1e3 * fit.time_offset_s:.1f}")


def main(argv: Optional[List[str]] = None) -> int:
    ap = build_parser()
    a = ap.parse_args(tool_argv(argv))
    from dpv_sensor.core.mount_calibration import MountFitConfig, PoseTrack, fit_mount
    from dpv_sensor.stream.mount_check import sequence_pairs
    rec, mount = _load(a, ap)
    seq = rec.sequence
    poses = [np.asarray(seq.pose(i), np.float64) for i in range(len(seq))]
    if a.simulate:
        from dpv_sensor.benchmarks.stream_table_inputs import odometry_poses
        try:
            poses = odometry_poses(seq, a.simulate)
        except ValueError as exc:
            ap.error(str(exc))
    track = PoseTrack()
    for i, T in enumerate(poses):
        track.add(float(seq.stamp(i)), T)
    pairs = sequence_pairs(seq, poses, a.every, not a.quiet)
    fit = fit_mount(pairs, track, MountFitConfig(max_offset_s=a.max_offset_ms / 1000.0))
    if not fit.ok:
        print(f'calibrate_mount: no estimate: {fit.reason}', file=sys.stderr)
        return EXIT_NO_ESTIMATE
    rep = report(fit, mount)
    rep['source'] = {k: v for k, v in rec.source.items() if isinstance(v, (str, int, float, bool, list))}
    rep['simulate'] = a.simulate
    _print(rep, fit)
    if a.json:
        pathlib.Path(a.json).write_text(json.dumps(rep, indent=1))
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
