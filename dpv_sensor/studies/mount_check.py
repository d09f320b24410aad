"""The mount check's accuracy on every folder: what ``calibrate_mount`` finds with the folder's own poses and with a
mount error and time offsets put in (the stream table's pose sources), against the truth. Backs docs/robot.md.

    python -m dpv_sensor.studies.mount_check --data DATA_FOLDER [--sources gt mount1 mount2 offset30ms offset-30ms]
        [--out out/mount_check]

A folder's own poses are not a perfect mount and clock either (motion capture calibrated to the camera, or a
dataset's registration): what the check finds with ``gt`` is that folder's own offset, and a put-in error is
judged by the change from it (``found - found on gt`` against the put-in truth), as well as absolutely. Writes
``OUT/mount_check.md`` and ``OUT/mount_check.json``.
"""
from __future__ import annotations

import argparse
import json
import math
import pathlib
from typing import Any, Dict, List, Optional

import numpy as np


def truth(pose_source: str) -> Dict[str, Any]:
    """What was put in: the mount's rotation vector (deg) and translation (mm) as the fit reports them (the true
    camera in the node's camera frame: ``F = X``), and the time offset (ms: the pose t ms after the image is
    ``dt = -t``)."""
    from scipy.spatial.transform import Rotation

    from dpv_sensor.benchmarks.stream_table_inputs import MOUNT_SOURCE, OFFSET_SOURCE, mount_error
    out = {'rotvec_deg': [0.0] * 3, 'translation_mm': [0.0] * 3, 'time_offset_ms': 0.0}
    m = MOUNT_SOURCE.fullmatch(pose_source)
    if m:
        X = mount_error(int(m.group(1)))
        out['rotvec_deg'] = [float(v) for v in np.degrees(Rotation.from_matrix(X[:3, :3]).as_rotvec())]
        out['translation_mm'] = [1e3 * float(v) for v in X[:3, 3]]
    m = OFFSET_SOURCE.fullmatch(pose_source)
    if m:
        out['time_offset_ms'] = -float(m.group(1))
    return out


def run(folder: pathlib.Path, pose_source: str, progress: bool) -> Dict[str, Any]:
    """The tool's pairs and fit on one folder and pose source."""
    from dpv_sensor.benchmarks.stream_table_inputs import odometry_poses
    from dpv_sensor.core.mount_calibration import PoseTrack, fit_mount
    from dpv_sensor.data.sequence import Sequence
    from dpv_sensor.stream.mount_check import fit_dict, sequence_pairs
    seq = Sequence(folder, depth=False)
    poses = odometry_poses(seq, pose_source)
    track = PoseTrack()
    for i, T in enumerate(poses):
        track.add(float(seq.stamp(i)), T)
    fit = fit_mount(sequence_pairs(seq, poses, 2, progress), track)
    return {'sequence': folder.name, 'poses': pose_source, 'truth': truth(pose_source), 'fit': fit_dict(fit)}


def _errors(r: Dict[str, Any], base: Optional[Dict[str, Any]]) -> Dict[str, Optional[float]]:
    """Absolute and relative-to-gt errors: rotation (deg, norm of the rotation-vector difference), translation
    (mm) and time (ms)."""
    f, t = r['fit'], r['truth']
    if not f['ok']:
        return {}
    out = {}
    for label, ref in (('abs', None), ('rel', base)):
        if label == 'rel' and (ref is None or not ref['fit']['ok']):
            continue
        zero_r = np.zeros(3) if ref is None else np.array(ref['fit']['rotvec_deg'])
        zero_t = np.zeros(3) if ref is None else np.array(ref['fit']['translation_mm'])
        zero_dt = 0.0 if ref is None else ref['fit']['time_offset_ms']
        out[f'rot_{label}'] = float(np.linalg.norm(np.array(f['rotvec_deg']) - zero_r - np.array(t['rotvec_deg'])))
        if all(s is not None for s in f['sigma_trans_mm']):
            out[f'trans_{label}'] = float(np.linalg.norm(np.array(f['translation_mm']) - zero_t
                                                         - np.array(t['translation_mm'])))
        out[f'time_{label}'] = abs(f['time_offset_ms'] - zero_dt - t['time_offset_ms'])
    return out


def markdown(rows: List[Dict[str, Any]]) -> str:
    def g(v, fmt):
        return '' if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)
    lines = ['| sequence | poses | pairs | found rotation (deg) | σ (deg) | found shift (mm) | σ (mm) | offset (ms) '
             '| σ | rot err abs / vs gt (deg) | shift err abs / vs gt (mm) | time err abs / vs gt (ms) |',
             '|' + '---|' * 12]
    for r in rows:
        f, e = r['fit'], r['errors']
        if not f['ok']:
            lines.append(f"| {r['sequence']} | {r['poses']} | {f['pairs']} | no estimate: {f['reason']} |" + ' |' * 8)
            continue
        rot = ', '.join(f'{v:+.2f}' for v in f['rotvec_deg'])
        srot = ', '.join(g(v, '.2f') for v in f['sigma_rot_deg'])
        shift = ', '.join(f'{v:+.0f}' for v in f['translation_mm'])
        sshift = ', '.join(g(v, '.0f') for v in f['sigma_trans_mm'])
        lines.append(f"| {r['sequence']} | {r['poses']} | {f['pairs']} | {rot} | {srot} | {shift} | {sshift} | "
                     f"{f['time_offset_ms']:+.1f} | {g(f['sigma_time_ms'], '.1f')} | "
                     f"{g(e.get('rot_abs'), '.2f')} / {g(e.get('rot_rel'), '.2f')} | "
                     f"{g(e.get('trans_abs'), '.0f')} / {g(e.get('trans_rel'), '.0f')} | "
                     f"{g(e.get('time_abs'), '.1f')} / {g(e.get('time_rel'), '.1f')} |")
    return '\n'.join(lines) + '\n'


def main(argv=None) -> int:
    from dpv_sensor.benchmarks.stream_table_inputs import sequence_folders
    ap = argparse.ArgumentParser(prog='studies.mount_check', description=__doc__.split('\n\n')[0])
    ap.add_argument('--data', required=True, help='folder of sequence folders')
    ap.add_argument('--sequences', nargs='*', default=None, help='only these folders')
    ap.add_argument('--sources', nargs='*', default=['gt', 'mount1', 'mount2', 'offset30ms', 'offset-30ms'])
    ap.add_argument('--out', default='out/mount_check')
    ap.add_argument('--quiet', action='store_true')
    a = ap.parse_args(argv)
    folders = [f for f in sequence_folders(pathlib.Path(a.data)) if not a.sequences or f.name in a.sequences]
    rows = []
    for folder in folders:
        base = None
        for src in a.sources:
            r = run(folder, src, not a.quiet)
            if src == 'gt':
                base = r
            r['errors'] = _errors(r, None if src == 'gt' else base)
            rows.append(r)
            print(markdown([r]).splitlines()[-1], flush=True)
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'mount_check.json').write_text(json.dumps(rows, indent=1))
    (out / 'mount_check.md').write_text(markdown(rows))
    print(markdown(rows))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
