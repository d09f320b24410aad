"""The label-free losses of the adaptation (dpv_sensor.training.self_supervised) on scenes whose answer is known:
a textured plane at a known depth seen from a translated and rotated source camera."""
import math
import os
import sys

import pytest
import torch

sys.path.insert(0, os.path.dirname(__file__))
from synthetic_planes import intrinsics, render_plane_pair, rot_x, rot_y, se3  # noqa: E402

from dpv_sensor.training import self_supervised as S  # noqa: E402

H, W, Z = 48, 64, 2.5


def _colour(gray_11hw):
    """Three different channels from one grey image (every channel order matters to the error)."""
    g = gray_11hw[:, 0]
    return torch.stack([g, 0.6 * g + 0.2, 1.0 - g], 1).float()


def _pair(T_src_ref, z=Z):
    K = intrinsics(W, H, 55.0)
    ref, src = render_plane_pair(K, K, T_src_ref, z, H, W, tex_scale=0.7)
    return _colour(ref), _colour(src), K.float()


T_MOVE = se3(rot_y(math.radians(1.5)) @ rot_x(math.radians(-1.0)), (0.12, -0.05, 0.04))


def test_photometric_error_by_hand():
    x = torch.rand(1, 3, 10, 12, generator=torch.Generator().manual_seed(0))
    assert S.photometric_error(x, x).abs().max() < 1e-6
    # a constant offset c: L1 = c everywhere; SSIM sees the mean shift only through its luminance term
    c = 0.1
    e = S.photometric_error(x, x + c, alpha=0.0)
    assert torch.allclose(e, torch.full_like(e, c), atol=1e-6)
    full = S.photometric_error(x, x + c)
    assert (full > 0.15 * c - 1e-6).all() and (full < full.new_tensor(1.0)).all()
    # the error of a swap of two channels counts once per channel: mean over 3 channels
    y = x.clone()
    y[:, [0, 1]] = x[:, [1, 0]]
    l1 = S.photometric_error(x, y, alpha=0.0)
    assert torch.allclose(l1, 2 * (x[:, 0] - x[:, 1]).abs() / 3, atol=1e-6)


@pytest.mark.parametrize('a, b, expected', [
    # flat images have no variance or covariance: SSIM is its luminance term (2 ab + C1) / (a^2 + b^2 + C1) with
    # C1 = 0.01^2; the error 0.85 (1 - SSIM) / 2 + 0.15 |a - b| (Monodepth2's alpha)
    (0.5, 0.6, 0.85 * (1 - 0.6001 / 0.6101) / 2 + 0.15 * 0.1),         # 0.021966
    (0.01, 0.02, 0.85 * (1 - 0.0005 / 0.0006) / 2 + 0.15 * 0.01),      # 0.072333: dark, where C1 matters
])
def test_photometric_error_of_flat_images_by_hand(a, b, expected):
    e = S.photometric_error(torch.full((1, 3, 4, 4), a, dtype=torch.float64),
                            torch.full((1, 3, 4, 4), b, dtype=torch.float64))
    assert torch.allclose(e, torch.full_like(e, expected), rtol=1e-9)


def test_ssim_structure_term_by_hand():
    """The centre of a 3x3 checker (its window is the whole image: mean 4/9, variance 20/81) against flat grey
    0.5: covariance 0, so SSIM = (2 (4/9) 0.5 + C1) / ((4/9)^2 + 0.25 + C1) * C2 / (20/81 + C2), C2 = 0.03^2."""
    a = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 0.0]], dtype=torch.float64).expand(1, 3, 3, 3)
    b = torch.full((1, 3, 3, 3), 0.5, dtype=torch.float64)
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ssim = (2 * 4 / 9 * 0.5 + c1) / ((4 / 9) ** 2 + 0.25 + c1) * c2 / (20 / 81 + c2)
    assert S.ssim_dissimilarity(a, b)[0, :, 1, 1].tolist() == pytest.approx([(1 - ssim) / 2] * 3, rel=1e-9)


def test_the_plane_sweeps_patch_error_is_the_image_error_at_a_3x3_images_centre():
    """plane_errors' 3x3 patch error (SSIM over the patch, L1 of its centre) is photometric_error at the centre of
    a 3x3 image (whose window is the whole image); a patch that differs only at its centre has L1 = that
    difference."""
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(1, 3, 3, 3, generator=g, dtype=torch.float64), torch.rand(1, 3, 3, 3, generator=g,
                                                                              dtype=torch.float64)
    patch = lambda img: img.reshape(1, 3, 1, 1, 9)                      # noqa: E731  row-major: the centre is 4
    for alpha in (0.0, 0.85):
        assert S._patch_error(patch(a), patch(b), alpha)[0, 0, 0].item() == pytest.approx(
            S.photometric_error(a, b, alpha)[0, 1, 1].item(), rel=1e-9)
    zeros = torch.zeros(1, 3, 1, 1, 9, dtype=torch.float64)
    centre = zeros.clone()
    centre[..., 4] = 1.0
    assert S._patch_error(zeros, centre, 0.0).item() == pytest.approx(1.0)


def _grid_camera(H, W, f=30.0):
    return torch.tensor([[[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]]], dtype=torch.float64)


def _noise(*shape, seed=0):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_plane_errors_grid_covers_every_image_pixel_on_the_stride():
    """The DPV grid of a 50x64 image at stride 4: ceil(50/4) x 64/4 = 13 x 16 (the last row sits on image row 48)."""
    ref = _noise(1, 3, 50, 64)
    still = torch.eye(4, dtype=torch.float64)[None, None]
    err, identity = S.plane_errors(ref, ref[:, None], _grid_camera(50, 64), still, torch.tensor([1.0, 2.0]))
    assert tuple(err.shape) == (1, 2, 13, 16) and tuple(identity.shape) == (1, 13, 16)


def test_the_unwarped_error_is_the_best_of_the_sources():
    """Two sources left where they are, one identical to the reference and one noise: the unwarped error is the
    minimum over them, 0 (the noise source alone would give about 0.47); score_error's fallback for a pixel the
    depth sends out of every source is that same minimum."""
    ref, noise = _noise(1, 3, 32, 32), _noise(1, 3, 32, 32, seed=1)
    K = _grid_camera(32, 32)
    still = torch.eye(4, dtype=torch.float64)[None, None].expand(1, 2, 4, 4)
    _err, identity = S.plane_errors(ref, torch.stack([ref, noise], 1), K, still, torch.tensor([1.0, 2.0]))
    assert identity.abs().max() < 1e-6
    far = torch.eye(4, dtype=torch.float64)
    far[0, 3] = 5.0                                       # 5 m sideways: at 2.5 m every pixel leaves both sources
    score = S.score_error(ref, torch.stack([ref, noise], 1), torch.full((1, 32, 32), 2.5, dtype=torch.float64), K,
                          far[None, None].expand(1, 2, 4, 4))
    assert score.abs().max() < 1e-6


def test_plane_errors_patches_at_the_image_edge_repeat_the_edge_pixel():
    """A 33-wide image at stride 4: the last grid column sits on the last image column (32); its patches take
    columns 31, 32, 32 (clamped to the image), as do the unwarped errors computed by hand from those pixels."""
    ref, src = _noise(1, 3, 33, 33), _noise(1, 3, 33, 33, seed=1)
    _err, identity = S.plane_errors(ref, src[:, None], _grid_camera(33, 33),
                                    torch.eye(4, dtype=torch.float64)[None, None], torch.tensor([2.0]))

    def patch(img, y, x):
        idx = [(min(max(y + dy, 0), 32), min(max(x + dx, 0), 32)) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
        return torch.stack([img[0, :, yy, xx] for yy, xx in idx], -1).reshape(1, 3, 1, 1, 9)
    for j, y in ((0, 0), (4, 16), (8, 32)):
        by_hand = S._patch_error(patch(ref, y, 32), patch(src, y, 32), S.SSIM_ALPHA)[0, 0, 0]
        assert identity[0, j, 8].item() == pytest.approx(by_hand.item(), rel=1e-9)


def test_a_patch_counts_where_its_centre_lands_in_the_source():
    """A 29-wide image, the source 0.5 px to the right at the 2 m plane: the last grid column's centres (x = 28)
    land at 28.5, past the last column, so they count as not reached (_FAR), though the rest of their patches
    (27.5 and left of it) lands inside; every other column's centre lands inside."""
    ref = _noise(1, 3, 32, 29)
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = 0.5 / 30.0 * 2.0                             # 0.5 px at 2 m with f = 30 px
    err, _ = S.plane_errors(ref, ref[:, None], _grid_camera(32, 29), T[None, None], torch.tensor([2.0]))
    assert (err[0, 0, :, -1] >= 1e3).all() and (err[0, 0, :, :-1] < 1e3).all()


def test_the_true_depth_explains_the_source_and_a_wrong_one_does_not():
    ref, src, K = _pair(T_MOVE)
    T = T_MOVE.float()[:, None]
    inner = (slice(None), slice(6, -6), slice(6, -6))
    errs = {}
    for scale in (1.0, 0.8, 1.25):
        depth = torch.full((1, H, W), Z * scale)
        err, mask = S.reprojection_error(ref, src[:, None], depth, K, T, automask=False)
        errs[scale] = S.masked_mean(err[inner], mask[inner]).item()
        assert mask[inner].float().mean() > 0.9
    assert errs[1.0] < 0.01
    assert errs[0.8] > 4 * errs[1.0] and errs[1.25] > 4 * errs[1.0]


def test_per_pixel_minimum_over_sources_ignores_a_source_that_disagrees():
    ref, src, K = _pair(T_MOVE)
    noise = torch.rand(src.shape, generator=torch.Generator().manual_seed(1))
    depth = torch.full((1, H, W), Z)
    T = T_MOVE.float()[:, None].expand(1, 2, 4, 4)
    both, mask = S.reprojection_error(ref, torch.stack([noise, src], 1), depth, K, T, automask=False)
    alone, _ = S.reprojection_error(ref, src[:, None], depth, K, T[:, :1], automask=False)
    inner = (slice(None), slice(6, -6), slice(6, -6))
    assert torch.allclose(both[inner], torch.minimum(alone[inner], both[inner]))
    assert S.masked_mean(both[inner], mask[inner]).item() < 0.01
    # the noise alone is far worse: the minimum picked the source that agrees
    bad, _ = S.reprojection_error(ref, noise[:, None], depth, K, T[:, :1], automask=False)
    assert bad[inner].mean() > 10 * both[inner].mean()


def test_a_source_out_of_view_is_skipped_and_a_pixel_no_source_reaches_is_masked():
    ref, src, K = _pair(T_MOVE)
    depth = torch.full((1, H, W), Z)
    far = se3(t=(5.0, 0.0, 0.0)).float()          # 5 m sideways at 2.5 m depth: every pixel leaves the image
    T = torch.stack([far[0], T_MOVE.float()[0]])[None]
    err, mask = S.reprojection_error(ref, torch.stack([src, src], 1), depth, K, T, automask=False)
    assert mask[:, 6:-6, 6:-6].all() and err[:, 6:-6, 6:-6].max() < 0.2
    err_far, mask_far = S.reprojection_error(ref, src[:, None], depth, K, far[:, None], automask=False)
    assert not mask_far.any()
    assert S.masked_mean(err_far, mask_far).item() == 0.0


def test_automask_drops_pixels_that_do_not_move():
    ref, src, K = _pair(T_MOVE)
    depth = torch.full((1, H, W), Z)
    T = T_MOVE.float()[:, None]
    _, moving = S.reprojection_error(ref, src[:, None], depth, K, T, automask=True)
    assert moving[:, 6:-6, 6:-6].float().mean() > 0.8
    # a camera that did not move: the unwarped source explains every pixel as well as any depth does
    still = se3().float()[:, None]
    _, static = S.reprojection_error(ref, ref[:, None], depth, K, still, automask=True)
    assert not static.any()
    # and the wrong depth on the moving pair is not rescued by the mask: it loses pixels, never gains them
    _, wrong = S.reprojection_error(ref, src[:, None], depth * 1.3, K, T, automask=True)
    assert wrong.sum() < moving.sum()


def test_gradient_of_the_loss_points_towards_the_true_depth():
    ref, src, K = _pair(T_MOVE)
    T = T_MOVE.float()[:, None]
    for start in (0.85 * Z, 1.15 * Z):
        d = torch.full((1, H, W), start, requires_grad=True)
        err, mask = S.reprojection_error(ref, src[:, None], d, K, T, automask=False)
        S.masked_mean(err[:, 6:-6, 6:-6], mask[:, 6:-6, 6:-6]).backward()
        step = -d.grad[0, 6:-6, 6:-6].sum()
        assert (step > 0) == (start < Z), (start, step)


def test_downsample_image_sits_on_the_quarter_grid():
    x = torch.arange(16.0).repeat(16, 1)[None, None].repeat(1, 3, 1, 1)     # value = column index
    q = S.downsample_image(x)
    assert q.shape[-2:] == (4, 4)
    # volume pixel j sits on image pixel 4j: the mean of columns 4j-2 .. 4j+2, clipped at the border (j = 0:
    # columns 0, 1, 2); every row and channel the same
    assert torch.allclose(q, torch.tensor([1.0, 4.0, 8.0, 12.0]).expand_as(q), atol=1e-5)


def test_parameter_penalty_and_distillation_by_hand():
    net = torch.nn.Linear(3, 2)
    base = {k: v.detach().clone() for k, v in net.named_parameters()}
    with torch.no_grad():
        net.weight[0, 1] += 0.3
        net.bias[1] -= 0.2
    assert S.parameter_penalty(net.named_parameters(), base).item() == pytest.approx(0.3 ** 2 + 0.2 ** 2, rel=1e-5)
    net.bias.requires_grad_(False)            # frozen parameters are not penalised
    assert S.parameter_penalty(net.named_parameters(), base).item() == pytest.approx(0.09, rel=1e-5)
    # KL(p_base || p) of two-plane DPVs: 0 for the same, sum p log(p / q) otherwise
    p = torch.tensor([0.7, 0.3]).log().view(1, 2, 1, 1)
    q = torch.tensor([0.4, 0.6]).log().view(1, 2, 1, 1)
    assert S.distillation(p, p).item() == pytest.approx(0.0, abs=1e-7)
    want = 0.7 * math.log(0.7 / 0.4) + 0.3 * math.log(0.3 / 0.6)
    assert S.distillation(q, p).item() == pytest.approx(want, rel=1e-5)
    assert S.distillation(p, q).item() != pytest.approx(want, rel=1e-3)      # not symmetric: the base is the target


def test_confidence_tie_weight_and_weighted_distillation_by_hand():
    conf = torch.tensor([0.2, 0.5, 0.75, 1.0])
    assert S.confidence_tie_weight(conf, 0.5).tolist() == pytest.approx([0.0, 0.0, 0.5, 1.0])
    assert S.confidence_tie_weight(conf, 0.0).tolist() == pytest.approx(conf.tolist())
    with pytest.raises(ValueError, match='threshold'):
        S.confidence_tie_weight(conf, 1.0)
    # two pixels: the same DPV (KL 0) and a moved one (KL k); weights 1 and w -> mean over both pixels
    base = torch.tensor([[0.7, 0.7], [0.3, 0.3]]).log().view(1, 2, 1, 2)
    adapted = torch.tensor([[0.7, 0.4], [0.3, 0.6]]).log().view(1, 2, 1, 2)
    k = 0.7 * math.log(0.7 / 0.4) + 0.3 * math.log(0.3 / 0.6)
    assert S.distillation(adapted, base).item() == pytest.approx(k / 2, rel=1e-5)
    for w in (0.0, 0.25, 1.0):
        weight = torch.tensor([[[1.0, w]]])
        assert S.distillation(adapted, base, weight).item() == pytest.approx(w * k / 2, rel=1e-5, abs=1e-9)
    # no gradient where the weight is 0: what the base network was unsure of is left to the photometry
    a = adapted.clone().requires_grad_(True)
    S.distillation(a, base, torch.tensor([[[1.0, 0.0]]])).backward()
    assert a.grad[..., 1].abs().max().item() == 0.0


def test_plane_sweep_errors_are_lowest_on_the_plane_nearest_the_true_depth():
    from dpv_sensor.core.dpv import depth_planes
    depths = depth_planes(0.3, 8.0, 32)
    for z in (1.0, 2.5):
        ref, src, K = _pair(T_MOVE, z)
        err, identity = S.plane_errors(ref, src[:, None], K, T_MOVE.float()[:, None], depths)
        assert err.shape == (1, 32, H // 4, W // 4) and identity.shape == (1, H // 4, W // 4)
        nearest = int((1.0 / depths - 1.0 / z).abs().argmin())          # planes are uniform in inverse depth
        best = err[0, :, 2:-2, 2:-2].argmin(0)
        assert (best == nearest).float().mean() > 0.6, (z, nearest, best.unique(return_counts=True))
        assert ((best - nearest).abs() <= 1).float().mean() > 0.95
        # the plane explains the pixel better than the unwarped source does
        assert (err.min(1).values[0, 2:-2, 2:-2] < identity[0, 2:-2, 2:-2]).float().mean() > 0.95


def test_photometric_evidence_by_hand():
    sigma = 0.05
    logp = torch.tensor([0.5, 0.5]).log().view(1, 2, 1, 1)
    # plane 1 errs sigma * ln 3 more than plane 0: evidence 0.5 * 1 + 0.5 * 1/3 = 2/3
    e = torch.tensor([0.01, 0.01 + sigma * math.log(3.0)]).view(1, 2, 1, 1)
    identity = torch.full((1, 1, 1), 0.2)
    assert S.photometric_evidence(logp, e, identity, sigma).item() == pytest.approx(-math.log(2 / 3), rel=1e-5)
    # a pixel the unwarped sources explain as well (it does not move) does not count
    assert S.photometric_evidence(logp, e, torch.full((1, 1, 1), 0.005), sigma).item() == 0.0
    # flat errors (no texture): no gradient, the networks' prior stays
    logits = torch.tensor([0.3, -0.2, 1.0]).view(1, 3, 1, 1).requires_grad_(True)
    flat = torch.full((1, 3, 1, 1), 0.04)
    S.photometric_evidence(torch.log_softmax(logits, 1), flat, identity, sigma).backward()
    assert logits.grad.abs().max() < 1e-7
    # one plane explains the patch: a gradient step moves mass towards it
    logits.grad = None
    sharp = torch.tensor([0.2, 0.02, 0.2]).view(1, 3, 1, 1)
    S.photometric_evidence(torch.log_softmax(logits, 1), sharp, identity, sigma).backward()
    assert logits.grad[0, 1] < 0 < logits.grad[0, 0] and logits.grad[0, 2] > 0
