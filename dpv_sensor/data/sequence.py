"""Sequence folders: the one on-disk format for posed RGB-D datasets (the layout of the shared development data folder).

Layout of a sequence folder::

    images/000000.jpg ...   colour, 8-bit RGB (JPEG q95 by default, PNG when written losslessly)
    depth/000000.png  ...   optional ground-truth z-depth, uint16 PNG, millimetres, 0 = invalid
    poses.txt               one line per frame: 16 numbers, row-major 4x4 T_world_cam (camera-to-world),
                            metres, OpenCV camera axes (x right, y down, z forward)
    K.txt                   3x3 intrinsics of the colour camera (depth registered to colour)
    stamps.txt              optional: one time stamp per frame in seconds (default: index / 30 Hz)
    meta.json               optional: free-form JSON metadata (generator, seed, licence, ...)
    extras/<name>/000000.png  optional per-frame 8-bit masks (e.g. ``specular_mask`` from the renderer)

:class:`Sequence` reads such a folder lazily (one image is decoded when asked for), wraps in-memory
arrays (:meth:`Sequence.from_arrays`, used by the synthetic renderer), and gives resized views
(:meth:`Sequence.resized`) whose intrinsics follow the project convention ``fx' = fx * s``,
``cx' = (cx + 0.5) * s - 0.5`` (pixel centres at integer coordinates). :func:`write_sequence` writes any
sequence-like object (anything with ``len``, ``K``, ``image``, ``depth``, ``pose``, ``stamp``) back to a folder.

Keyframe and window helpers (:meth:`Sequence.keyframe_indices`, :func:`keyframe_windows`) return plain
frame indices so training, evaluation and the demo sample the five-frame windows the same way.
"""
from __future__ import annotations

import json
import os
import pathlib
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, NamedTuple, Optional, Sequence as SequenceT, Tuple, Union

import cv2
import numpy as np

from dpv_sensor.core.pose_math import scale_intrinsics_np  # noqa: F401  (re-exported: the resize convention)
from dpv_sensor.common import to_jsonable

PathLike = Union[str, os.PathLike]

DEFAULT_FPS = 30.0
IMAGE_EXTENSIONS = ('.jpg', '.jpeg', '.png')
MAX_DEPTH_MM = 65535


class SequenceFormatError(ValueError):
    """A sequence folder does not follow the format (missing file, wrong count, malformed numbers)."""


class Window(NamedTuple):
    """A window of keyframes: ``frames`` are frame indices in time order, ``frames[ref_pos] == ref``."""
    ref: int
    frames: np.ndarray
    ref_pos: int


# --------------------------------------------------------------------------------------------------
# small readers / writers
# --------------------------------------------------------------------------------------------------

def _read_matrix_lines(path: pathlib.Path, ncols: int) -> np.ndarray:
    rows = []
    with open(path, 'r') as f:
        for lineno, line in enumerate(f, 1):
            line = line.split('#', 1)[0].strip()
            if not line:
                continue
            try:
                values = [float(x) for x in line.replace(',', ' ').split()]
            except ValueError as exc:
                raise SequenceFormatError(f'{path}:{lineno}: not a list of numbers ({exc})') from None
            if len(values) != ncols:
                raise SequenceFormatError(f'{path}:{lineno}: expected {ncols} numbers, got {len(values)}')
            rows.append(values)
    return np.asarray(rows, dtype=np.float64).reshape(-1, ncols)


def read_poses(path: PathLike) -> np.ndarray:
    """poses.txt -> (N, 4, 4) float64 T_world_cam."""
    path = pathlib.Path(path)
    poses = _read_matrix_lines(path, 16).reshape(-1, 4, 4)
    if len(poses) and not np.allclose(poses[:, 3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise SequenceFormatError(f'{path}: last row of a pose must be 0 0 0 1')
    return poses


def read_intrinsics(path: PathLike) -> np.ndarray:
    """K.txt -> (3, 3) float64 (3 lines of 3 numbers, or 9 numbers on one line)."""
    path = pathlib.Path(path)
    values = _read_matrix_lines(path, 3) if _count_numbers_per_line(path) == 3 else _read_matrix_lines(path, 9)
    if values.size != 9:
        raise SequenceFormatError(f'{path}: expected a 3x3 matrix')
    return values.reshape(3, 3)


def _count_numbers_per_line(path: pathlib.Path) -> int:
    with open(path, 'r') as f:
        for line in f:
            line = line.split('#', 1)[0].strip()
            if line:
                return len(line.replace(',', ' ').split())
    raise SequenceFormatError(f'{path}: empty file')


def _format_number(x: float) -> str:
    # repr of a Python float round-trips exactly.
    return repr(float(x))


def write_poses(path: PathLike, poses_n44: np.ndarray) -> None:
    """Write (N, 4, 4) T_world_cam row-major, one pose per line, with exact float64 round trip."""
    poses_n44 = np.asarray(poses_n44, dtype=np.float64).reshape(-1, 4, 4)
    with open(path, 'w') as f:
        for T in poses_n44:
            f.write(' '.join(_format_number(v) for v in T.reshape(-1)) + '\n')


def write_intrinsics(path: PathLike, K_33: np.ndarray) -> None:
    K_33 = np.asarray(K_33, dtype=np.float64).reshape(3, 3)
    with open(path, 'w') as f:
        for row in K_33:
            f.write(' '.join(_format_number(v) for v in row) + '\n')


def depth_from_png_mm(depth_u16: np.ndarray) -> np.ndarray:
    """uint16 millimetres (0 = invalid) -> float32 metres (0 = invalid)."""
    return depth_u16.astype(np.float32) * np.float32(0.001)


def depth_to_png_mm(depth_m: np.ndarray) -> np.ndarray:
    """float metres (0, NaN, inf or negative = invalid) -> uint16 millimetres (0 = invalid).

    Depths beyond 65.535 m cannot be represented and become invalid (0).
    """
    d = np.asarray(depth_m, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    mm = np.zeros(d.shape, dtype=np.float64)
    mm[valid] = np.round(d[valid] * 1000.0)
    mm[(mm > MAX_DEPTH_MM)] = 0
    return mm.astype(np.uint16)


def _as_rgb_uint8(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ValueError(f'expected an HxWx3 RGB image, got shape {image.shape}')
    image = image[:, :, :3]
    if image.dtype != np.uint8:
        if np.issubdtype(image.dtype, np.floating):
            image = np.clip(np.round(image * 255.0), 0, 255)
        image = image.astype(np.uint8)
    return np.ascontiguousarray(image)


# --------------------------------------------------------------------------------------------------
# keyframes and windows
# --------------------------------------------------------------------------------------------------

def keyframe_indices(num_frames: int, every: int = 1, start: int = 0, stop: Optional[int] = None) -> np.ndarray:
    """Frame indices ``start, start+every, ...`` below ``stop`` (default: the number of frames)."""
    if every < 1:
        raise ValueError('every must be >= 1')
    stop = num_frames if stop is None else min(stop, num_frames)
    return np.arange(start, max(start, stop), every, dtype=np.int64)


def keyframe_windows(keyframes: SequenceT[int], size: int = 5, mode: str = 'centered') -> List[Window]:
    """All complete windows of ``size`` consecutive keyframes.

    ``mode='centered'``: the reference is the middle keyframe (``size`` odd), neighbours on both sides —
    the paper's training/evaluation window. ``mode='causal'``: the reference is the newest keyframe and the
    others precede it — what a live sensor can use. Keyframes too close to the ends of the list for a full
    window are skipped. Each :class:`Window` holds frame indices in time order.
    """
    kf = np.asarray(keyframes, dtype=np.int64).reshape(-1)
    if size < 1:
        raise ValueError('size must be >= 1')
    if mode == 'centered':
        if size % 2 != 1:
            raise ValueError('a centered window needs an odd size')
        ref_pos = size // 2
    elif mode == 'causal':
        ref_pos = size - 1
    else:
        raise ValueError(f"mode must be 'centered' or 'causal', got {mode!r}")
    out = []
    for j in range(ref_pos, len(kf) - (size - 1 - ref_pos)):
        frames = kf[j - ref_pos:j - ref_pos + size].copy()
        out.append(Window(ref=int(kf[j]), frames=frames, ref_pos=ref_pos))
    return out


# --------------------------------------------------------------------------------------------------
# reading a sequence folder
# --------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _FolderFiles:
    """A sequence folder checked against the format: its per-frame files (in frame order), poses, K, stamps and
    metadata."""
    images: List[pathlib.Path]
    poses: np.ndarray
    K_33: np.ndarray
    depths: Optional[List[pathlib.Path]]
    stamps: np.ndarray
    meta: Dict[str, Any]
    extras: Dict[str, List[pathlib.Path]]

    @classmethod
    def find(cls, folder: pathlib.Path, depth: bool = True) -> '_FolderFiles':
        """Check the folder's layout and read its text files; SequenceFormatError names what is wrong. With
        ``depth=False`` depth/ is not looked at."""
        image_files = _image_files(folder)
        poses = read_poses(folder / 'poses.txt')
        if len(image_files) != len(poses):
            raise SequenceFormatError(
                f'{folder}: {len(image_files)} images but {len(poses)} poses in poses.txt')
        K_33 = read_intrinsics(folder / 'K.txt')
        depths = _depth_files(folder, image_files) if depth else None
        stamps = _read_stamps(folder, len(poses))
        meta = _read_meta(folder)
        return cls(images=image_files, poses=poses, K_33=K_33, depths=depths, stamps=stamps, meta=meta,
                   extras=_extras_files(folder, image_files))


def _image_files(folder: pathlib.Path) -> List[pathlib.Path]:
    """The colour images of a folder in frame order, after checking that poses.txt, K.txt and images/ exist."""
    if not folder.is_dir():
        raise SequenceFormatError(f'{folder}: not a directory')
    for name in ('poses.txt', 'K.txt'):
        if not (folder / name).is_file():
            raise SequenceFormatError(f'{folder}: {name} is missing')
    image_dir = folder / 'images'
    if not image_dir.is_dir():
        raise SequenceFormatError(f'{folder}: images/ is missing')
    return sorted(p for p in image_dir.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)


def _depth_files(folder: pathlib.Path, image_files: List[pathlib.Path]) -> Optional[List[pathlib.Path]]:
    """depth/<image stem>.png for every image (None without depth/; one missing is an error)."""
    depth_dir = folder / 'depth'
    if not depth_dir.is_dir():
        return None
    depth_files = []
    for p in image_files:
        d = depth_dir / (p.stem + '.png')
        if not d.is_file():
            raise SequenceFormatError(f'{folder}: depth/{d.name} is missing (image {p.name})')
        depth_files.append(d)
    return depth_files


def _read_stamps(folder: pathlib.Path, num_frames: int) -> np.ndarray:
    """stamps.txt (one per frame), or index / DEFAULT_FPS without it."""
    if not (folder / 'stamps.txt').is_file():
        return np.arange(num_frames, dtype=np.float64) / DEFAULT_FPS
    stamps = _read_matrix_lines(folder / 'stamps.txt', 1).reshape(-1)
    if len(stamps) != num_frames:
        raise SequenceFormatError(f'{folder}: {len(stamps)} stamps but {num_frames} poses')
    return stamps


def _read_meta(folder: pathlib.Path) -> Dict[str, Any]:
    """meta.json, or {} without it."""
    if not (folder / 'meta.json').is_file():
        return {}
    with open(folder / 'meta.json', 'r') as f:
        return json.load(f)


def _extras_files(folder: pathlib.Path, image_files: List[pathlib.Path]) -> Dict[str, List[pathlib.Path]]:
    """extras/<name>/<image stem>.png by name, for the extras that have a file for every image."""
    extras_files: Dict[str, List[pathlib.Path]] = {}
    if (folder / 'extras').is_dir():
        for sub in sorted((folder / 'extras').iterdir()):
            if sub.is_dir():
                files = [sub / (p.stem + '.png') for p in image_files]
                if all(f.is_file() for f in files):
                    extras_files[sub.name] = files
    return extras_files


def _image_size(image_files: List[pathlib.Path]) -> Optional[Tuple[int, int]]:
    """(width, height) of the first image (None for no images)."""
    if not image_files:
        return None
    first = cv2.imread(str(image_files[0]), cv2.IMREAD_COLOR)
    if first is None:
        raise SequenceFormatError(f'{image_files[0]}: cannot decode image')
    return (int(first.shape[1]), int(first.shape[0]))


def _read_rgb(path: pathlib.Path) -> np.ndarray:
    """An image file as uint8 HxWx3 RGB."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise SequenceFormatError(f'{path}: cannot decode image')
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _read_depth_mm(path: pathlib.Path) -> np.ndarray:
    """A uint16 millimetre depth PNG as float32 metres (0 = invalid)."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.ndim != 2:
        raise SequenceFormatError(f'{path}: not a single-channel PNG')
    if raw.dtype != np.uint16:
        raise SequenceFormatError(f'{path}: depth PNG must be uint16 millimetres')
    return depth_from_png_mm(raw)


def _read_extra(path: pathlib.Path) -> np.ndarray:
    """An extra's file: 8-bit masks as bool (> 127), other bit depths as stored."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SequenceFormatError(f'{path}: cannot decode')
    return raw > 127 if raw.dtype == np.uint8 else raw


# --------------------------------------------------------------------------------------------------
# Sequence
# --------------------------------------------------------------------------------------------------

class Sequence:
    """A posed RGB-D sequence: colour images, optional z-depth, T_world_cam poses, intrinsics, stamps.

    ``Sequence(folder)`` reads a sequence folder lazily; ``Sequence(folder, depth=False)`` never looks at its depth/
    (a sequence without depth, as a recording to adapt to is read). Accessors:

    - ``len(seq)``; ``seq.K`` (3x3 float64); ``seq.size`` = (W, H); ``seq.poses`` (N,4,4); ``seq.stamps`` (N,)
    - ``seq.image(i)`` -> uint8 HxWx3 RGB; ``seq.depth(i)`` -> float32 HxW metres, 0 = invalid
    - ``seq.pose(i)`` -> 4x4 float64 T_world_cam (OpenCV camera axes); ``seq.stamp(i)`` -> seconds
    - ``seq.extra(name, i)`` -> per-frame extra array (e.g. the renderer's ``specular_mask``)
    - ``seq.resized(width, height)`` -> a view at another resolution with K scaled accordingly
    - ``seq.world_scaled(s)`` -> a view of the same images in a world ``s`` times larger (depths, translations)
    - ``seq.keyframe_indices(every)``, ``seq.windows(every, size=5, mode='centered'|'causal')``
    """

    def __init__(self, folder: PathLike, depth: bool = True):
        folder = pathlib.Path(folder)
        files = _FolderFiles.find(folder, depth=depth)
        self._setup(K=files.K_33, size=_image_size(files.images), poses=files.poses, stamps=files.stamps,
                    load_image=lambda i: _read_rgb(files.images[i]),
                    load_depth=None if files.depths is None else (lambda i: _read_depth_mm(files.depths[i])),
                    meta=files.meta,
                    extras={n: (lambda i, paths=paths: _read_extra(paths[i])) for n, paths in files.extras.items()},
                    name=folder.name, folder=folder)

    # ---------------------------------------------------------------------------------------------
    def _setup(self, *, K, size, poses, stamps, load_image, load_depth, meta, extras, name, folder=None):
        self._K = np.array(K, dtype=np.float64).reshape(3, 3)
        self._size = None if size is None else (int(size[0]), int(size[1]))
        self._poses = np.array(poses, dtype=np.float64).reshape(-1, 4, 4)
        self._stamps = np.array(stamps, dtype=np.float64).reshape(-1)
        if len(self._stamps) != len(self._poses):
            raise SequenceFormatError(f'{len(self._stamps)} stamps but {len(self._poses)} poses')
        self._load_image = load_image
        self._load_depth = load_depth
        self._extras: Dict[str, Callable[[int], np.ndarray]] = dict(extras)
        self.meta: Dict[str, Any] = dict(meta)
        self.name = name
        self.folder = folder

    @classmethod
    def _from_loaders(cls, **kwargs) -> 'Sequence':
        seq = cls.__new__(cls)
        seq._setup(**kwargs)
        return seq

    @classmethod
    def from_arrays(cls, images, depths, poses, K, stamps=None, meta: Optional[dict] = None,
                    extras: Optional[Dict[str, Any]] = None, name: str = 'in-memory') -> 'Sequence':
        """An in-memory sequence.

        images: (N,H,W,3) uint8 RGB array or a list of them; depths: (N,H,W) float metres (0 = invalid) or
        None; poses: (N,4,4) T_world_cam; K: 3x3; stamps: (N,) seconds (default index / 30 Hz);
        extras: {name: (N,H,W) array or list} returned by :meth:`extra`. Arrays are not copied.
        """
        images = [_as_rgb_uint8(im) for im in images]
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        n = len(poses)
        if len(images) != n:
            raise ValueError(f'{len(images)} images but {n} poses')
        if depths is not None:
            depths = [np.asarray(d, dtype=np.float32) for d in depths]
            if len(depths) != n:
                raise ValueError(f'{len(depths)} depth maps but {n} poses')
        if stamps is None:
            stamps = np.arange(n, dtype=np.float64) / DEFAULT_FPS
        size = (images[0].shape[1], images[0].shape[0]) if n else None
        for i, im in enumerate(images):
            if (im.shape[1], im.shape[0]) != size:
                raise ValueError(f'image {i} has size {im.shape[1]}x{im.shape[0]}, expected {size}')
            if depths is not None and depths[i].shape != im.shape[:2]:
                raise ValueError(f'depth {i} has shape {depths[i].shape}, image {im.shape[:2]}')
        extras = dict(extras or {})
        for key, value in extras.items():
            if len(value) != n:
                raise ValueError(f'extra {key!r} has {len(value)} frames, expected {n}')

        def load_depth(i):
            d = depths[i].copy()
            d[~np.isfinite(d) | (d < 0)] = 0.0
            return d

        return cls._from_loaders(
            K=K, size=size, poses=poses, stamps=stamps,
            load_image=lambda i: images[i].copy(),
            load_depth=None if depths is None else load_depth,
            meta=meta or {}, extras={k: (lambda i, v=v: np.asarray(v[i]).copy()) for k, v in extras.items()},
            name=name)

    # ---------------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._poses)

    def __repr__(self) -> str:
        w, h = self.size if self._size else (0, 0)
        return f'Sequence({self.name!r}, frames={len(self)}, size={w}x{h}, depth={self.has_depth})'

    def _check_index(self, i: int) -> int:
        n = len(self)
        i = int(i)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f'frame {i} out of range for a sequence of {n} frames')
        return i

    @property
    def K(self) -> np.ndarray:
        """3x3 float64 intrinsics (a copy)."""
        return self._K.copy()

    @property
    def size(self) -> Tuple[int, int]:
        """(width, height) of the images."""
        if self._size is None:
            raise SequenceFormatError('an empty sequence has no image size')
        return self._size

    @property
    def has_depth(self) -> bool:
        return self._load_depth is not None

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) float64 T_world_cam (a copy)."""
        return self._poses.copy()

    @property
    def stamps(self) -> np.ndarray:
        """(N,) float64 seconds (a copy)."""
        return self._stamps.copy()

    @property
    def extra_names(self) -> List[str]:
        return sorted(self._extras)

    def image(self, i: int) -> np.ndarray:
        """Frame i as uint8 HxWx3 RGB."""
        return self._load_image(self._check_index(i))

    def depth(self, i: int) -> np.ndarray:
        """Ground-truth z-depth of frame i: float32 HxW metres, 0 = invalid."""
        if self._load_depth is None:
            raise SequenceFormatError(f'sequence {self.name!r} has no depth')
        return self._load_depth(self._check_index(i))

    def pose(self, i: int) -> np.ndarray:
        """4x4 float64 T_world_cam of frame i (camera-to-world, OpenCV axes)."""
        return self._poses[self._check_index(i)].copy()

    def stamp(self, i: int) -> float:
        """Time stamp of frame i in seconds."""
        return float(self._stamps[self._check_index(i)])

    def extra(self, name: str, i: int) -> np.ndarray:
        """Per-frame extra array ``name`` (e.g. ``'specular_mask'``: bool HxW) of frame i."""
        if name not in self._extras:
            raise KeyError(f'sequence {self.name!r} has no extra {name!r} (has {self.extra_names})')
        return self._extras[name](self._check_index(i))

    # ---------------------------------------------------------------------------------------------
    def resized(self, width: int, height: int) -> 'Sequence':
        """A view of this sequence at ``width x height``.

        Images are resized with area averaging when shrinking (bilinear when growing); depth with
        centre-aligned nearest neighbour, so invalid pixels stay invalid and no depth is interpolated
        across edges; K is scaled as fx' = fx*s_x, cx' = (cx + 0.5)*s_x - 0.5 (same for y). Boolean extras
        are resized with nearest neighbour. Nothing is loaded until a frame is asked for.
        """
        width, height = int(width), int(height)
        if width < 1 or height < 1:
            raise ValueError('width and height must be positive')
        w0, h0 = self.size
        if (width, height) == (w0, h0):
            return self
        sx, sy = width / w0, height / h0
        K = scale_intrinsics_np(self._K, sx, sy)
        interp = cv2.INTER_AREA if (sx <= 1 and sy <= 1) else cv2.INTER_LINEAR
        base = self

        def load_image(i):
            return cv2.resize(base.image(i), (width, height), interpolation=interp)

        load_depth = None
        if self.has_depth:
            def load_depth(i):
                return resize_nearest(base.depth(i), width, height)

        extras = {n: (lambda i, n=n: resize_nearest(base.extra(n, i), width, height)) for n in self._extras}
        return Sequence._from_loaders(K=K, size=(width, height), poses=self._poses, stamps=self._stamps,
                                      load_image=load_image, load_depth=load_depth, meta=self.meta,
                                      extras=extras, name=f'{self.name}@{width}x{height}', folder=self.folder)

    def world_scaled(self, scale: float) -> 'Sequence':
        """A view of this sequence in a world ``scale`` times larger: every depth and every pose translation times
        ``scale``, the images, intrinsics and stamps unchanged (a world scaled as a whole, textures included,
        looks the same). ``scale`` < 1 brings every surface nearer: a check of whether depth is read from the
        views' geometry or from the usual sizes of rooms."""
        scale = float(scale)
        if not scale > 0:
            raise ValueError(f'world scale must be positive, got {scale}')
        if scale == 1.0:
            return self
        poses = self._poses.copy()
        poses[:, :3, 3] *= scale
        base = self
        load_depth = None
        if self.has_depth:
            def load_depth(i):
                return base.depth(i) * np.float32(scale)

        return Sequence._from_loaders(K=self._K, size=self._size, poses=poses, stamps=self._stamps,
                                      load_image=self.image, load_depth=load_depth, meta=self.meta,
                                      extras={n: (lambda i, n=n: base.extra(n, i)) for n in self._extras},
                                      name=f'{self.name}x{scale:g}', folder=self.folder)

    def keyframe_indices(self, every: int = 1, start: int = 0, stop: Optional[int] = None) -> np.ndarray:
        """Frame indices of keyframes taken every ``every`` frames from ``start``."""
        return keyframe_indices(len(self), every, start, stop)

    def windows(self, every: int = 1, size: int = 5, mode: str = 'centered', start: int = 0) -> List[Window]:
        """All complete windows of ``size`` keyframes (keyframes every ``every`` frames); see
        :func:`keyframe_windows` for the ``centered`` and ``causal`` variants."""
        return keyframe_windows(self.keyframe_indices(every, start), size=size, mode=mode)

    def subset(self, indices: SequenceT[int]) -> 'Sequence':
        """A view with the given frames (in the given order)."""
        idx = [self._check_index(i) for i in indices]
        base = self
        extras = {n: (lambda i, n=n: base.extra(n, idx[i])) for n in self._extras}
        return Sequence._from_loaders(
            K=self._K, size=self._size, poses=self._poses[idx], stamps=self._stamps[idx],
            load_image=lambda i: base.image(idx[i]),
            load_depth=None if not self.has_depth else (lambda i: base.depth(idx[i])),
            meta=self.meta, extras=extras, name=self.name, folder=self.folder)

    def without_depth(self) -> 'Sequence':
        """A view without depth (asking it for depth raises): what a recording to adapt to looks like."""
        base = self
        return Sequence._from_loaders(K=self._K, size=self._size, poses=self._poses, stamps=self._stamps,
                                      load_image=lambda i: base.image(i), load_depth=None, meta=self.meta,
                                      extras={}, name=self.name, folder=self.folder)

    def with_poses(self, poses) -> 'Sequence':
        """A view with every frame's pose replaced by ``poses`` ((N, 4, 4) T_world_cam, e.g. the node's)."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(poses) != len(self):
            raise ValueError(f'{len(poses)} poses for {len(self)} frames')
        base = self
        extras = {n: (lambda i, n=n: base.extra(n, i)) for n in self._extras}
        return Sequence._from_loaders(K=self._K, size=self._size, poses=poses, stamps=self._stamps,
                                      load_image=lambda i: base.image(i),
                                      load_depth=None if not self.has_depth else (lambda i: base.depth(i)),
                                      meta=self.meta, extras=extras, name=self.name, folder=self.folder)

    def materialize(self) -> 'Sequence':
        """Load every frame into memory (useful for a resized view of a folder that is read repeatedly)."""
        n = len(self)
        images = [self.image(i) for i in range(n)]
        depths = [self.depth(i) for i in range(n)] if self.has_depth else None
        extras = {name: [self.extra(name, i) for i in range(n)] for name in self._extras}
        return Sequence.from_arrays(images, depths, self._poses, self._K, self._stamps, meta=self.meta,
                                    extras=extras, name=self.name)


def resize_nearest(a, width: int, height: int) -> np.ndarray:
    """A depth map or mask at ``width x height`` by centre-aligned nearest neighbour (invalid pixels stay invalid,
    nothing is interpolated across edges); the dtype kept (booleans too)."""
    a = np.asarray(a)
    dtype = a.dtype
    if dtype == np.bool_:
        a = a.astype(np.uint8)
    return cv2.resize(a, (int(width), int(height)), interpolation=cv2.INTER_NEAREST_EXACT).astype(dtype)


def write_sequence(folder: PathLike, seq, lossless: bool = False, jpeg_quality: int = 95,
                   write_depth: bool = True, write_extras: bool = True, progress: bool = False) -> pathlib.Path:
    """Write a sequence-like object as a sequence folder and return the folder path.

    ``seq`` needs ``len``, ``K``, ``image(i)``, ``pose(i)``; ``depth(i)`` (written unless it has no
    depth), ``stamp(i)``, ``meta`` and ``extra_names``/``extra(name, i)`` are used when present.
    Images are JPEG (quality ``jpeg_quality``) or PNG when ``lossless``; depth is uint16 millimetres
    (rounded; 0, NaN and depths beyond 65.535 m are written as 0 = invalid); poses, K and stamps are written
    with full float64 precision. Boolean extras are written as 0/255 PNGs under extras/<name>/.
    Existing frame files of the same names are overwritten.
    """
    folder = pathlib.Path(folder)
    n = len(seq)
    (folder / 'images').mkdir(parents=True, exist_ok=True)
    has_depth = write_depth and getattr(seq, 'has_depth', True)
    if has_depth:
        (folder / 'depth').mkdir(exist_ok=True)
    extra_names = list(getattr(seq, 'extra_names', [])) if write_extras else []
    for name in extra_names:
        (folder / 'extras' / name).mkdir(parents=True, exist_ok=True)

    ext = '.png' if lossless else '.jpg'
    params = [] if lossless else [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)]
    iterator = range(n)
    if progress:
        from tqdm import tqdm
        iterator = tqdm(iterator, desc=f'writing {folder.name}', unit='frame')
    poses, stamps = [], []
    for i in iterator:
        stem = f'{i:06d}'
        rgb = _as_rgb_uint8(seq.image(i))
        if not cv2.imwrite(str(folder / 'images' / (stem + ext)), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params):
            raise OSError(f'cannot write {folder / "images" / (stem + ext)}')
        if has_depth:
            cv2.imwrite(str(folder / 'depth' / (stem + '.png')), depth_to_png_mm(seq.depth(i)))
        for name in extra_names:
            a = np.asarray(seq.extra(name, i))
            if a.dtype == np.bool_:
                a = a.astype(np.uint8) * 255
            cv2.imwrite(str(folder / 'extras' / name / (stem + '.png')), a)
        poses.append(np.asarray(seq.pose(i), dtype=np.float64))
        stamps.append(float(seq.stamp(i)) if hasattr(seq, 'stamp') else i / DEFAULT_FPS)
    write_poses(folder / 'poses.txt', np.asarray(poses).reshape(-1, 4, 4))
    write_intrinsics(folder / 'K.txt', seq.K)
    with open(folder / 'stamps.txt', 'w') as f:
        for s in stamps:
            f.write(_format_number(s) + '\n')
    meta = getattr(seq, 'meta', None)
    if meta:
        with open(folder / 'meta.json', 'w') as f:
            json.dump(to_jsonable(meta), f, indent=1, sort_keys=True)
    return folder


