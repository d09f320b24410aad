"""Tests of dpv_sensor.core.dpv, with values computed by hand.

Hand example used throughout: d_min = 1, d_max = 4, D = 3 -> inverse depths 1, 0.625, 0.25,
i.e. planes at 1, 1.6 and 4 m.
"""
import math

import numpy as np
import pytest
import torch

from dpv_sensor.core import dpv

DT = torch.float64


def _logp(probs_d, h=1, w=1):
    p = torch.tensor(probs_d, dtype=DT).reshape(1, -1, 1, 1).expand(1, -1, h, w)
    return torch.log(p.clamp_min(1e-300))


def test_depth_planes_by_hand():
    planes = dpv.depth_planes(1.0, 4.0, 3, dtype=DT)
    assert torch.allclose(planes, torch.tensor([1.0, 1.6, 4.0], dtype=DT))
    p = dpv.depth_planes(0.3, 8.0, 64)
    assert p.dtype == torch.float32 and p[0].item() == pytest.approx(0.3) and p[-1].item() == pytest.approx(8.0)
    assert (p[1:] > p[:-1]).all()
    inv = 1.0 / p.double()
    assert torch.allclose(inv[1:] - inv[:-1], (inv[1] - inv[0]).expand(63), rtol=1e-5)
    with pytest.raises(ValueError):
        dpv.depth_planes(2.0, 1.0, 8)


def test_depth_to_index_by_hand():
    idx = dpv.depth_to_index(torch.tensor([1.0, 1.6, 4.0, 2.0, 0.5, 8.0], dtype=DT), 1.0, 4.0, 3)
    # 2 m: (1 - 0.5) / 0.75 * 2 = 4/3 ; 0.5 m: (1 - 2)/0.75*2 = -8/3 ; 8 m: (1 - 0.125)/0.75*2 = 7/3
    assert torch.allclose(idx, torch.tensor([0.0, 1.0, 2.0, 4 / 3, -8 / 3, 7 / 3], dtype=DT))
    assert torch.isnan(dpv.depth_to_index(torch.tensor([0.0]), 1.0, 4.0, 3)).all()
    assert torch.allclose(dpv.index_to_depth(idx[:4], 1.0, 4.0, 3), torch.tensor([1.0, 1.6, 4.0, 2.0], dtype=DT))


def test_normalize_and_uniform():
    x = torch.randn(2, 5, 3, 4, dtype=DT)
    lp = dpv.normalize_log(x)
    assert torch.allclose(lp.exp().sum(1), torch.ones(2, 3, 4, dtype=DT))
    assert torch.allclose(dpv.uniform_log(1, 5, 2, 2, dtype=DT), torch.full((1, 5, 2, 2), -math.log(5), dtype=DT))
    c = dpv.clamp_log(torch.tensor([0.0, -1000.0], dtype=DT).reshape(1, 2, 1, 1))
    assert c.min().item() >= dpv.LOG_FLOOR - 1e-9 and torch.allclose(c.exp().sum(1), torch.ones(1, 1, 1, dtype=DT))


def test_expected_depth_by_hand():
    planes = dpv.depth_planes(1.0, 4.0, 3, dtype=DT)
    assert dpv.expected_depth(_logp([0, 1, 0]), planes).item() == pytest.approx(1.6)
    assert dpv.expected_depth(_logp([1, 0, 0]), planes).item() == pytest.approx(1.0)
    assert dpv.expected_depth(_logp([0.5, 0, 0.5]), planes).item() == pytest.approx(2.5)
    assert dpv.expected_depth(_logp([0.2, 0.3, 0.5]), planes).item() == pytest.approx(0.2 + 0.48 + 2.0)
    # one-hot helper
    oh = dpv.one_hot_log(torch.tensor([[[2, 0]]]), 3)
    assert torch.allclose(dpv.expected_depth(oh, planes.float()), torch.tensor([[[4.0, 1.0]]]), atol=1e-6)
    assert torch.allclose(dpv.argmax_depth(oh, planes.float()), torch.tensor([[[4.0, 1.0]]]))


def test_confidence_by_hand():
    planes = dpv.depth_planes(1.0, 10.0, 10, dtype=DT)
    # uniform: the +-1 bin window lies inside the volume -> mass 2/D
    uni = _logp([0.1] * 10)
    f = dpv.expected_index(uni, planes).item()
    assert 1.0 < f < 8.0
    assert dpv.confidence(uni, planes).item() == pytest.approx(0.2)
    # one-hot anywhere (also at the ends) -> 1
    for k in (0, 4, 9):
        p = [0.0] * 10
        p[k] = 1.0
        assert dpv.confidence(_logp(p), planes).item() == pytest.approx(1.0)
    # split between two neighbouring planes: the estimate f lies between them (a little beyond 3.5,
    # since the mean of depth exceeds the mean of inverse depth); the window [f-1, f+1] covers all of
    # plane 4 and plane 3 but for f - 3.5
    lp = _logp([0, 0, 0, 0.5, 0.5, 0, 0, 0, 0, 0])
    f = dpv.expected_index(lp, planes).item()
    assert 3.5 < f < 3.6
    assert dpv.confidence(lp, planes).item() == pytest.approx(0.5 * (1 - (f - 3.5)) + 0.5)
    assert dpv.confidence(lp, planes).item() > 0.95
    # split between planes 3 and 5: estimate f = 4 + delta, window covers 0.5 -+ delta of each -> 0.5
    assert dpv.confidence(_logp([0, 0, 0, 0.5, 0, 0.5, 0, 0, 0, 0]), planes).item() == pytest.approx(0.5)
    # 0.8 at plane 4 (1.667 m) and 0.2 at plane 0 (1 m): d_hat = 1.5333 m, f = 3.478; the window
    # [2.478, 4.478] holds 0.978 of plane 4 and nothing of plane 0
    lp = _logp([0.2, 0, 0, 0, 0.8, 0, 0, 0, 0, 0])
    assert dpv.expected_depth(lp, planes).item() == pytest.approx(0.2 + 0.8 / 0.6)
    f = dpv.expected_index(lp, planes).item()
    assert f == pytest.approx((1.0 - 1.0 / (0.2 + 0.8 / 0.6)) / 0.9 * 9)
    assert dpv.confidence(lp, planes).item() == pytest.approx(0.8 * (f + 1.0 - 3.5))


def test_ratio_confidence_by_hand():
    """Planes 1, 4/3, 2, 4 m (inverse depths 1, 0.75, 0.5, 0.25; index f(d) = 4 (1 - 1/d)). Estimate 2 m
    (index 2), ratio 1.25: the band [1.6, 2.5] m is the index window [1.5, 2.4], i.e. 0.9 of plane 2."""
    planes = dpv.depth_planes(1.0, 4.0, 4, dtype=DT)
    assert torch.allclose(planes, torch.tensor([1.0, 4.0 / 3.0, 2.0, 4.0], dtype=DT))
    d_hat = torch.full((1, 1, 1), 2.0, dtype=DT)
    conf = lambda probs: dpv.ratio_confidence(_logp(probs), planes, d_hat).item()   # noqa: E731
    assert conf([0, 0, 1, 0]) == pytest.approx(0.9)
    assert conf([0.25] * 4) == pytest.approx(0.25 * 0.9)
    assert conf([0, 0, 0.5, 0.5]) == pytest.approx(0.45)
    assert conf([0.5, 0.5, 0, 0]) == pytest.approx(0.0)
    # a wider band: ratio 2 -> [1, 4] m = index window [0, 3]: half of plane 0, planes 1 and 2, half of plane 3
    assert dpv.ratio_confidence(_logp([0.1, 0.2, 0.3, 0.4]), planes, d_hat, ratio=2.0).item() == \
        pytest.approx(0.05 + 0.2 + 0.3 + 0.2)
    # the band beyond the last plane holds nothing: estimate 4 m, band [3.2, 5] m = index [2.75, 3.2]
    far = torch.full((1, 1, 1), 4.0, dtype=DT)
    assert dpv.ratio_confidence(_logp([0, 0, 0, 1]), planes, far).item() == pytest.approx(0.45)
    with pytest.raises(ValueError, match='ratio'):
        dpv.ratio_confidence(_logp([0.25] * 4), planes, d_hat, ratio=1.0)


def test_ratio_confidence_is_strict_far_where_the_plane_window_is_lenient():
    """The same DPV shape (mass on three neighbouring planes) near and far: the +-1-plane confidence is the
    same, the ratio confidence is lower far away, where three planes span more than a factor 1.25."""
    planes = dpv.depth_planes(0.3, 8.0, 32, dtype=DT)
    res = {}
    for k in (5, 29):
        p = [0.0] * 32
        p[k - 1], p[k], p[k + 1] = 0.25, 0.5, 0.25
        lp = _logp(p)
        d = dpv.depth_estimate(lp, planes, 'median')
        res[k] = (dpv.confidence(lp, planes, depth_bhw=d).item(), dpv.ratio_confidence(lp, planes, d).item())
    assert res[5][0] == pytest.approx(res[29][0])
    assert res[5][1] > 0.99 and res[29][1] < 0.65
    for mode, (plane_c, ratio_c) in (('plane', res[29]), ('ratio', res[29])):
        p = [0.0] * 32
        p[28], p[29], p[30] = 0.25, 0.5, 0.25
        lp = _logp(p)
        d = dpv.depth_estimate(lp, planes, 'median')
        got = dpv.published_confidence(lp, planes, d, mode).item()
        assert got == pytest.approx(plane_c if mode == 'plane' else ratio_c)
    with pytest.raises(ValueError, match='confidence'):
        dpv.published_confidence(lp, planes, d, 'entropy')


def test_confidence_peaked_beats_flat_and_batched():
    planes = dpv.depth_planes(0.5, 5.0, 16, dtype=DT)
    logits = torch.zeros(2, 16, 3, 4, dtype=DT)
    logits[1, 7] = 10.0
    c = dpv.confidence(dpv.normalize_log(logits), planes)
    assert c.shape == (2, 3, 4)
    assert (c[0] < 0.2).all() and (c[1] > 0.99).all()
    assert ((c >= 0) & (c <= 1)).all()


def test_nll_by_hand():
    planes = dpv.depth_planes(1.0, 4.0, 3, dtype=DT)
    lp = _logp([0.2, 0.3, 0.5])
    # GT exactly on plane 1
    assert dpv.nll(lp, planes, torch.tensor([[[1.6]]], dtype=DT)).item() == pytest.approx(-math.log(0.3))
    # GT at fractional index 1.25: inverse depth 1 - 0.75*1.25/2 = 0.53125 -> 1.882352... m
    gt = torch.tensor([[[1.0 / 0.53125]]], dtype=DT)
    expect = -(0.75 * math.log(0.3) + 0.25 * math.log(0.5))
    assert dpv.nll(lp, planes, gt).item() == pytest.approx(expect)
    # GT on the last plane (upper end) and on the first plane
    assert dpv.nll(lp, planes, torch.tensor([[[4.0]]], dtype=DT)).item() == pytest.approx(-math.log(0.5))
    assert dpv.nll(lp, planes, torch.tensor([[[1.0]]], dtype=DT)).item() == pytest.approx(-math.log(0.2))


def test_nll_masks_and_reductions():
    planes = dpv.depth_planes(1.0, 4.0, 3, dtype=DT)
    lp = _logp([0.2, 0.3, 0.5], 1, 4)
    gt = torch.tensor([[[1.6, 0.0, 9.0, 1.0]]], dtype=DT)           # valid, invalid 0, beyond d_max, valid
    per = dpv.nll(lp, planes, gt, reduction='none')
    assert torch.allclose(per, torch.tensor([[[-math.log(0.3), 0.0, 0.0, -math.log(0.2)]]], dtype=DT))
    mean = dpv.nll(lp, planes, gt)
    assert mean.item() == pytest.approx((-math.log(0.3) - math.log(0.2)) / 2)
    assert dpv.nll(lp, planes, gt, reduction='sum').item() == pytest.approx(-math.log(0.3) - math.log(0.2))
    mask = torch.tensor([[[False, True, True, True]]])
    assert dpv.nll(lp, planes, gt, mask).item() == pytest.approx(-math.log(0.2))
    # nothing valid -> 0, still differentiable
    lpg = lp.clone().requires_grad_(True)
    z = dpv.nll(lpg, planes, torch.zeros(1, 1, 4, dtype=DT))
    z.backward()
    assert z.item() == 0.0 and torch.equal(lpg.grad, torch.zeros_like(lpg))
    with pytest.raises(ValueError):
        dpv.nll(lp, planes, gt, reduction='max')
    vm = dpv.valid_depth_mask(torch.tensor([0.0, 0.99, 1.0, 4.0, 4.01, float('nan')]), 1.0, 4.0)
    assert vm.tolist() == [False, False, True, True, False, False]


def test_nll_gradient_is_softmax_minus_two_hot_target():
    planes = dpv.depth_planes(1.0, 4.0, 3, dtype=DT)
    logits = torch.tensor([0.1, -0.4, 0.7], dtype=DT).reshape(1, 3, 1, 1).requires_grad_(True)
    gt = torch.tensor([[[1.0 / 0.53125]]], dtype=DT)                  # index 1.25
    dpv.nll(dpv.normalize_log(logits), planes, gt).backward()
    target = torch.tensor([0.0, 0.75, 0.25], dtype=DT)
    assert torch.allclose(logits.grad.reshape(3), torch.softmax(logits.detach().reshape(3), 0) - target)


def test_gradcheck_depth_and_confidence():
    planes = dpv.depth_planes(0.5, 4.0, 6, dtype=DT)
    x = torch.randn(1, 6, 2, 3, dtype=DT, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: dpv.expected_depth(dpv.normalize_log(t), planes), (x,))
    assert torch.autograd.gradcheck(lambda t: dpv.confidence(dpv.normalize_log(t), planes), (x,), atol=1e-5)


# ------------------------------------------------------------------ readouts (median, relative)

def test_median_by_hand():
    planes = dpv.depth_planes(1.0, 4.0, 3, dtype=DT)                   # 1, 1.6, 4 m
    # one-hot at plane 1: its mass covers index [0.5, 1.5], the CDF reaches 0.5 at index 1
    assert dpv.quantile_index(_logp([0, 1, 0])).item() == pytest.approx(1.0)
    assert dpv.median_depth(_logp([0, 1, 0]), planes).item() == pytest.approx(1.6)
    # half on plane 0, half on plane 1: the median is the boundary between them, index 0.5
    assert dpv.quantile_index(_logp([0.5, 0.5, 0])).item() == pytest.approx(0.5)
    # 0.2 / 0.2 / 0.6: the CDF is 0.4 at index 1.5 and rises 0.6 per index after, 0.5 at 1.5 + 1/6
    assert dpv.quantile_index(_logp([0.2, 0.2, 0.6])).item() == pytest.approx(1.5 + 1.0 / 6.0)
    # the quantile never leaves [0, D - 1]
    assert dpv.quantile_index(_logp([1, 0, 0])).item() == pytest.approx(0.0)
    assert dpv.quantile_index(_logp([0, 0, 1]), q=0.99).item() == pytest.approx(2.0)


def _quantile_by_full_cdf(logp_bdhw, q):
    """The quantile as its docstring defines it, the whole running-sum CDF stored (the reference)."""
    D = logp_bdhw.shape[1]
    p = torch.exp(logp_bdhw)
    acc, planes = p[:, 0], [p[:, 0]]
    for k in range(1, D):
        acc = acc + p[:, k]
        planes.append(acc)
    cdf = torch.stack(planes, 1)
    k = (cdf < q).sum(1, keepdim=True).clamp(max=D - 1)
    before = torch.where(k > 0, cdf.gather(1, (k - 1).clamp(min=0)), torch.zeros_like(cdf[:, :1]))
    pk = p.gather(1, k).clamp_min(torch.finfo(p.dtype).tiny)
    return (k.to(p.dtype) - 0.5 + ((q - before) / pk).clamp(0.0, 1.0))[:, 0].clamp(0.0, D - 1.0)


@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
def test_quantile_equals_the_full_cdf_bit_for_bit(dtype):
    # peaked, flat, mass short of q on the last plane (the clamp to D - 1), NaN and -inf planes, one plane
    g = torch.Generator().manual_seed(3)
    logp = dpv.normalize_log(4.0 * torch.randn(2, 9, 5, 6, generator=g, dtype=dtype))
    logp[0, :, 0, 0] = dpv.normalize_log(torch.zeros(1, 9, 1, 1, dtype=dtype))[0, :, 0, 0]
    logp[0, :, 0, 1] = float('-inf')
    logp[0, -1, 0, 1] = math.log(0.4)
    logp[0, 3:, 0, 2] = float('nan')
    logp[1, 2, 1, 1] = float('-inf')
    for q in (0.5, 0.1, 0.99):
        expected = _quantile_by_full_cdf(logp, q)
        got = dpv.quantile_index(logp, q)
        assert torch.equal(got.isnan(), expected.isnan())
        assert torch.equal(got.nan_to_num(-1.0), expected.nan_to_num(-1.0)), q
    single = dpv.normalize_log(torch.randn(1, 1, 2, 2, generator=g, dtype=dtype))
    assert torch.equal(dpv.quantile_index(single), _quantile_by_full_cdf(single, 0.5))


def test_quantile_gradient():
    x = torch.randn(1, 5, 2, 3, dtype=DT, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: dpv.quantile_index(dpv.normalize_log(t)), (x,))


def test_relative_readout_by_hand():
    planes = dpv.depth_planes(1.0, 2.0, 2, dtype=DT)                   # 1 m and 2 m
    # p = (0.5, 0.5) reweighted by 1/d: (2/3, 1/3); the CDF reaches 0.5 inside plane 0's bin at
    # index -0.5 + 0.5 / (2/3) = 0.25, i.e. inverse depth 1 - 0.5 * 0.25 = 0.875
    assert dpv.relative_depth(_logp([0.5, 0.5]), planes).item() == pytest.approx(1.0 / 0.875)
    assert dpv.expected_depth(_logp([0.5, 0.5]), planes).item() == pytest.approx(1.5)
    # a one-hot DPV reads the same depth with every readout
    planes = dpv.depth_planes(1.0, 4.0, 3, dtype=DT)
    for r in dpv.READOUTS:
        assert dpv.depth_estimate(_logp([0, 1, 0]), planes, r).item() == pytest.approx(1.6)
    with pytest.raises(ValueError, match='readout'):
        dpv.depth_estimate(_logp([0, 1, 0]), planes, 'mode')


def test_relative_readout_minimises_the_expected_relative_error():
    """Brute force over a fine depth grid: sum_k p_k |x - d_k| / d_k is smallest within half a plane of
    the 'relative' readout (the discrete minimiser sits on a plane; the readout interpolates in its bin)."""
    torch.manual_seed(3)
    D = 16
    planes = dpv.depth_planes(0.3, 8.0, D, dtype=DT)
    lp = dpv.normalize_log(2.0 * torch.randn(1, D, 1, 8, dtype=DT))
    x = torch.linspace(0.3, 8.0, 20001, dtype=DT)
    p = lp.exp()[0, :, 0].T                                           # 8, D
    cost = (p[:, None, :] * (x[None, :, None] - planes).abs() / planes).sum(-1)    # 8, grid
    best = x[cost.argmin(1)]
    got = dpv.relative_depth(lp, planes)[0, 0]
    gi = dpv.depth_to_index(got, 0.3, 8.0, D)
    bi = dpv.depth_to_index(best, 0.3, 8.0, D)
    assert ((gi - bi).abs() <= 0.5 + 1e-6).all(), (gi, bi)


def test_two_mode_dpv_mean_is_a_flying_pixel_median_is_not():
    planes = dpv.depth_planes(1.0, 4.0, 10, dtype=DT)
    lp = _logp([0, 0, 0.6, 0, 0, 0, 0, 0, 0.4, 0])
    mean_idx = dpv.expected_index(lp, planes).item()
    assert 3.0 < mean_idx < 7.0                                       # between the modes, on neither
    assert dpv.confidence(lp, planes, 'mean').item() == pytest.approx(0.0, abs=1e-9)
    for r in ('median', 'relative'):
        assert abs(dpv.estimate_index(lp, planes, r).item() - 2.0) <= 0.5
        assert dpv.confidence(lp, planes, r).item() >= 0.6 - 1e-9    # the near mode's mass
        given = dpv.confidence(lp, planes, depth_bhw=dpv.depth_estimate(lp, planes, r))
        assert given.item() == pytest.approx(dpv.confidence(lp, planes, r).item())


def test_gradcheck_readouts():
    planes = dpv.depth_planes(0.5, 4.0, 6, dtype=DT)
    x = torch.randn(1, 6, 2, 3, dtype=DT, requires_grad=True)
    for r in ('median', 'relative'):
        assert torch.autograd.gradcheck(lambda t: dpv.depth_estimate(dpv.normalize_log(t), planes, r), (x,))
    d_hat = torch.tensor([[[0.7, 1.1, 1.9], [2.5, 3.3, 0.6]]], dtype=DT)
    assert torch.autograd.gradcheck(lambda t: dpv.ratio_confidence(dpv.normalize_log(t), planes, d_hat), (x,))


def test_auto_readout_depends_on_the_measurement_model():
    from dpv_sensor.params import SPECS
    spec = [p for p in SPECS if p.name == 'depth_readout'][0]
    assert set(spec.choices) == set(dpv.READOUT_CHOICES) and spec.default == dpv.DEFAULT_READOUT
    assert dpv.resolve_readout('auto', learned=True) == 'relative'
    assert dpv.resolve_readout('auto', learned=False) == 'mean'
    assert dpv.resolve_readout('median', learned=False) == 'median'
    with pytest.raises(ValueError, match='readout'):
        dpv.resolve_readout('mode', learned=True)


def test_ratio_confidence_with_an_index_error_integrates_the_gaussian():
    from dpv_sensor.core import dpv as dpv_ops
    from dpv_sensor.core.geometry import inverse_depth_index
    D = 32
    depths = dpv_ops.depth_planes(0.5, 8.0, D)
    logp = torch.full((1, D, 1, 1), -1e4)
    logp[:, 12] = 0.0
    logp = torch.log_softmax(logp, 1)
    d = dpv_ops.index_to_depth(torch.tensor([[[12.0]]]), 0.5, 8.0, D)
    plain = dpv_ops.ratio_confidence(logp, depths, d, 1.25)
    assert float(dpv_ops.ratio_confidence(logp, depths, d, 1.25, torch.zeros(1, 1, 1))) == pytest.approx(float(plain))
    lo = float(inverse_depth_index(d / 1.25, 0.5, 8.0, D))
    hi = float(inverse_depth_index(d * 1.25, 0.5, 8.0, D))
    # by numeric integration: plane 12 uniform over [11.5, 12.5], convolved with N(0, 2^2), inside [lo, hi]
    x = np.linspace(11.5, 12.5, 2001)
    from scipy.stats import norm
    want = np.trapezoid(norm.cdf((hi - x) / 2.0) - norm.cdf((lo - x) / 2.0), x)
    got = float(dpv_ops.ratio_confidence(logp, depths, d, 1.25, torch.full((1, 1, 1), 2.0)))
    assert got == pytest.approx(want, abs=1e-5)
    # never above the plain confidence, falling with sigma, finite for an infinite sigma
    vals = [float(dpv_ops.ratio_confidence(logp, depths, d, 1.25, torch.full((1, 1, 1), s)))
            for s in (0.5, 1.0, 4.0, 16.0, float('inf'))]
    assert all(b <= a + 1e-7 for a, b in zip([float(plain)] + vals, vals)) and math.isfinite(vals[-1])


def test_rescale_depth_by_hand():
    """Planes 0.5-8 m, D = 5: 1/z = 2, 1.53125, 1.0625, 0.59375, 0.125 per metre. All mass on plane 2 (1/z =
    1.0625), scaled by s = 1.0625 / 0.828125 (to 1/z = 0.828125, half way to plane 3 in 1/z): target plane j reads
    the source at 1/z = s / z_j, plane 2 at index 1.3585 and plane 3 at 2.6415, 0.6415 from the mass on either
    side: the mass splits equally between planes 2 and 3. A pixel with s = 1 keeps its values bit for bit."""
    D, d_min, d_max = 5, 0.5, 8.0
    inv = 1.0 / dpv.index_to_depth(torch.arange(D, dtype=torch.float64), d_min, d_max, D)
    assert inv.tolist() == pytest.approx([2.0, 1.53125, 1.0625, 0.59375, 0.125])
    logp = dpv.one_hot_log(torch.tensor([[[2, 2]]]), D, peak=0.0).double()
    z_half = 1.0 / ((inv[2] + inv[3]) / 2)           # the depth half way between planes 2 and 3 in 1/z
    s = torch.tensor([[[math.log(z_half / (1.0 / inv[2])), 0.0]]], dtype=torch.float64)
    out = dpv.rescale_depth(logp, s, d_min, d_max)
    assert torch.equal(out[..., 1], logp[..., 1])
    p = out[0, :, 0, 0].exp()
    scale = float(s[0, 0, 0].exp())
    src_idx = [(2.0 - float(inv[j]) * scale) / (2.0 - 0.125) * (D - 1) for j in range(D)]
    expect = torch.tensor([max(0.0, 1.0 - abs(i - 2.0)) for i in src_idx], dtype=torch.float64)
    expect = (expect + math.exp(dpv.LOG_FLOOR)) / (expect + math.exp(dpv.LOG_FLOOR)).sum()
    np.testing.assert_allclose(p.numpy(), expect.numpy(), atol=1e-9)
    assert float(p.sum()) == pytest.approx(1.0)
    assert float(p[2]) == pytest.approx(0.5, abs=1e-9) and float(p[3]) == pytest.approx(0.5, abs=1e-9)
    assert src_idx[2] == pytest.approx(1.358491, abs=1e-6) and src_idx[3] == pytest.approx(2.641509, abs=1e-6)


def test_rescale_depth_there_and_back_keeps_a_smooth_dpv():
    """A Gaussian in index (sigma 2 planes) scaled by 1.1 and back by 1/1.1 returns within interpolation error; its
    median moves by the scale on the way."""
    D, d_min, d_max = 32, 0.5, 8.0
    depths = dpv.depth_planes(d_min, d_max, D, dtype=torch.float64)
    i = torch.arange(D, dtype=torch.float64)
    logp = torch.log_softmax(-0.5 * ((i - 14.0) / 2.0) ** 2, 0).view(1, D, 1, 1)
    s = torch.full((1, 1, 1), math.log(1.1), dtype=torch.float64)
    there = dpv.rescale_depth(logp, s, d_min, d_max)
    assert float(dpv.median_depth(there, depths) / dpv.median_depth(logp, depths)) == pytest.approx(1.1, rel=0.01)
    back = dpv.rescale_depth(there, -s, d_min, d_max)
    assert float((back.exp() - logp.exp()).abs().max()) < 0.01


def test_rescale_depth_keeps_pixels_without_a_finite_scale_and_broadcasts_a_batch_of_one():
    D, d_min, d_max = 8, 0.5, 8.0
    logp = torch.log_softmax(torch.randn(2, D, 1, 3, generator=torch.Generator().manual_seed(0)), 1)
    s = torch.tensor([[[float('nan'), float('inf'), 0.2]]])
    out = dpv.rescale_depth(logp, s, d_min, d_max)
    assert torch.equal(out[..., :2], logp[..., :2])
    for b in range(2):     # the batch-one scale applies to each DPV as it would alone
        alone = dpv.rescale_depth(logp[b:b + 1], s, d_min, d_max)
        assert torch.equal(out[b:b + 1], alone) and not torch.equal(alone[..., 2], logp[b:b + 1, :, :, 2])
