"""Sharper depth: sub-plane readout (dpv.subplane_index) and the colour-guided edge filter (edge_filter.py)."""
from __future__ import annotations

import torch

from dpv_sensor.core import dpv
from dpv_sensor.core.edge_filter import joint_weighted_median


def _gaussian_logp(centres_hw: torch.Tensor, D: int = 32, sigma: float = 0.35) -> torch.Tensor:
    k = torch.arange(D, dtype=torch.float64).reshape(1, D, 1, 1)
    return torch.log_softmax(-(k - centres_hw[None, None]) ** 2 / (2 * sigma ** 2), 1)


def test_subplane_finds_a_peak_between_planes_where_the_readouts_snap_to_planes():
    centres = torch.linspace(10.0, 14.0, 41, dtype=torch.float64).reshape(1, 41)   # a slanted surface
    logp = _gaussian_logp(centres)
    depths = dpv.depth_planes(0.5, 5.0, 32, dtype=torch.float64)
    median = dpv.quantile_index(logp)
    # a narrow peak: the median lags the surface by up to ~0.3 plane and snaps back at every plane (terraces) ...
    assert (median[0] - centres[0]).abs().max() > 0.15
    # ... the parabola through the log-probabilities recovers the centre (exact for a Gaussian in the index)
    refined = dpv.subplane_index(logp, median)
    assert torch.allclose(refined[0], centres[0], atol=1e-6)
    # the depth form agrees
    d = dpv.subplane_depth(logp, depths, dpv.index_to_depth(median, 0.5, 5.0, 32))
    assert torch.allclose(dpv.depth_to_index(d, 0.5, 5.0, 32)[0], centres[0], atol=1e-6)


def test_subplane_leaves_flat_and_wide_dpvs_and_nan_alone():
    flat = dpv.uniform_log(1, 16, 2, 3, dtype=torch.float64)
    idx = torch.full((1, 2, 3), 7.3, dtype=torch.float64)
    assert torch.equal(dpv.subplane_index(flat, idx), idx)
    # a wide peak: the 3-plane mass is small, so the readout moves only a little towards the vertex
    wide = _gaussian_logp(torch.full((1, 1), 7.5, dtype=torch.float64), D=16, sigma=4.0)
    i0 = dpv.quantile_index(wide)
    assert (dpv.subplane_index(wide, i0) - i0).abs().max() < 0.05
    nan = torch.full((1, 1, 1), float('nan'), dtype=torch.float64)
    assert torch.isnan(dpv.subplane_index(wide, nan)).all()


def _step_scene(h=24, w=40, col=20, blur=4):
    """A depth step 1 m | 2 m whose estimate is blurred over ``blur`` px each side; the colour edge is sharp."""
    u = torch.arange(w, dtype=torch.float64)
    t = ((u - (col - 0.5)) / (2 * blur) + 0.5).clamp(0, 1)                 # ramp in inverse depth
    inv = (1.0 - t) * 1.0 + t * 0.5
    depth = (1.0 / inv).expand(h, w)[None].clone()
    image = torch.zeros(1, 3, h, w, dtype=torch.float64)
    image[:, :, :, col:] = 0.8
    image[:, 0] += 0.05
    truth = torch.where(u < col, torch.tensor(1.0, dtype=torch.float64), torch.tensor(2.0, dtype=torch.float64))
    return depth, image, truth.expand(h, w)[None]


def test_weighted_median_moves_a_blurred_depth_step_onto_the_colour_edge():
    depth, image, truth = _step_scene()
    out = joint_weighted_median(depth, torch.ones_like(depth), image, radius=6, step=2)
    before = ((depth - truth).abs() / truth).mean()
    after = ((out - truth).abs() / truth).mean()
    assert after < 0.5 * before
    # two pixels or more from the colour edge, each side has its own depth again
    assert torch.allclose(out[0, :, 12:18], torch.tensor(1.0, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(out[0, :, 22:28], torch.tensor(2.0, dtype=torch.float64), atol=1e-9)


def test_weighted_median_replaces_an_unsure_outlier_and_keeps_nan():
    h, w = 12, 12
    depth = torch.full((1, h, w), 1.5, dtype=torch.float64)
    depth[0, 5, 5] = 4.0
    depth[0, 2, 2] = float('nan')
    weight = torch.ones_like(depth)
    out = joint_weighted_median(depth, weight, torch.full((1, 3, h, w), 0.3, dtype=torch.float64), radius=2, step=1)
    assert out[0, 5, 5] == 1.5 and torch.isnan(out[0, 2, 2])
    assert joint_weighted_median(depth, weight, torch.rand(1, 3, h, w, dtype=torch.float64), radius=0) is depth
    flat = torch.full((1, h, w), 2.0, dtype=torch.float64)
    assert torch.equal(joint_weighted_median(flat, torch.rand(1, h, w, dtype=torch.float64),
                                             torch.rand(1, 3, h, w, dtype=torch.float64)), flat)
