"""Where the depth error comes from: abs_rel split by image position, GT depth, occlusion edges, error size, image
texture and whether the window's other keyframes saw the pixel at all.

Rendered sequences (held-out seeds, never trained on) and sequence folders (``--seqs``, e.g. SUN3D) are streamed
frame by frame through ``Estimator`` with the node's defaults, as in :mod:`dpv_sensor.studies.selection`, and
every scored pixel of every keyframe output is put into these groups (abs_rel = |d - d_gt| / d_gt, pooled over pixels):

* ``cell``: an 8 x 8 grid over the image (drawn as a heat map);
* ``gt_depth``: bands of the GT depth in metres (labels ``lo-hi``);
* ``edge``: within ``edge_radius`` px of a GT depth jump of more than 10 % (occlusion edges) or not;
* ``size``: ``gross`` (abs_rel > 0.25, i.e. outside delta < 1.25) or ``fine``;
* ``texture``: the frame's scored pixels in thirds of local image texture (mean gradient magnitude of the grey
  image over 7 x 7 px): ``weak`` / ``mid`` / ``strong`` (ties at a threshold go to the lower third);
* ``views``: in how many of the *other keyframes of the window* (the sources of its plane sweep; past ones in
  ``causal`` mode, both sides in ``centered`` mode) the pixel's GT 3-D point lies inside the image. ``0`` means
  no source could have seen it (new content at the leading edge of the motion); occlusion is not checked.

Each group reports per label the fraction of pixels, their abs_rel and their share of the total error.

    .venv/bin/python -m dpv_sensor.studies.error_breakdown --weights dpv_sensor/weights/lite.safetensors \
        --seeds 20-25 [--seqs FOLDER ...] [--frames 60] [--mode knet] [--window-mode causal] \
        [--pose-noise REL_T ROT_DEG] \
        [--threads 2] [--out DIR]

``--out`` writes ``error_breakdown.json`` and ``error_breakdown.png`` (heat map and the groups as bars).
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from scipy import ndimage

from dpv_sensor.evaluation import metrics as M
from dpv_sensor import params as P
from dpv_sensor.cli import add_setting

GROSS_ABS_REL = 0.25
DEPTH_BANDS_M = (0.3, 1.0, 1.5, 2.0, 3.0, 4.0, 8.0)
GRID = 8


def views_of_window(gt_depth_hw: np.ndarray, K_33: np.ndarray, T_world_cam_44: np.ndarray,
                    others_T_world_cam: Sequence[np.ndarray]) -> np.ndarray:
    """Per pixel, how many of the other cameras (same K and image size) have its GT 3-D point in their image
    (in front of the camera, inside ``[0, W-1] x [0, H-1]``;
    :func:`dpv_sensor.evaluation.metrics.reproject`). Pixels without GT (0 / NaN) count 0. Occlusion is not checked."""
    gt = np.asarray(gt_depth_hw, np.float64)
    valid = M.gt_valid_mask(gt)
    z = np.where(valid, gt, 0.0)
    count = np.zeros(gt.shape, np.int32)
    T_world_cam = np.asarray(T_world_cam_44, np.float64)
    for T_other in others_T_world_cam:
        T_other_cam = np.linalg.inv(np.asarray(T_other, np.float64)) @ T_world_cam
        inside = M.reproject(z, K_33, K_33, T_other_cam, gt.shape)[3].reshape(gt.shape)
        count += valid & inside
    return count


def depth_edge_mask(gt_depth_hw: np.ndarray, radius: int = 4, rel_jump: float = 0.1) -> np.ndarray:
    """True within ``radius`` px of a GT depth discontinuity (max - min over a 3x3 over the depth > rel_jump)."""
    gt = np.asarray(gt_depth_hw, np.float64)
    valid = np.isfinite(gt) & (gt > 0)
    hi = ndimage.maximum_filter(np.where(valid, gt, 0.0), size=3)
    lo = ndimage.minimum_filter(np.where(valid, gt, np.inf), size=3)
    with np.errstate(invalid='ignore', divide='ignore'):
        jump = valid & ((hi - lo) / np.where(valid, gt, 1.0) > rel_jump)
    if radius > 0:
        jump = ndimage.binary_dilation(jump, structure=np.ones((2 * radius + 1, 2 * radius + 1), bool))
    return jump


def keyframe_frames(poses_in: Sequence[np.ndarray], config) -> List[int]:
    """Frame indices that become keyframes when these poses stream, unbroken, through the estimator's selector."""
    from dpv_sensor.stream.keyframes import KeyframeSelector
    sel = KeyframeSelector(config.keyframe_translation, config.keyframe_rotation_deg, config.keyframe_max_interval)
    return [i for i, T in enumerate(poses_in) if sel.decide(np.asarray(T, np.float64)).is_keyframe]


def local_texture(image_hw3: np.ndarray, size: int = 7) -> np.ndarray:
    """Mean gradient magnitude of the grey image (0..1 scale) over ``size`` x ``size`` px: how much texture a
    matching window around each pixel holds."""
    img = np.asarray(image_hw3, np.float64)
    grey = img.mean(axis=-1) if img.ndim == 3 else img
    if np.issubdtype(np.asarray(image_hw3).dtype, np.integer):
        grey = grey / 255.0
    gy, gx = np.gradient(grey)
    return ndimage.uniform_filter(np.hypot(gx, gy), size=size)


def window_others(keyframes: Sequence[int], pos: int, window_size: int, window_mode: str) -> List[int]:
    """The other keyframes (items of ``keyframes``) in the window of keyframe ``keyframes[pos]``: the sources of
    its plane sweep; ``window_size - 1`` past ones in ``causal`` mode, half on each side in ``centered`` mode."""
    if window_mode == 'centered':
        half = window_size // 2
        return [keyframes[j] for j in range(max(0, pos - half), min(len(keyframes), pos + half + 1)) if j != pos]
    return [keyframes[j] for j in range(max(0, pos - (window_size - 1)), pos)]


class ErrorBreakdown:
    """Pools abs_rel sums and pixel counts per group label (see the module docstring)."""

    GROUPS = ('gt_depth', 'edge', 'size', 'texture', 'views')

    def __init__(self, min_depth: float = 0.3, max_depth: float = 8.0, edge_radius: int = 4, grid: int = GRID):
        self.min_depth, self.max_depth, self.edge_radius, self.grid = min_depth, max_depth, edge_radius, grid
        self.sums: Dict[str, Dict[str, List[float]]] = {g: {} for g in self.GROUPS}
        self.cell_sum = np.zeros((grid, grid))
        self.cell_count = np.zeros((grid, grid))
        self.total = [0.0, 0]

    def _add(self, group: str, label: str, err_n: np.ndarray) -> None:
        s = self.sums[group].setdefault(label, [0.0, 0])
        s[0] += float(err_n.sum())
        s[1] += int(err_n.size)

    def add(self, pred_hw: np.ndarray, gt_hw: np.ndarray, views_hw: Optional[np.ndarray] = None,
            image_hw3: Optional[np.ndarray] = None) -> None:
        """One frame: prediction and GT in metres at the same size; ``views_hw`` from :func:`views_of_window`;
        ``image_hw3`` the keyframe's image at that size (for the texture group)."""
        m = M.evaluation_mask(pred_hw, gt_hw, self.min_depth, self.max_depth)
        gt = np.asarray(gt_hw, np.float64)
        err = np.zeros(gt.shape)
        err[m] = np.abs(np.asarray(pred_hw, np.float64)[m] - gt[m]) / gt[m]
        self.total[0] += float(err[m].sum())
        self.total[1] += int(m.sum())
        H, W = gt.shape
        ys, xs = np.nonzero(m)
        np.add.at(self.cell_sum, (ys * self.grid // H, xs * self.grid // W), err[m])
        np.add.at(self.cell_count, (ys * self.grid // H, xs * self.grid // W), 1)
        for lo, hi in zip(DEPTH_BANDS_M[:-1], DEPTH_BANDS_M[1:]):
            last = hi == DEPTH_BANDS_M[-1]
            band = m & (gt >= lo) & ((gt <= hi) if last else (gt < hi))
            self._add('gt_depth', f'{lo:g}-{hi:g}', err[band])
        edge = depth_edge_mask(gt, self.edge_radius)
        self._add('edge', 'edge', err[m & edge])
        self._add('edge', 'flat', err[m & ~edge])
        self._add('size', 'gross', err[m & (err > GROSS_ABS_REL)])
        self._add('size', 'fine', err[m & (err <= GROSS_ABS_REL)])
        if image_hw3 is not None and m.any():
            tex = local_texture(image_hw3)
            lo, hi = np.quantile(tex[m], [1 / 3, 2 / 3])
            self._add('texture', 'weak', err[m & (tex <= lo)])
            self._add('texture', 'mid', err[m & (tex > lo) & (tex <= hi)])
            self._add('texture', 'strong', err[m & (tex > hi)])
        if views_hw is not None:
            for label, sel in (('0', views_hw == 0), ('1', views_hw == 1), ('2+', views_hw >= 2)):
                self._add('views', label, err[m & sel])

    def summary(self) -> Dict:
        """{'pixels', 'abs_rel', groups: {group: {label: {pixel_fraction, abs_rel, error_share}}}, 'cells'}."""
        n, e = self.total[1], self.total[0]
        groups = {}
        for g, labels in self.sums.items():
            if not labels:
                continue
            groups[g] = {lab: {'pixel_fraction': c / n if n else float('nan'),
                               'abs_rel': s / c if c else float('nan'),
                               'error_share': s / e if e else float('nan')} for lab, (s, c) in labels.items()}
        with np.errstate(invalid='ignore', divide='ignore'):
            cells = np.where(self.cell_count > 0, self.cell_sum / np.maximum(self.cell_count, 1), np.nan)
        return {'pixels': n, 'abs_rel': e / n if n else float('nan'), 'groups': groups,
                'cells_abs_rel': [[None if not np.isfinite(v) else float(v) for v in row] for row in cells]}


def markdown(summary: Dict) -> str:
    lines = [f"pixel-pooled abs_rel {summary['abs_rel']:.4f} over {summary['pixels']} pixels", '',
             '| group | label | pixels | abs_rel | share of error |', '|---|---|---|---|---|']
    for g, labels in summary['groups'].items():
        for lab, r in labels.items():
            lines.append(f"| {g} | {lab} | {r['pixel_fraction']:.1%} | {r['abs_rel']:.3f} | {r['error_share']:.1%} |")
    lines += ['', f'abs_rel by image cell ({GRID} x {GRID}, top row first):']
    for row in summary['cells_abs_rel']:
        lines.append(' '.join('  -  ' if v is None else f'{v:.3f}' for v in row))
    return '\n'.join(lines)


def plot(summary: Dict, path, title: Optional[str] = None) -> pathlib.Path:
    """Heat map of abs_rel over the image and one bar chart per group (abs_rel; labels carry the pixel share)."""
    from dpv_sensor.evaluation.plots import _plt, _save
    plt = _plt()
    groups = summary['groups']
    fig, axes = plt.subplots(1, 1 + len(groups), figsize=(3.6 * (1 + len(groups)), 3.4))
    cells = np.array([[np.nan if v is None else v for v in row] for row in summary['cells_abs_rel']])
    im = axes[0].imshow(cells, cmap='magma', vmin=0.0, vmax=max(0.05, float(np.nanmax(cells))))
    axes[0].set_title('abs_rel by image cell', fontsize=9)
    axes[0].set_xticks([])
    axes[0].set_yticks([])
    fig.colorbar(im, ax=axes[0], fraction=0.046)
    for ax, (g, labels) in zip(axes[1:], groups.items()):
        names = list(labels)
        ax.bar(range(len(names)), [labels[n]['abs_rel'] for n in names], color='tab:blue')
        ax.set_xticks(range(len(names)))
        ax.set_xticklabels([f"{n}\n{labels[n]['pixel_fraction']:.0%} px" for n in names], fontsize=7)
        ax.axhline(summary['abs_rel'], color='k', lw=0.8, ls='--')
        titles = {'gt_depth': 'GT depth (m)', 'views': 'seen by how many window keyframes'}
        ax.set_title(titles.get(g, g), fontsize=9)
        ax.grid(axis='y', alpha=0.3)
    axes[1].set_ylabel('abs_rel (dashed: all pixels)')
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path, 110)


def breakdown_sequences(model, sequences: Sequence[Tuple[str, object, int]], *, mode: str = 'knet',
                        window_mode: str = P.default('window_mode'), pose_noise: Tuple[float, float] = (0.0, 0.0),
                        device: str = P.default('device'), progress=None) -> Dict:
    """Stream ``(name, sequence, seed)`` items through the estimator (node defaults plus mode / window_mode; GT
    poses, or odometry-like ones seeded by ``seed`` when ``pose_noise`` is set) and break down the error."""
    from dpv_sensor.evaluation.offline import EvalOptions, build_config, depth_limits, input_poses, run_sequence
    noisy = pose_noise[0] > 0 or pose_noise[1] > 0
    config, _ = build_config({'filter_mode': mode, 'window_mode': window_mode, 'device': str(device)})
    acc: Optional[ErrorBreakdown] = None
    for name, seq, seed in sequences:
        opts = EvalOptions(seed=seed, progress=False, pose_source='noisy' if noisy else 'gt',
                           pose_noise=tuple(pose_noise))
        records, status = run_sequence(seq, config, opts, model=model)
        if acc is None:
            acc = ErrorBreakdown(*depth_limits(opts, status))
        keyframes = keyframe_frames(input_poses(seq, opts), config)
        position = {f: p for p, f in enumerate(keyframes)}
        if any(r.reset_reason for r in records[1:]) or any(r.index not in position for r in records):
            raise ValueError(f'{name}: the estimator restarted mid-stream or chose other keyframes than an unbroken '
                             f'stream would; the window views cannot be reconstructed')
        for r in records:
            others = window_others(keyframes, position[r.index], config.window_size, window_mode)
            views = views_of_window(r.gt_depth_hw, r.K_33, r.gt_T_world_cam_44, [seq.pose(j) for j in others])
            acc.add(r.depth_hw, r.gt_depth_hw, views, r.image_hw3)
        if progress:
            so_far = acc.total[0] / max(acc.total[1], 1)
            progress(f'{name}: {len(records)} keyframes, pooled abs_rel so far {so_far:.4f}')
    if acc is None:
        raise ValueError('no sequences given (--seeds and --seqs are both empty)')
    return acc.summary()


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog='error_breakdown', description=__doc__.split('\n\n')[0])
    ap.add_argument('--weights', default='dpv_sensor/weights/lite.safetensors')
    ap.add_argument('--seeds', default='20-25', help="held-out rendered seeds (0..99); '' for none")
    ap.add_argument('--seqs', nargs='*', default=[], help='sequence folders with GT depth and poses')
    ap.add_argument('--frames', type=int, default=60, help='frames per sequence (320x240, 30 Hz)')
    ap.add_argument('--mode', default='knet', help='filter_mode')
    add_setting(ap, 'window_mode')
    ap.add_argument('--pose-noise', type=float, nargs=2, default=[0.0, 0.0], metavar=('REL_T', 'ROT_DEG'),
                    help='odometry-like pose errors per frame instead of GT poses (default: GT poses)')
    ap.add_argument('--threads', type=int, default=2)
    ap.add_argument('--out', default=None, help='folder for error_breakdown.json and error_breakdown.png')
    a = ap.parse_args(argv)
    import torch
    from dpv_sensor.benchmarks.heldout import load_model
    from dpv_sensor.data.sequence import Sequence as SequenceFolder
    from dpv_sensor.data.synthetic import render_sequence
    from dpv_sensor.training.dataset import check_heldout_seeds, parse_seeds
    torch.set_num_threads(a.threads)
    try:
        seeds = check_heldout_seeds(parse_seeds(a.seeds))
        items = [(f'synthetic seed {s}', render_sequence(s, a.frames, width=320, height=240, lazy=True), s)
                 for s in seeds]
        for folder in a.seqs:
            try:
                items.append((folder, SequenceFolder(folder), 0))
            except Exception as e:
                raise ValueError(f'cannot read sequence folder {folder}: {type(e).__name__}: {e}') from None
        try:
            model, _ = load_model(a.weights)
        except Exception as e:
            raise ValueError(f'cannot load weights {a.weights}: {type(e).__name__}: {e}') from None
        summary = breakdown_sequences(model, items, mode=a.mode, window_mode=a.window_mode,
                                      pose_noise=tuple(a.pose_noise), progress=lambda m: print(m, flush=True))
    except ValueError as e:
        print(f'error_breakdown: {e}', file=sys.stderr)
        return 2
    summary.update(weights=a.weights, seeds=list(seeds), seqs=list(a.seqs), frames=a.frames, mode=a.mode,
                   window_mode=a.window_mode, pose_noise=list(a.pose_noise))
    print(markdown(summary))
    if a.out:
        out = pathlib.Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        with open(out / 'error_breakdown.json', 'w') as f:
            json.dump(summary, f, indent=1)
        plot(summary, out / 'error_breakdown.png',
             title=f'{pathlib.Path(a.weights).name}, seeds {a.seeds or "-"} '
                   f'{" ".join(pathlib.Path(f).name for f in a.seqs)}, {a.mode}, {a.window_mode}')
        print(f'wrote {out}/error_breakdown.json and .png')
    return 0


if __name__ == '__main__':
    sys.exit(main())
