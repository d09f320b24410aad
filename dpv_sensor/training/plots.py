"""The trainer's figures: the validation montage and the loss / validation curves, and the ``adapt`` tool's report
(PNG, written atomically)."""
from __future__ import annotations

import os
from typing import Dict, List, Optional

import numpy as np

from dpv_sensor.training.stream_validation import stream_metric_key

__all__ = ['save_montage', 'plot_curves', 'save_adapt_report']

#: every axes title at the axes' top edge, given explicitly: left unset, matplotlib measures each axes' tick labels at
#: every draw to lift its title above them (a third of these figures' drawing time), and none of these axes has any
#: at its top, so the figures come out the same, byte for byte
_TITLE_Y = 1.0


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
            ax.set_title(name, fontsize=8, y=_TITLE_Y)
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
        axes[0].set_title('training loss', y=_TITLE_Y)
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
        axes[1].set_title('validation abs_rel (held-out seeds)', y=_TITLE_Y)
        axes[2].set_title('validation NLL of GT', y=_TITLE_Y)
        for ax in axes[1:]:
            ax.set_xlabel('step')
            ax.legend(fontsize=7)
            ax.grid(alpha=0.3)
    fig.tight_layout()
    _atomic_savefig(fig, path)
    plt.close(fig)


def save_adapt_report(path: str, result, gt: Optional[Dict], d_min: float, d_max: float, title: str = '') -> None:
    """The ``adapt`` tool's PNG: the loss per step (raw and smoothed) with the held-out scores of the base and the
    adapted weights, and per held-out example a row image | depth before | depth after | confidence before |
    confidence after (``result``: :class:`dpv_sensor.training.adapt_loop.AdaptResult`; ``gt``: the tool's
    ground-truth scores, quoted in the title when given)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    rows = len(result.examples)
    fig = plt.figure(figsize=(13, 3.2 + 2.2 * rows))
    grid = fig.add_gridspec(1 + rows, 5, height_ratios=[1.4] + [1.0] * rows)
    ax = fig.add_subplot(grid[0, :3])
    hist = result.history
    if hist:
        steps = np.array([h['step'] for h in hist])
        for key, colour in (('loss', 'k'), ('photometric', 'tab:blue'), ('photometric_q', 'tab:orange'),
                            ('evidence', 'tab:green'), ('evidence_q', 'tab:olive'), ('penalty', 'tab:gray'),
                            ('distill', 'tab:purple'), ('nll', 'tab:blue'), ('anchor', 'tab:red')):
            y = np.array([h.get(key, np.nan) for h in hist], np.float64)
            if not np.isfinite(y).any():
                continue
            ax.plot(steps, y, color=colour, alpha=0.25, lw=0.8)
            k = max(1, min(25, len(y) // 10))
            if len(y) >= k:
                ax.plot(steps[k - 1:], np.convolve(y, np.ones(k) / k, mode='valid'), color=colour, lw=1.6, label=key)
        ax.legend(fontsize=8)
    ax.set_xlabel('step')
    ax.set_title('training loss', fontsize=9, y=_TITLE_Y)
    ax.grid(alpha=0.3)
    ax2 = fig.add_subplot(grid[0, 3:])
    ax2.bar(['base', 'adapted'], [result.base_score, result.adapted_score], color=['tab:gray', 'tab:green'])
    v = result.verdict
    beside = ''.join(f"\n{k} beside it: {b['base']:.5f} -> {b['adapted']:.5f}"
                     for k, b in (getattr(result, 'beside', None) or {}).items())
    ax2.set_title(f'held-out {result.score_kind} score (lower is better)\n{v.runs_better} of {v.runs} runs better, '
                  f'sign-flip p {v.p_value:.3f}{beside}', fontsize=9, y=_TITLE_Y)
    lo = min(result.base_score, result.adapted_score)
    hi = max(result.base_score, result.adapted_score)
    if np.isfinite(lo) and hi > 0:
        ax2.set_ylim(max(0.0, lo - 2 * (hi - lo) - 0.02 * hi), hi + 0.5 * (hi - lo) + 0.02 * hi)
    for r, ex in enumerate(result.examples):
        panels = [(np.clip(ex['image'], 0, 1), None, f"held-out frame {ex['frame']}"),
                  (ex['depth'], 'turbo', 'depth, base'), (ex['depth_adapted'], 'turbo', 'depth, adapted'),
                  (ex['confidence'], 'viridis', 'confidence, base'),
                  (ex['confidence_adapted'], 'viridis', 'confidence, adapted')]
        vmax = float(np.percentile(ex['depth'], 98))
        for c, (img, cmap, name) in enumerate(panels):
            a = fig.add_subplot(grid[1 + r, c])
            if cmap is None:
                a.imshow(img)
            elif cmap == 'turbo':
                a.imshow(img, cmap=cmap, vmin=d_min, vmax=max(vmax, d_min + 0.1))
            else:
                a.imshow(img, cmap=cmap, vmin=0, vmax=1)
            a.set_title(name, fontsize=8, y=_TITLE_Y)
            a.axis('off')
    if gt:
        nan = float('nan')
        b, ad = gt.get('base', {}), gt.get('adapted', {})
        title += (f"\nheld-out GT: abs_rel {b.get('abs_rel', nan):.4f} -> {ad.get('abs_rel', nan):.4f}, "
                  f"delta1 {b.get('delta1', nan):.3f} -> {ad.get('delta1', nan):.3f}, "
                  f"ECE {b.get('ece') or nan:.3f} -> {ad.get('ece') or nan:.3f}")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    _atomic_savefig(fig, path)
    plt.close(fig)
