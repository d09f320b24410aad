"""Figures for evaluations (matplotlib, Agg backend; nothing here opens a window).

- :func:`montage`: one row per frame - image | GT depth | predicted depth | confidence | abs-rel error -
  with one shared depth colour scale for GT and prediction of *all* rows, confidence on [0, 1] and the
  abs-rel error on [0, ``max_error``]; pixels without a value are drawn grey.
- :func:`sparsification_plot`: sparsification curves against the oracle and random removal (one
  configuration or several overlaid), AUSE in the legend.
- :func:`bar_table`: a simple bar chart of one metric across configurations.
- :func:`window_graph_plot`: the factor graph of one pose-refinement window.
"""
from __future__ import annotations

import pathlib
from typing import Dict, List, Optional, Sequence

import numpy as np

__all__ = ['montage', 'sparsification_plot', 'bar_table', 'depth_range', 'window_graph_plot']



def _save(fig, path, dpi: int) -> pathlib.Path:
    """Lay out, write (creating the folder) and close a figure; return its path."""
    fig.tight_layout()
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    _plt().close(fig)
    return path

def _plt():
    import matplotlib
    matplotlib.use('Agg', force=False)
    import matplotlib.pyplot as plt
    return plt


def depth_range(depths: Sequence[np.ndarray], lo_pct: float = 2.0, hi_pct: float = 98.0) -> tuple:
    """A shared colour range (vmin, vmax) from the valid (finite, > 0) values of several depth maps."""
    vals = [np.asarray(d, np.float64)[np.isfinite(d) & (np.asarray(d) > 0)] for d in depths if d is not None]
    vals = np.concatenate(vals) if vals else np.zeros(0)
    if vals.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(vals, [lo_pct, hi_pct])
    if hi <= lo:
        hi = lo + 1e-3
    return float(lo), float(hi)


def _masked(a: Optional[np.ndarray]) -> np.ma.MaskedArray:
    a = np.asarray(a, np.float64)
    return np.ma.masked_where(~np.isfinite(a) | (a <= 0), a)


def montage(rows: List[Dict], path, *, max_error: float = 0.5, title: Optional[str] = None,
            cmap_depth: str = 'turbo', dpi: int = 110) -> pathlib.Path:
    """Write a montage PNG and return its path.

    rows: dicts with ``image`` (HxWx3 uint8 or None), ``gt`` (HxW metres, 0/NaN = none), ``pred`` (HxW
    metres, NaN = none), ``confidence`` (HxW in [0, 1] or None) and an optional ``label``. The error
    column is |pred - gt| / gt where both exist.
    """
    plt = _plt()
    if not rows:
        raise ValueError('montage needs at least one row')
    vmin, vmax = depth_range([r['gt'] for r in rows] + [r['pred'] for r in rows])
    cols = ['image', 'GT depth', 'predicted depth', 'confidence', 'abs-rel error']
    h, w = np.asarray(rows[0]['pred']).shape
    fig_w = 2.6 * len(cols) + 1.2
    fig_h = 2.6 * len(rows) * h / max(w, 1) + 0.9
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(fig_w, fig_h), squeeze=False)
    cm_depth = plt.get_cmap(cmap_depth).with_extremes(bad='0.5')
    cm_conf = plt.get_cmap('viridis').with_extremes(bad='0.5')
    cm_err = plt.get_cmap('magma').with_extremes(bad='0.5')
    ims = {}
    for r, row in enumerate(rows):
        gt = np.asarray(row['gt'], np.float64)
        pred = np.asarray(row['pred'], np.float64)
        ax = axes[r]
        if row.get('image') is not None:
            ax[0].imshow(row['image'])
        else:
            ax[0].imshow(np.full(pred.shape + (3,), 128, np.uint8))
        ax[0].set_ylabel(row.get('label', ''), fontsize=8)
        ims['depth'] = ax[1].imshow(_masked(gt), cmap=cm_depth, vmin=vmin, vmax=vmax, interpolation='nearest')
        ax[2].imshow(_masked(pred), cmap=cm_depth, vmin=vmin, vmax=vmax, interpolation='nearest')
        conf = row.get('confidence')
        if conf is not None:
            c = np.ma.masked_where(~np.isfinite(pred), np.asarray(conf, np.float64))
            ims['conf'] = ax[3].imshow(c, cmap=cm_conf, vmin=0.0, vmax=1.0, interpolation='nearest')
        with np.errstate(invalid='ignore', divide='ignore'):
            err = np.abs(pred - gt) / gt
        err = np.ma.masked_where(~(np.isfinite(err) & (gt > 0) & np.isfinite(pred) & (pred > 0)), err)
        ims['err'] = ax[4].imshow(err, cmap=cm_err, vmin=0.0, vmax=max_error, interpolation='nearest')
        for a in ax:
            a.set_xticks([])
            a.set_yticks([])
    for c, name in enumerate(cols):
        axes[0][c].set_title(name, fontsize=9)
    fig.subplots_adjust(left=0.03, right=0.85, top=0.93 if title else 0.96, bottom=0.02, wspace=0.04, hspace=0.06)
    # colour bars on the right: depth (m), confidence, error
    bars = [('depth', 'depth (m)'), ('conf', 'confidence'), ('err', f'abs rel (clip {max_error:g})')]
    for k, (key, label) in enumerate(b for b in bars if b[0] in ims):
        cax = fig.add_axes([0.865 + 0.047 * k, 0.1, 0.008, 0.8])
        cb = fig.colorbar(ims[key], cax=cax)
        cb.set_label(label, fontsize=7)
        cb.ax.tick_params(labelsize=6)
    if title:
        fig.suptitle(title, fontsize=10)
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def sparsification_plot(curves: Dict[str, Dict[str, np.ndarray]], path, *, title: Optional[str] = None,
                        dpi: int = 110) -> pathlib.Path:
    """Sparsification curves (solid), oracle (dashed) and random (dotted) per configuration.

    curves: {name: {'fractions', 'sparsification', 'oracle', 'random'}} (as from
    ``MetricAccumulator.mean_curves()``). The legend carries each configuration's AUSE.
    """
    from dpv_sensor.evaluation.metrics import ause
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.0, 4.2))
    colors = plt.rcParams['axes.prop_cycle'].by_key()['color']
    for k, (name, c) in enumerate(curves.items()):
        if c is None:
            continue
        col = colors[k % len(colors)]
        f = np.asarray(c['fractions']) * 100.0
        ax.plot(f, c['sparsification'], color=col, lw=1.8, label=f'{name} (AUSE {ause(c):.4f})')
        ax.plot(f, c['oracle'], color=col, lw=1.0, ls='--', label=f'{name} oracle')
        ax.plot(f, c['random'], color=col, lw=1.0, ls=':', label=f'{name} random')
    ax.set_xlabel('pixels removed (%), least confident first')
    ax.set_ylabel('abs_rel of the remaining pixels')
    ax.set_xlim(0, 100)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path, dpi)


def reliability_plot(calibration: Dict[str, Dict], path, *, title: Optional[str] = None,
                     dpi: int = 110) -> pathlib.Path:
    """Reliability diagram: per confidence bin, the share of pixels whose true depth lies within x1.25 of the
    published one against the bin's mean confidence (the diagonal = calibrated), with the share of pixels per bin
    underneath.

    calibration: {name: ``metrics.calibration_summary(...)``}; the legend carries each one's ECE and the share kept
    and delta1 at a confidence of 0.9.
    """
    plt = _plt()
    fig, (ax, axn) = plt.subplots(2, 1, figsize=(5.2, 5.6), sharex=True, gridspec_kw={'height_ratios': [3, 1]})
    colors = plt.rcParams['axes.prop_cycle'].by_key()['color']
    ax.plot([0, 1], [0, 1], color='0.6', lw=1.0, ls='--', label='calibrated')
    for k, (name, cal) in enumerate(calibration.items()):
        if not cal:
            continue
        col = colors[k % len(colors)]
        b = cal['bins']
        conf = np.asarray(b['mean_confidence'], np.float64)
        hit = np.asarray(b['hit_rate'], np.float64)
        count = np.asarray(b['count'], np.float64)
        edges = np.asarray(b['edges'], np.float64)
        used = count > 0
        kept = (cal.get('kept') or {}).get('0.9') or {}
        ax.plot(conf[used], hit[used], 'o-', color=col, lw=1.6, ms=4,
                label=f"{name}: ECE {cal['ece']:.3f}, conf>=0.9 keeps {kept.get('share', float('nan')):.0%} "
                      f"(d1 {kept.get('delta1', float('nan')):.2f})")
        centres = 0.5 * (edges[1:] + edges[:-1])
        width = (edges[1] - edges[0]) / max(1, len(calibration))
        axn.bar(centres - 0.5 * (edges[1] - edges[0]) + (k + 0.5) * width, count / max(1.0, count.sum()),
                width=width, color=col)
    ax.set_ylabel('share within x1.25 of the truth')
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc='upper left')
    axn.set_xlabel('published confidence')
    axn.set_ylabel('share of pixels')
    axn.grid(alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path, dpi)


def bar_table(values: Dict[str, float], path, *, ylabel: str = 'abs_rel', title: Optional[str] = None,
              dpi: int = 110) -> pathlib.Path:
    """A bar chart of one number per configuration."""
    plt = _plt()
    names = list(values)
    fig, ax = plt.subplots(figsize=(max(4.0, 0.9 * len(names) + 1.5), 3.2))
    ax.bar(range(len(names)), [values[n] for n in names], color='tab:blue')
    ax.set_xticks(range(len(names)))
    ax.set_xticklabels(names, rotation=30, ha='right', fontsize=8)
    ax.set_ylabel(ylabel)
    ax.grid(axis='y', alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path, dpi)


def window_graph_plot(window: Sequence, factors: Dict[str, List], path, *, reference=None,
                      title: Optional[str] = None, dpi: int = 110) -> pathlib.Path:
    """The factor graph of one pose-refinement window (``RefinementResult.factors``): keyframes as circles in
    time order (the reference filled), each factor a small square joined to the keyframes it ties - the gauge
    prior above its keyframe, odometry between neighbours on the line, photometric alignments as arcs above,
    keypoint poses as arcs below."""
    plt = _plt()
    keys = list(window)
    x = {k: float(i) for i, k in enumerate(keys)}
    fig, ax = plt.subplots(figsize=(1.6 * len(keys) + 1.5, 3.6))
    styles = {'odometry': ('black', 0.0), 'photometric': ('tab:blue', 1.0), 'keypoint': ('tab:orange', -1.0)}
    shown = set()

    def factor(xm, ym, colour, label):
        ax.plot([xm], [ym], marker='s', ms=7, color=colour, zorder=4,
                label=None if label in shown else label)
        shown.add(label)

    for kind, (colour, side) in styles.items():
        seen: Dict[tuple, int] = {}
        for a, b in factors.get(kind, []):
            if a not in x or b not in x:
                continue
            xa, xb = x[a], x[b]
            # a second factor between the same keyframes (an alignment kept from an earlier window) arcs higher
            pair = (min(xa, xb), max(xa, xb))
            extra = 0.3 * seen.get(pair, 0)
            seen[pair] = seen.get(pair, 0) + 1
            if side == 0.0:
                ax.plot([xa, xb], [0, 0], color=colour, lw=1.5, zorder=1)
                factor((xa + xb) / 2, 0.0, colour, 'odometry between')
                continue
            t = np.linspace(0, 1, 40)
            h = side * (0.35 + 0.25 * abs(xb - xa) + extra)
            xs = xa + (xb - xa) * t
            ax.plot(xs, h * np.sin(np.pi * t), color=colour, lw=1.3, zorder=1)
            factor((xa + xb) / 2, h, colour, f'{kind} between')
    for a, _ in factors.get('prior', []):
        if a in x:
            ax.plot([x[a], x[a]], [0, 0.45], color='grey', lw=1.2, zorder=1)
            factor(x[a], 0.45, 'grey', 'gauge prior')
    for k in keys:
        ref = k == reference
        ax.plot([x[k]], [0], marker='o', ms=22, mfc='tab:green' if ref else 'white', mec='black', zorder=5)
        ax.annotate('ref' if ref else f'{x[k] - x.get(reference, 0):+.0f}', (x[k], 0), ha='center',
                    va='center', fontsize=8, zorder=6)
    ax.set_xlim(-0.7, len(keys) - 0.3)
    ax.set_ylim(-2.2, 2.2)
    ax.axis('off')
    ax.legend(loc='upper center', bbox_to_anchor=(0.5, -0.02), ncol=4, fontsize=8, frameon=False)
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path, dpi)
