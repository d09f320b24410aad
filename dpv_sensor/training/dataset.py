"""Streamed training samples: runs of consecutive keyframes, each with a five-frame window.

Every sample is cut from a *fresh* scene: sample ``i`` of rank ``r`` (of ``world`` ranks) renders the
synthetic scene with seed ``seed_base + i * world + r`` (``seed_base`` >= ``TRAIN_SEED_BASE`` =
1,000,000), so no scene is ever seen twice, ranks never share scenes, DataLoader workers interleave
without overlap, and a resumed run continues exactly where it stopped (``start_index``). Seeds
``VAL_SEEDS`` (0..99) are reserved for validation and can never be produced here.

Optionally a fraction of the samples comes from real-looking sequence folders (TartanAir hospital,
CC BY 4.0) with random scale and crop. SUN3D, TUM fr1_rpy and ICL-NUIM lr kt3 folders are refused
(``HELDOUT_FOLDERS``): they are held-out validation data.

Layout of one sample (M keyframes, K unrolled filter steps, window w, S = w - 1 sources)::

    images   float32 (M, 3, H, W) in [0, 1]      (photometrically augmented)
    depths   float32 (M, H, W) metres, 0 = invalid
    poses    float32 (M, 4, 4) T_first_cam: camera-to-"first keyframe" (relative, so float32 is exact enough)
    K        float32 (3, 3) intrinsics of the H x W images
    stamps   float32 (M,) seconds, relative to the first keyframe
    ref_idx  int64 (K,)   keyframe index of the reference of filter step j
    src_idx  int64 (K, S) keyframe indices of its sources
    src_count int64 (K,)  how many of them step j uses (the last ones): S, or 1, 2, 3, 4 ... in a
                          stream-start run (``startup_prob``, causal windows), like the estimator
    seed     int64        the scene seed (or -1 - frame offset for folder samples)

With ``pose_noise_prob`` > 0 a share of the samples gets odometry-like pose errors (the depths stay exact),
so K-Net meets warped priors that are slightly misaligned, as with real odometry and real GT poses.

Keyframes are ``gap`` frames apart with ``gap`` drawn per keyframe from [gap_min, gap_max], i.e. the
irregular spacing a motion-triggered keyframe selector produces.
"""
from __future__ import annotations

import dataclasses
import os
from typing import Dict, Iterator, List, Optional, Sequence as Seq, Tuple

import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from dpv_sensor.core.pose_math import scale_intrinsics_np
from dpv_sensor import params as P

TRAIN_SEED_BASE = 1_000_000
VAL_SEEDS = range(0, 100)

__all__ = ['TRAIN_SEED_BASE', 'VAL_SEEDS', 'WindowLayout', 'Augment', 'StreamConfig',
           'SceneStream', 'sample_from_sequence', 'scale_K_np', 'resize_crop', 'check_not_heldout', 'HELDOUT_FOLDERS',
           'check_heldout_seeds', 'parse_seeds']


def parse_seeds(text: str) -> Tuple[int, ...]:
    """Seed list from the command line: '0-5' or '0,3,7' or '0-2,7' -> (0, 1, 2, 7); '' -> ()."""
    out: List[int] = []
    for part in str(text).split(','):
        part = part.strip()
        if not part:
            continue
        try:
            if '-' in part:
                a, b = part.split('-')
                out.extend(range(int(a), int(b) + 1))
            else:
                out.append(int(part))
        except ValueError:
            raise ValueError(f'seed list {text!r}: expected e.g. 0-5 or 0,3,7') from None
    return tuple(out)


def check_heldout_seeds(seeds, what: str = 'synthetic seed') -> Tuple[int, ...]:
    """``seeds`` as a tuple; ValueError naming the first one outside ``VAL_SEEDS`` (training draws those)."""
    seeds = tuple(int(s) for s in seeds)
    for s in seeds:
        if s not in VAL_SEEDS:
            raise ValueError(f'{what} {s} is not held out ({VAL_SEEDS.start}..{VAL_SEEDS.stop - 1}): '
                             f'training draws seeds outside that range')
    return seeds


@dataclasses.dataclass(frozen=True)
class WindowLayout:
    """Which keyframes form the window of each unrolled filter step.

    ``ref_position='center'`` is the paper's window ``[t-2, t-1, t, t+1, t+2]`` (in keyframes);
    ``'last'`` is the causal window ``[t-4 .. t]``. Either way M = steps + window - 1 keyframes are
    needed and step j's window is keyframes ``j .. j + window - 1``.
    """
    steps: int = 3
    window: int = P.default('window_size')
    ref_position: str = 'center'

    def __post_init__(self):
        if self.steps < 1 or self.window < 2:
            raise ValueError(f'need steps >= 1 and window >= 2, got {self.steps}, {self.window}')
        if self.ref_position not in ('center', 'last'):
            raise ValueError(f"ref_position must be 'center' or 'last', got {self.ref_position!r}")

    @property
    def num_keyframes(self) -> int:
        return self.steps + self.window - 1

    @property
    def ref_slot(self) -> int:
        return self.window // 2 if self.ref_position == 'center' else self.window - 1

    def indices(self, steps: Optional[int] = None) -> Tuple[np.ndarray, np.ndarray]:
        """(ref_idx (K,), src_idx (K, window-1)) for ``steps`` (default self.steps) filter steps."""
        K = self.steps if steps is None else steps
        refs, srcs = [], []
        for j in range(K):
            win = list(range(j, j + self.window))
            ref = win.pop(self.ref_slot)
            refs.append(ref)
            srcs.append(win)
        return np.asarray(refs, np.int64), np.asarray(srcs, np.int64).reshape(K, self.window - 1)


@dataclasses.dataclass(frozen=True)
class Augment:
    """Photometric augmentation (per sequence, plus a small per-frame exposure flicker).

    Geometry is never augmented (it would have to stay consistent with poses and K)."""
    gain: Tuple[float, float] = (0.6, 1.4)
    gamma: Tuple[float, float] = (0.7, 1.4)
    colour: float = 0.1          # per-channel gain jitter (relative)
    frame_gain: float = 0.06     # per-frame exposure jitter (relative)
    noise: Tuple[float, float] = (0.0, 0.02)   # std of additive Gaussian noise
    enabled: bool = True

    def apply(self, images_n3hw: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        if not self.enabled:
            return images_n3hw
        n = images_n3hw.shape[0]
        x = np.clip(images_n3hw, 0.0, 1.0) ** rng.uniform(*self.gamma)
        g = rng.uniform(*self.gain) * (1.0 + rng.uniform(-self.colour, self.colour, size=(1, 3, 1, 1)))
        g = g * (1.0 + rng.uniform(-self.frame_gain, self.frame_gain, size=(n, 1, 1, 1)))
        x = x * g
        sigma = rng.uniform(*self.noise)
        if sigma > 0:
            x = x + rng.normal(0.0, sigma, size=x.shape)
        return np.clip(x, 0.0, 1.0).astype(np.float32)


@dataclasses.dataclass
class StreamConfig:
    """What :class:`SceneStream` renders. Sizes are the training size of the images (the nets are
    fully convolutional; H and W must be multiples of 4 for the quarter-resolution DPV)."""
    width: int = 128
    height: int = 96
    layout: WindowLayout = dataclasses.field(default_factory=WindowLayout)
    gap_min: int = 3
    gap_max: int = 6
    seed_base: int = TRAIN_SEED_BASE
    augment: Augment = dataclasses.field(default_factory=Augment)
    render_kwargs: Dict = dataclasses.field(default_factory=dict)
    folders: Tuple[str, ...] = ()         # optional sequence folders to mix in (e.g. TartanAir)
    folder_prob: float = 0.0              # probability that a sample comes from a folder
    folder_gap: Tuple[int, int] = (1, 2)  # keyframe gap (frames) inside folders (~8 cm/frame in TartanAir)
    folder_scale: Tuple[float, float] = (1.0, 2.0)  # random zoom relative to "fit the width" before cropping
    extra_sizes: Tuple[Tuple[int, int], ...] = ()   # other (width, height) drawn per batch (multi-scale)
    ref_positions: Tuple[str, ...] = ()   # if given, the window layout's ref_position is drawn per batch
    startup_prob: float = 0.0             # probability (per batch) of a stream-start run (causal windows only)
    size_group: int = 1                   # consecutive samples sharing a size (= the batch size)
    pose_noise_prob: float = 0.0          # probability that a sample's poses are corrupted like odometry
    pose_noise_rot_deg: float = 0.7       # ... by up to this rotation per keyframe step (drawn per sample)
    pose_noise_trans_rel: float = 0.05    # ... and up to this translation error relative to the step
    world_scale_prob: float = 0.0         # probability that a sample's whole world is scaled (depths and poses)
    world_scale: Tuple[float, float] = (0.5, 1.6)   # ... by a factor drawn log-uniformly in this range

    def __post_init__(self):
        if self.width % 4 or self.height % 4:
            raise ValueError(f'training size must be a multiple of 4, got {self.width}x{self.height}')
        if not (1 <= self.gap_min <= self.gap_max):
            raise ValueError(f'need 1 <= gap_min <= gap_max, got {self.gap_min}, {self.gap_max}')
        if self.seed_base < TRAIN_SEED_BASE:
            raise ValueError(f'training seeds must be >= {TRAIN_SEED_BASE} (validation seeds are held out), '
                             f'got seed_base={self.seed_base}')
        for f in self.folders:
            check_not_heldout(f)
        for pos in self.ref_positions:
            if pos not in ('center', 'last'):
                raise ValueError(f"ref_positions must be 'center' or 'last', got {pos!r}")
        for w, h in self.extra_sizes:
            if w % 4 or h % 4:
                raise ValueError(f'training sizes must be multiples of 4, got {w}x{h}')
        if not 0.0 <= self.pose_noise_prob <= 1.0 or self.pose_noise_rot_deg < 0 or self.pose_noise_trans_rel < 0:
            raise ValueError('pose noise: need 0 <= pose_noise_prob <= 1 and non-negative magnitudes')
        lo, hi = self.world_scale
        if not 0.0 <= self.world_scale_prob <= 1.0 or not 0.0 < lo <= hi:
            raise ValueError(f'world scale: need 0 <= world_scale_prob <= 1 and 0 < min <= max, got '
                             f'{self.world_scale_prob}, {self.world_scale}')


# Sequence folders that are validation data only: a folder whose name contains one of these (lower case) is
# refused for training. SUN3D is the held-out real test data; TUM RGB-D fr1_rpy (motion-capture poses) and
# ICL-NUIM lr kt3 (another renderer, exact poses) are the real / foreign checks of confidence and poses.
HELDOUT_FOLDERS = (('sun3d', 'SUN3D'), ('tum_fr1_rpy', 'TUM RGB-D fr1_rpy'), ('icl_nuim_lr_kt3', 'ICL-NUIM lr kt3'))


def check_not_heldout(folder: str) -> None:
    """Refuse held-out evaluation folders for training (``HELDOUT_FOLDERS``: SUN3D, TUM fr1_rpy,
    ICL-NUIM lr kt3)."""
    name = os.path.basename(os.path.normpath(str(folder))).lower()
    for key, what in HELDOUT_FOLDERS:
        if key in name:
            raise ValueError(f'{folder} is held-out evaluation data ({what}) and must never be trained on')


scale_K_np = scale_intrinsics_np      # intrinsics after scaling the image by (sx, sy): pose_math's one copy


def resize_crop(image: np.ndarray, depth: np.ndarray, K_33: np.ndarray, scaled_wh: Tuple[int, int],
                crop_xy: Tuple[int, int], out_wh: Tuple[int, int]) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Resize (area for colour, exact nearest for depth) to ``scaled_wh`` and crop ``out_wh`` at
    ``crop_xy``; returns (image uint8, depth float32, K)."""
    import cv2
    H0, W0 = image.shape[:2]
    Ws, Hs = scaled_wh
    sx, sy = Ws / W0, Hs / H0
    if (Ws, Hs) != (W0, H0):
        image = cv2.resize(image, (Ws, Hs), interpolation=cv2.INTER_AREA if sx < 1 else cv2.INTER_LINEAR)
        depth = cv2.resize(depth, (Ws, Hs), interpolation=cv2.INTER_NEAREST_EXACT)
    x0, y0 = crop_xy
    w, h = out_wh
    K = scale_K_np(K_33, sx, sy)
    K[0, 2] -= x0
    K[1, 2] -= y0
    return image[y0:y0 + h, x0:x0 + w], depth[y0:y0 + h, x0:x0 + w], K


def _clean_depth(depth: np.ndarray) -> np.ndarray:
    d = np.asarray(depth, dtype=np.float32)
    return np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)


def sample_from_sequence(seq, frame_ids: Seq[int], layout: WindowLayout, rng: np.random.Generator,
                         augment: Optional[Augment] = None, out_wh: Optional[Tuple[int, int]] = None,
                         scale: float = 1.0, seed: int = -1) -> Dict[str, torch.Tensor]:
    """Build one sample (see the module docstring) from the given keyframes of a sequence.

    ``seq`` is anything with ``image(i)`` (uint8 HxWx3 RGB), ``depth(i)`` (metres), ``pose(i)``
    (4x4 T_world_cam) and ``K``; ``stamp(i)`` is used when present. With ``out_wh`` the frames are
    scaled by ``scale`` relative to "fit the width" and randomly cropped to ``out_wh``. A sequence without
    depth (``has_depth`` False) gives a sample without ``depths`` (its depth is never asked for).
    """
    frame_ids = [int(i) for i in frame_ids]
    if len(frame_ids) != layout.num_keyframes:
        raise ValueError(f'need {layout.num_keyframes} keyframes, got {len(frame_ids)}')
    K0 = np.asarray(seq.K, dtype=np.float64)
    imgs, deps = [], []
    K = K0
    crop = None
    with_depth = bool(getattr(seq, 'has_depth', True))
    for i in frame_ids:
        im = np.asarray(seq.image(i))
        de = _clean_depth(seq.depth(i)) if with_depth else np.zeros(im.shape[:2], np.float32)
        if out_wh is not None and (im.shape[1], im.shape[0]) != tuple(out_wh):
            H0, W0 = im.shape[:2]
            s = max(out_wh[0] / W0, out_wh[1] / H0) * scale
            Ws, Hs = max(out_wh[0], int(round(W0 * s))), max(out_wh[1], int(round(H0 * s)))
            if crop is None:
                crop = (int(rng.integers(0, Ws - out_wh[0] + 1)), int(rng.integers(0, Hs - out_wh[1] + 1)))
            im, de, K = resize_crop(im, de, K0, (Ws, Hs), crop, out_wh)
        imgs.append(im)
        deps.append(de)
    images = np.stack(imgs).astype(np.float32).transpose(0, 3, 1, 2) / 255.0
    if augment is not None:
        images = augment.apply(images, rng)
    T_world = np.stack([np.asarray(seq.pose(i), dtype=np.float64) for i in frame_ids])
    T_first_world = np.linalg.inv(T_world[0])
    poses = T_first_world[None] @ T_world
    if hasattr(seq, 'stamp'):
        stamps = np.asarray([float(seq.stamp(i)) for i in frame_ids])
    else:
        stamps = np.asarray(frame_ids, dtype=np.float64) / 30.0
    # time since the first keyframe; a run played backwards gets its time mirrored, so it still moves
    # forward: the filter resets on time going backwards, which would cut every unrolled step of that run
    stamps = np.abs(stamps - stamps[0])
    ref_idx, src_idx = layout.indices()
    sample = {
        'images': torch.from_numpy(np.ascontiguousarray(images)),
        'depths': torch.from_numpy(np.stack(deps)),
        'poses': torch.from_numpy(poses.astype(np.float32)),
        'K': torch.from_numpy(K.astype(np.float32)),
        'stamps': torch.from_numpy(stamps.astype(np.float32)),
        'ref_idx': torch.from_numpy(ref_idx),
        'src_idx': torch.from_numpy(src_idx),
        'seed': torch.tensor(int(seed), dtype=torch.int64),
    }
    if not with_depth:
        del sample['depths']
    return sample


def draw_keyframes(rng: np.random.Generator, num_keyframes: int, gap_min: int, gap_max: int,
                   start_max: int = 0) -> List[int]:
    """Frame indices of ``num_keyframes`` keyframes with gaps drawn from [gap_min, gap_max]."""
    ids = [int(rng.integers(0, start_max + 1))]
    for _ in range(num_keyframes - 1):
        ids.append(ids[-1] + int(rng.integers(gap_min, gap_max + 1)))
    return ids


class SceneStream(IterableDataset):
    """Endless (or ``num_samples``-long) stream of training samples, each from a fresh scene.

    Sharding: sample ``i`` (i = start_index, start_index + 1, ...) of this rank uses scene seed
    ``seed_base + i * world_size + rank``; DataLoader worker ``w`` of ``n`` produces the samples with
    ``i % n == w`` so an in-order DataLoader yields i = start_index, start_index + 1, ... exactly.
    """

    def __init__(self, config: StreamConfig, rank: int = 0, world_size: int = 1, start_index: int = 0,
                 num_samples: Optional[int] = None):
        super().__init__()
        self.config = config
        self.rank = int(rank)
        self.world_size = int(world_size)
        self.start_index = int(start_index)
        self.num_samples = num_samples
        self._folders = None

    def seed_of(self, i: int) -> int:
        seed = self.config.seed_base + i * self.world_size + self.rank
        assert seed not in VAL_SEEDS
        return seed

    def __iter__(self) -> Iterator[Dict[str, torch.Tensor]]:
        info = get_worker_info()
        wid, nw = (0, 1) if info is None else (info.id, info.num_workers)
        i = self.start_index + wid
        end = None if self.num_samples is None else self.start_index + self.num_samples
        while end is None or i < end:
            yield self.make_sample(i)
            i += nw

    def size_of(self, i: int) -> Tuple[int, int]:
        """(width, height) of sample i: ``(width, height)`` or, with ``extra_sizes``, one of the sizes
        drawn per group of ``size_group`` consecutive samples (a batch must share one size)."""
        cfg = self.config
        sizes = [(cfg.width, cfg.height)] + [tuple(s) for s in cfg.extra_sizes]
        if len(sizes) == 1:
            return sizes[0]
        g = (i // max(1, cfg.size_group)) * self.world_size + self.rank
        return sizes[int(np.random.default_rng([cfg.seed_base, g]).integers(0, len(sizes)))]

    def layout_of(self, i: int) -> WindowLayout:
        """Window layout of sample i: the configured one or, with ``ref_positions``, a reference
        position drawn per group of ``size_group`` samples (centered and causal windows mixed)."""
        cfg = self.config
        if not cfg.ref_positions:
            return cfg.layout
        g = (i // max(1, cfg.size_group)) * self.world_size + self.rank
        pos = cfg.ref_positions[int(np.random.default_rng([cfg.seed_base, g, 1]).integers(0, len(cfg.ref_positions)))]
        return dataclasses.replace(cfg.layout, ref_position=pos)

    def startup_of(self, i: int) -> bool:
        """Whether sample i imitates the start of a stream (drawn per group of ``size_group``)."""
        cfg = self.config
        if cfg.startup_prob <= 0:
            return False
        g = (i // max(1, cfg.size_group)) * self.world_size + self.rank
        return bool(np.random.default_rng([cfg.seed_base, g, 2]).random() < cfg.startup_prob)

    def _finish(self, smp: Dict[str, torch.Tensor], i: int) -> Dict[str, torch.Tensor]:
        """Add ``src_count`` (K,): sources used by each step. A stream-start run with causal windows
        uses 1, 2, 3, 4 sources in its first steps, as the estimator does after a (re)start."""
        S = smp['src_idx'].shape[1]
        K = smp['src_idx'].shape[0]
        counts = torch.full((K,), S, dtype=torch.int64)
        causal = bool(smp['ref_idx'][0] == S)          # the reference is the newest keyframe of its window
        if causal and self.startup_of(i):
            counts = torch.clamp(torch.arange(1, K + 1, dtype=torch.int64), max=S)
        smp['src_count'] = counts
        return smp

    def _pose_noise(self, smp: Dict[str, torch.Tensor], rng: np.random.Generator) -> Dict[str, torch.Tensor]:
        """With probability ``pose_noise_prob``, replace the sample's poses by an odometry-like corruption of
        them (:func:`dpv_sensor.data.trajectory.corrupt_trajectory`: per keyframe step a rotation error about a
        random axis and a translation error in a random direction, accumulating along the run; magnitudes drawn
        uniformly up to ``pose_noise_rot_deg`` / ``pose_noise_trans_rel`` per sample). Images and depths stay
        exact, so the nets learn what real poses do to the plane sweep and to the warped prior (K-Net learns to
        damp it)."""
        cfg = self.config
        if cfg.pose_noise_prob <= 0 or rng.random() >= cfg.pose_noise_prob:
            return smp
        from dpv_sensor.data.trajectory import corrupt_trajectory
        poses = [T.double().numpy() for T in smp['poses']]
        noisy = corrupt_trajectory(poses, trans_noise_rel=float(rng.uniform(0.0, cfg.pose_noise_trans_rel)),
                                   rot_noise_deg=float(rng.uniform(0.0, cfg.pose_noise_rot_deg)),
                                   seed=int(rng.integers(0, 2 ** 31)))
        smp['poses'] = torch.from_numpy(np.stack(noisy).astype(np.float32))
        return smp

    def world_factor_of(self, i: int) -> float:
        """The factor by which sample i's whole world is scaled: with probability ``world_scale_prob`` one drawn
        log-uniformly in ``world_scale``, else 1. The sample is then built from
        :meth:`~dpv_sensor.data.sequence.Sequence.world_scaled`: every depth and translation times the factor,
        the images unchanged (a world scaled as a whole, textures included, looks the same), so the networks
        cannot read the depth off the rooms' usual sizes and must take it from the cost volume; a factor < 1
        also brings surfaces close to the camera, which the renders rarely do. Drawn from its own generator,
        so the rest of a sample is the same with and without it."""
        cfg = self.config
        if cfg.world_scale_prob <= 0:
            return 1.0
        rng = np.random.default_rng([int(self.seed_of(i)) % 2 ** 32, 5])
        if rng.random() >= cfg.world_scale_prob:
            return 1.0
        lo, hi = cfg.world_scale
        return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))

    def _open_folders(self):
        if self._folders is None:
            from dpv_sensor.data.sequence import Sequence
            self._folders = [Sequence(f) for f in self.config.folders]
        return self._folders

    def make_sample(self, i: int) -> Dict[str, torch.Tensor]:
        """The i-th sample of this rank (deterministic in i, rank and world size)."""
        cfg = self.config
        seed = self.seed_of(i)
        rng = np.random.default_rng(seed)
        M = cfg.layout.num_keyframes
        if cfg.folders and rng.random() < cfg.folder_prob:
            seqs = self._open_folders()
            seq = seqs[int(rng.integers(0, len(seqs)))]
            span = (M - 1) * cfg.folder_gap[1]
            ids = draw_keyframes(rng, M, cfg.folder_gap[0], cfg.folder_gap[1], start_max=len(seq) - 1 - span)
            if rng.random() < 0.5:      # play the run backwards: another plausible trajectory
                ids = ids[::-1]
            smp = sample_from_sequence(seq.world_scaled(self.world_factor_of(i)), ids, self.layout_of(i), rng,
                                       cfg.augment, self.size_of(i),
                                       scale=float(rng.uniform(*cfg.folder_scale)), seed=-1 - ids[0])
        else:
            from dpv_sensor.data.synthetic import render_sequence
            ids = draw_keyframes(rng, M, cfg.gap_min, cfg.gap_max, start_max=cfg.gap_max)
            w, h = self.size_of(i)
            seq = render_sequence(seed, ids[-1] + 1, width=w, height=h, lazy=True, **cfg.render_kwargs)
            smp = sample_from_sequence(seq.world_scaled(self.world_factor_of(i)), ids, self.layout_of(i), rng,
                                       cfg.augment, seed=seed)
        return self._finish(self._pose_noise(smp, rng), i)
