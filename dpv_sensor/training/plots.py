"""The trainer's figures: the validation montage and the loss / validation curves (PNG, written atomically)."""
from __future__ import annotations

import os
from typing import Dict, List, Optional

import numpy as np

from dpv_sensor.training.stream_validation import stream_metric_key

__all__ = ['save_montage', 'plot_curves']


def save_montage(examples: List[Dict], path: str, d_min: float, d_max: float, title: str = '') -> None:
    """PNG: per (source, mode) row: image | GT | depth | confidence | |error|/GT."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    if not examples:
        return
    rows = len(examples)
    fig, axes = plt.subplots(rows, 5, figsize=(13, 2.2 * rows + 0.4), squeeze=False)
    gt0 = examples[0]['gt']
    vmax = float(np.percentile(gt0[gt0 > 0], 99)) if (gt0 > 0).any() else d_max
    for r, ex in enumerate(examples):
        gt = ex['gt']
        err = np.where(gt > 0, np.abs(ex['depth'] - gt) / np.maximum(gt, 1e-6), np.nan)
        panels = [(np.clip(ex['image'], 0, 1), None, 'image'), (np.where(gt > 0, gt, np.nan), 'turbo', 'GT depth'),
                  (ex['depth'], 'turbo', f"{ex['source']} {ex['mode']}"), (ex['conf'], 'viridis', 'confidence'),
                  (err, 'magma', f'abs rel err (mean {np.nanmean(err):.3f})')]
        for c, (img, cmap, name) in enumerate(panels):
            ax = axes[r, c]
            if cmap is None:
                ax.imshow(img)
            elif cmap == 'turbo':
                ax.imshow(img, cmap=cmap, vmin=d_min, vmax=vmax)
            elif cmap == 'magma':
                ax.imshow(img, cmap=cmap, vmin=0, vmax=0.3)
            else:
                ax.imshow(img, cmap=cmap, vmin=0, vmax=1)
            ax.set_title(name, fontsize=8)
            ax.axis('off')
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    _atomic_savefig(fig, path)
    plt.close(fig)


def _atomic_savefig(fig, path: str) -> None:
    tmp = f'{path}.tmp.png'
    fig.savefig(tmp, dpi=90)
    os.replace(tmp, path)


def plot_curves(history: Dict, path: str, reference: Optional[Dict] = None) -> None:
    """PNG with the training loss (raw and smoothed, per term) and the validation metrics over steps.

    ``reference``: validation results of the classical model, drawn as horizontal lines."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    tr = history.get('train', [])
    if tr:
        steps = np.array([t['step'] for t in tr])
        for key, colour in (('loss', 'k'), ('nll_full', 'tab:blue'), ('nll_meas_q', 'tab:orange')):
            y = np.array([t.get(key, np.nan) for t in tr], np.float64)
            axes[0].plot(steps, y, color=colour, alpha=0.25, lw=0.8)
            k = max(1, min(25, len(y) // 10))
            if len(y) >= k:
                sm = np.convolve(y, np.ones(k) / k, mode='valid')
                axes[0].plot(steps[k - 1:], sm, color=colour, lw=1.6, label=key)
        axes[0].set_xlabel('step')
        axes[0].set_ylabel('NLL (nats)')
        axes[0].set_title('training loss')
        axes[0].legend(fontsize=8)
        axes[0].grid(alpha=0.3)
    va = history.get('val', [])
    if va:
        steps = np.array([v['step'] for v in va])
        for mode, colour in (('none', 'tab:gray'), ('global', 'tab:green'), ('knet', 'tab:red')):
            y = [v['metrics'].get(f'net_{mode}', {}).get('abs_rel', np.nan) for v in va]
            axes[1].plot(steps, y, 'o-', color=colour, label=f'net {mode}')
            yn = np.array([v['metrics'].get(f'noisy_net_{mode}', {}).get('abs_rel', np.nan) for v in va], np.float64)
            if np.isfinite(yn).any():
                axes[1].plot(steps, yn, 'x--', color=colour, label=f'net {mode}, noisy poses')
            for key, marker in ((stream_metric_key(mode, False), 'D-'), (stream_metric_key(mode, True), 'D:')):
                ys = np.array([v['metrics'].get(key, {}).get('abs_rel', np.nan) for v in va], np.float64)
                if np.isfinite(ys).any():
                    axes[1].plot(steps, ys, marker, color=colour, mfc='none',
                                 label=f'net {mode}, streamed' + (', noisy poses' if 'noisy' in key else ''))
            y2 = [v['metrics'].get(f'net_{mode}', {}).get('nll_full', np.nan) for v in va]
            axes[2].plot(steps, y2, 'o-', color=colour, label=f'net {mode} (full res)')
        y3 = [v['metrics'].get('net_knet', {}).get('nll_meas_q', np.nan) for v in va]
        axes[2].plot(steps, y3, 's--', color='tab:orange', label='net measurement (1/4 res, before filter)')
        if reference:
            for mode, ls in (('none', ':'), ('global', '--')):
                ref = reference.get(f'classical_{mode}')
                if ref:
                    axes[1].axhline(ref['abs_rel'], color='tab:purple', ls=ls, label=f'classical {mode}')
                    axes[2].axhline(ref['nll_filtered_q'], color='tab:purple', ls=ls, label=f'classical {mode} (1/4)')
        axes[1].set_title('validation abs_rel (held-out seeds)')
        axes[2].set_title('validation NLL of GT')
        for ax in axes[1:]:
            ax.set_xlabel('step')
            ax.legend(fontsize=7)
            ax.grid(alpha=0.3)
    fig.tight_layout()
    _atomic_savefig(fig, path)
    plt.close(fig)
