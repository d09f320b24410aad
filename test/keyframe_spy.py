"""What the estimator published in an offline run, recorded from inside, and its abs_rel computed here by hand: the
expected values of tests of tools that score such runs themselves (the trainer's streaming validation, the selection
and error-breakdown studies), independent of the runner and the metrics module they use."""
from __future__ import annotations

import numpy as np


class KeyframeSpy:
    """Records, per Pipeline, every keyframe output its push returns while the spy is installed."""

    def __init__(self, monkeypatch):
        from dpv_sensor.stream.pipeline import Pipeline
        self._by_pipe: dict = {}
        real = Pipeline.push

        def push(pipe, frame):
            res = real(pipe, frame)
            outputs = self._by_pipe.setdefault(id(pipe), (pipe, []))[1]
            if res.output is not None and res.output.is_keyframe:
                outputs.append(res.output)
            return res
        monkeypatch.setattr(Pipeline, 'push', push)

    def runs(self) -> list:
        """[(pipeline, [keyframe outputs])] in the order the pipelines first pushed a frame."""
        return list(self._by_pipe.values())


def scored_pixels(outputs, seq, estimator):
    """Per output: (prediction, GT) of its scored pixels, float64. GT of the output's frame (found by stamp) taken at
    the depth map's size by nearest pixel centres; scored: GT finite, > 0 and inside the estimator's depth range, and a
    prediction (finite, > 0)."""
    lo, hi = estimator.d_min, estimator.d_max
    index = {float(seq.stamp(i)): i for i in range(len(seq))}
    for out in outputs:
        pred = np.asarray(out.depth_hw, np.float64)
        gt_full = np.asarray(seq.depth(index[out.stamp]), np.float64)
        (h, w), (H, W) = pred.shape, gt_full.shape
        rows = np.minimum(((np.arange(h) + 0.5) * H / h).astype(int), H - 1)
        cols = np.minimum(((np.arange(w) + 0.5) * W / w).astype(int), W - 1)
        gt = gt_full[rows][:, cols]
        with np.errstate(invalid='ignore'):
            m = np.isfinite(gt) & (gt > 0) & (gt >= lo) & (gt <= hi) & np.isfinite(pred) & (pred > 0)
        yield pred[m], gt[m]


def frame_mean_abs_rel(outputs, seq, estimator) -> float:
    """The mean over frames of each frame's mean |pred - gt| / gt, predictions clipped to the depth range."""
    lo, hi = estimator.d_min, estimator.d_max
    per_frame = [np.mean(np.abs(np.clip(p, lo, hi) - g) / g) if p.size else np.nan
                 for p, g in scored_pixels(outputs, seq, estimator)]
    return float(np.nanmean(per_frame))


def pooled_abs_rel(outputs, seq, estimator) -> float:
    """|pred - gt| / gt over the scored pixels of all outputs together (no clipping)."""
    pairs = list(scored_pixels(outputs, seq, estimator))
    return float(sum(np.sum(np.abs(p - g) / g) for p, g in pairs) / sum(p.size for p, _ in pairs))
