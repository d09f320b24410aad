"""The stream table's inputs: the pose sources (the odometry each run's bag is written with, what was done to the GT
poses), the sequences (the data folder's, the rendered held-out seeds) and the names runs are cached and tabled
under.

Pose sources: ``gt``, ``offset<t>ms``, ``mount<k>``, ``noisy<k>``, ``noisy<k>cov`` and ``noisy<k>twist`` (the
stream_table module's docstring describes each): odometry_poses, odometry_variance, odometry_twist_variance,
time_shifted_poses, mount_error, noise_description, PosedView (a sequence with its poses replaced). Sequences:
sequence_folders, rendered_sequence. Names: params_tag, run_key.
"""
from __future__ import annotations

import pathlib
import re
import shutil
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

# odometry-like noise of the table's noisy rows: translation error per step (fraction of the step), rotation error
# per frame (deg)
NOISE_TRANS_REL = 0.02
NOISE_ROT_DEG = 0.1
RENDER_FRAMES = 60
RENDER_SIZE = (320, 240)
# the time-offset pose source: the odometry a camera image is paired with describes the pose this much later (ms)
TIME_OFFSET_MS = 10.0
# the constant pose covariance of the noisy<k>twist sources (per axis: m^2, rad^2), diff_drive_controller's example
# pose_covariance_diagonal: says nothing about the motion between two poses, the twist covariance does
CONSTANT_POSE_VARIANCE = (1e-3, 1e-3)


class PosedView:
    """A sequence with its poses replaced (the odometry a bag is written with); everything else is the sequence's."""

    def __init__(self, seq, poses):
        self._seq = seq
        self._poses = [np.asarray(T, np.float64) for T in poses]
        if len(self._poses) != len(seq):
            raise ValueError(f'{len(self._poses)} poses for a sequence of {len(seq)} frames')

    def __len__(self):
        return len(self._seq)

    def pose(self, i):
        return self._poses[i]

    def __getattr__(self, name):
        return getattr(self._seq, name)


NOISY_SOURCE = re.compile(r'noisy(\d+)(cov|twist)?')
OFFSET_SOURCE = re.compile(r'offset(-?\d+(?:\.\d+)?)ms')
MOUNT_SOURCE = re.compile(r'mount(\d+)')
# the mount-error pose sources: a rotation of this many degrees (uniform) about an axis tilted at random, and a
# translation of this many metres (uniform) in a random direction
MOUNT_ERROR_DEG = (1.0, 3.0)
MOUNT_ERROR_M = (0.02, 0.05)


def mount_error(seed: int) -> np.ndarray:
    """The true mount ``X`` (4x4, the camera's pose in the odometry's frame) of pose source ``mount<seed>``: the
    node is told the identity, so the node's camera pose is the true one times ``X^-1``. Seeded: the same seed is
    the same mount on every sequence."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(1000 + int(seed))
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    X = np.eye(4)
    X[:3, :3] = Rotation.from_rotvec(np.radians(rng.uniform(*MOUNT_ERROR_DEG)) * axis / np.linalg.norm(axis)
                                     ).as_matrix()
    X[:3, 3] = rng.uniform(*MOUNT_ERROR_M) * direction / np.linalg.norm(direction)
    return X


def odometry_poses(seq, pose_source: str) -> List[np.ndarray]:
    """The poses written as odometry for a pose source: 'gt', 'noisy<seed>', 'noisy<seed>cov' or 'noisy<seed>twist'
    (corrupt_trajectory with the table's noise, seeded), 'offset<ms>ms' (the GT pose ``ms`` milliseconds after each
    image's stamp, SLERP + linear between frames, ``ms`` negative: before: a camera-odometry time offset) or
    'mount<seed>' (the GT pose times ``mount_error(seed)^-1``: a mount nobody calibrated)."""
    gt = [np.asarray(seq.pose(i), np.float64) for i in range(len(seq))]
    if pose_source == 'gt':
        return gt
    m = OFFSET_SOURCE.fullmatch(pose_source)
    if m:
        return time_shifted_poses(seq, gt, float(m.group(1)) / 1000.0)
    m = MOUNT_SOURCE.fullmatch(pose_source)
    if m:
        X_inv = np.linalg.inv(mount_error(int(m.group(1))))
        return [T @ X_inv for T in gt]
    m = NOISY_SOURCE.fullmatch(pose_source)
    if not m:
        raise ValueError(f'pose source {pose_source!r} is neither gt, offset<ms>ms, mount<seed>, noisy<seed>, '
                         'noisy<seed>cov nor noisy<seed>twist')
    from dpv_sensor.data.trajectory import corrupt_trajectory
    return corrupt_trajectory(gt, trans_noise_rel=NOISE_TRANS_REL, rot_noise_deg=NOISE_ROT_DEG, seed=int(m.group(1)))


def odometry_variance(seq, pose_source: str) -> Optional[np.ndarray]:
    """The pose variance a pose source's odometry publishes (rows per frame: position m^2, rotation rad^2 per
    axis): the noise model's accumulated variance for 'noisy<seed>cov', CONSTANT_POSE_VARIANCE for
    'noisy<seed>twist', None (covariance not filled) otherwise."""
    m = NOISY_SOURCE.fullmatch(pose_source)
    if not (m and m.group(2)):
        return None
    if m.group(2) == 'twist':
        return np.tile(np.asarray(CONSTANT_POSE_VARIANCE, np.float64), (len(seq), 1))
    from dpv_sensor.data.trajectory import corruption_variance
    gt = [np.asarray(seq.pose(i), np.float64) for i in range(len(seq))]
    return corruption_variance(gt, trans_noise_rel=NOISE_TRANS_REL, rot_noise_deg=NOISE_ROT_DEG)


def odometry_twist_variance(seq, pose_source: str) -> Optional[np.ndarray]:
    """The twist variance a pose source's odometry publishes (rows per frame: linear m^2/s, angular rad^2/s per
    axis): the noise model's motion noise as rates for 'noisy<seed>twist' (corruption_twist_variance), None (not
    filled) otherwise."""
    m = NOISY_SOURCE.fullmatch(pose_source)
    if not (m and m.group(2) == 'twist'):
        return None
    from dpv_sensor.data.trajectory import corruption_twist_variance
    gt = [np.asarray(seq.pose(i), np.float64) for i in range(len(seq))]
    return corruption_twist_variance(gt, [float(seq.stamp(i)) for i in range(len(seq))],
                                     trans_noise_rel=NOISE_TRANS_REL, rot_noise_deg=NOISE_ROT_DEG)


def time_shifted_poses(seq, poses: List[np.ndarray], offset_s: float) -> List[np.ndarray]:
    """The trajectory ``poses`` (one per frame, at ``seq.stamp(i)``) evaluated ``offset_s`` seconds after each frame's
    stamp (SLERP + linear between the two frames around it, held at the ends)."""
    from dpv_sensor.core.pose_math import interpolate_pose
    stamps = np.array([float(seq.stamp(i)) for i in range(len(seq))], np.float64)
    out = []
    for t in stamps + float(offset_s):
        j = int(np.searchsorted(stamps, t, side='right'))
        if j <= 0:
            out.append(poses[0].copy())
        elif j >= len(stamps):
            out.append(poses[-1].copy())
        else:
            a = (t - stamps[j - 1]) / (stamps[j] - stamps[j - 1])
            out.append(interpolate_pose(poses[j - 1], poses[j], float(a)))
    return out


def noise_description(pose_source: str) -> Optional[Dict[str, float]]:
    """What was done to the GT poses of a pose source (None for gt)."""
    if pose_source == 'gt':
        return None
    m = OFFSET_SOURCE.fullmatch(pose_source)
    if m:
        return {'time_offset_ms': float(m.group(1))}
    m = MOUNT_SOURCE.fullmatch(pose_source)
    if m:
        X = mount_error(int(m.group(1)))
        from scipy.spatial.transform import Rotation
        return {'mount_rotvec_deg': [float(v) for v in np.degrees(Rotation.from_matrix(X[:3, :3]).as_rotvec())],
                'mount_translation_m': [float(v) for v in X[:3, 3]]}
    m = NOISY_SOURCE.fullmatch(pose_source)
    published = m.group(2) if m else None
    return {'trans_rel': NOISE_TRANS_REL, 'rot_deg_per_frame': NOISE_ROT_DEG,
            'covariance': published == 'cov', 'twist_covariance': published == 'twist'}


def sequence_folders(data: pathlib.Path) -> List[pathlib.Path]:
    """Every sequence folder (one with poses.txt and K.txt) directly under `data`, sorted by name."""
    return sorted(p for p in data.iterdir() if p.is_dir() and (p / 'poses.txt').is_file() and (p / 'K.txt').is_file())


def add_folder_args(parser) -> None:
    """The ``--data`` / ``--sequences`` options of a benchmark over sequence folders (see :func:`chosen_folders`)."""
    parser.add_argument('--data', type=pathlib.Path, required=True, help='folder of sequence folders')
    parser.add_argument('--sequences', nargs='*', help='only these sequence folders of --data')


def chosen_folders(parser, args) -> Dict[str, pathlib.Path]:
    """{name: folder} of the sequence folders ``args.data`` / ``args.sequences`` name (all of ``--data`` without
    ``--sequences``); ``parser.error`` names a missing folder."""
    if not args.data.is_dir():
        parser.error(f'--data {args.data}: not a folder')
    folders = {f.name: f for f in sequence_folders(args.data)}
    for n in args.sequences or []:
        if n not in folders:
            parser.error(f'no sequence folder {n!r} in {args.data}')
    return {n: folders[n] for n in (args.sequences or folders)}


def rendered_sequence(out: pathlib.Path, seed: int, frames: int, progress: bool,
                      size: Tuple[int, int] = RENDER_SIZE) -> pathlib.Path:
    """The held-out rendered scene `seed` as a sequence folder under OUT/sequences (rendered once; rendered again
    when the frame count or the size asked for differ)."""
    folder = out / 'sequences' / f'synthetic_seed{seed}'
    done = folder / '.complete'
    tag = f'{frames} {size[0]}x{size[1]}'
    if done.is_file() and done.read_text().strip() == tag:
        return folder
    from dpv_sensor.client.replay import render_scene
    if folder.exists():
        shutil.rmtree(folder)
    render_scene(folder, seed, frames, size[0], size[1], progress)
    done.write_text(tag)
    return folder


def params_tag(params: Dict[str, Any]) -> str:
    """A file-name-safe name of the --params overrides ('defaults' without any)."""
    if not params:
        return 'defaults'
    text = ','.join(f'{k}={params[k]}' for k in sorted(params))
    return re.sub(r'[^A-Za-z0-9=,._-]+', '_', text)


def run_key(seq_name: str, pose_source: str, params: Dict[str, Any]) -> str:
    return f'{seq_name}__{pose_source}__{params_tag(params)}'
