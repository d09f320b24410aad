"""D-Net / K-Net / R-Net: shapes, the paper's parameter count, layer equivalences, geometry, counting.

Cost notes (2-core CPU): ``lite`` runs the full pipeline (D-Net with 2 sources, K-Net, R-Net) for real at
320x240 and 640x480. ``paper`` runs for real at 320x240 (D-Net with 1 source, K-Net, R-Net, ~40 GMAC);
at 640x480 its full pipeline (4 sources; K-Net alone is ~365 GMAC there) is checked on the ``meta``
device, which propagates exact shapes through every layer without computing anything.
"""
from __future__ import annotations

import dataclasses
import os
import sys

import pytest
import torch
import torch.nn as nn

from dpv_sensor.core import dpv
from dpv_sensor.core.nets import DPVNet, get_preset
from dpv_sensor.core.nets.dnet import (CostVolume, FeatureExtractor, L1Cost, SPPBranch, feature_intrinsics,
                                       feature_size, normalize_image)
from dpv_sensor.core.nets.knet import ExpandedInputConv3d, KNet, image_to_volume_grid
from dpv_sensor.core.nets.model import count_macs, count_parameters
from dpv_sensor.core.nets.presets import preset_from_dict
from dpv_sensor.core.nets.rnet import RNet, upsample_logp

sys.path.insert(0, os.path.dirname(__file__))
from synthetic_planes import intrinsics, render_plane_pair, rot_y, se3  # noqa: E402

torch.set_num_threads(min(2, torch.get_num_threads()))


def _window(B, N, H, W, seed=0, device='cpu', dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    ref = torch.rand(B, 3, H, W, generator=g).to(device, dtype)
    srcs = torch.rand(B, N, 3, H, W, generator=g).to(device, dtype)
    f = 0.9 * W
    K = torch.tensor([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]], dtype=dtype).repeat(B, 1, 1)
    T = torch.eye(4, dtype=dtype).repeat(B, N, 1, 1)
    for n in range(N):
        T[:, n, 0, 3] = 0.1 * (n + 1) * (-1) ** n
    return ref, srcs, K.to(device), T.to(device)


def _check_pipeline(net, B, N, H, W, device='cpu'):
    p = net.preset
    D = p.num_planes
    h, w = feature_size(H, W)
    ref, srcs, K, T = _window(B, N, H, W, device=device)
    with torch.no_grad():
        logp, K_vol, feats = net.measure(ref, srcs, K, T)
        assert logp.shape == (B, D, h, w)
        assert K_vol.shape == (B, 3, 3)
        assert feats.fusion.shape == (B, p.feature_channels, h, w)
        assert feats.half.shape == (B, p.stem_channels, -(-H // 2), -(-W // 2))
        corr = net.knet(logp - logp.roll(1, dims=1), ref)
        assert corr.shape == (B, D, h, w)
        full = net.refine(logp, feats, ref)
        assert full.shape == (B, D, H, W)
    if device != 'meta':
        assert logp.dtype == torch.float32 and full.dtype == torch.float32
        for t in (logp, corr, full):
            assert torch.isfinite(t).all()
        torch.testing.assert_close(logp.exp().sum(1), torch.ones(B, h, w))
        torch.testing.assert_close(full.exp().sum(1), torch.ones(B, H, W))


# ---------------------------------------------------------------------------------------------- shapes
@pytest.mark.parametrize('W,H', [(320, 240), (640, 480)])
def test_lite_shapes(W, H):
    torch.manual_seed(0)
    _check_pipeline(DPVNet('lite').eval(), 1, 2, H, W)


def test_paper_shapes_320x240():
    """Real forward of the paper D-Net (1 source view) and R-Net; K-Net (85 GMAC here) on the meta device."""
    torch.manual_seed(0)
    net = DPVNet('paper').eval()
    ref, srcs, K, T = _window(1, 1, 240, 320)
    with torch.no_grad():
        logp, K_vol, feats = net.measure(ref, srcs, K, T)
        full = net.refine(logp, feats, ref)
    assert logp.shape == (1, 64, 60, 80) and feats.fusion.shape == (1, 64, 60, 80)
    assert feats.half.shape == (1, 32, 120, 160) and full.shape == (1, 64, 240, 320)
    assert torch.isfinite(full).all()
    torch.testing.assert_close(full.exp().sum(1), torch.ones(1, 240, 320))
    with torch.device('meta'):
        knet = KNet(get_preset('paper'))
        assert knet(torch.empty(1, 64, 60, 80), torch.empty(1, 3, 240, 320)).shape == (1, 64, 60, 80)


def test_paper_shapes_640x480_meta():
    with torch.device('meta'):
        net = DPVNet('paper').eval()
    _check_pipeline(net, 1, 4, 480, 640, device='meta')


@pytest.mark.parametrize('W,H', [(37, 29), (50, 41), (64, 48)])
def test_odd_sizes_and_batch(W, H):
    """Sizes not divisible by 4 (crop after each transposed conv) and batch 2."""
    torch.manual_seed(0)
    _check_pipeline(DPVNet('lite').eval(), 2, 2, H, W)


# ---------------------------------------------------------------------------------------------- params
def test_paper_parameter_count_matches_the_appendix():
    """Hand derivation from the appendix tables (plain convs WITH bias, no BN; params = k*k*cin*cout + cout).

    D-Net feature extractor (table "D-Net structure"):
      conv0_1  3x3  3->32 s2 :   3*32*9 + 32 =      896
      conv0_2  3x3 32->32    :  32*32*9 + 32 =    9,248
      conv0_3  3x3 32->32    :                    9,248
      conv1    3 blocks x 2 convs 32->32 : 6 * 9,248 =         55,488
      conv1_1  3x3 32->64 s2 :  32*64*9 + 64 =   18,496
      conv2    15 blocks x 2 convs 64->64: 30 * (64*64*9 + 64 = 36,928) = 1,107,840
      conv2_1  3x3 64->128   :  64*128*9 + 128 = 73,856
      conv3    2 blocks x 2 convs 128->128: 4 * (128*128*9 + 128 = 147,584) = 590,336
      conv4    3 dilated blocks x 2 convs : 6 * 147,584 =    885,504
      branch1..4  1x1 128->32 : 4 * (128*32 + 32 = 4,128) =   16,512
      fusion   3x3 320->128 : 320*128*9 + 128 = 368,768
               1x1 128->64  : 128*64 + 64     =   8,256
      total                                      3,144,448
    Cost volume: the softmax temperature (1 scalar, our addition)       1
    K-Net (table "K-Net structure", 3x3x3 conv3d, k^3 = 27):
      conv_0   4->32  : 4*32*27 + 32 =  3,488;  32->32 : 32*32*27 + 32 = 27,680
      conv_1   4 blocks x 2 convs 32->32 : 8 * 27,680 = 221,440
      conv_2   32->32 : 27,680;  32->1 : 32*27 + 1 = 865
      table total 281,153  (+1 scalar gain of the identity/damping path, our addition) = 281,154
    R-Net (table "R-Net structure", D = 64):
      conv_0   2 x 3x3 (64+D)->(64+D) = 128->128 : 2 * (128*128*9 + 128 = 147,584) = 295,168
      trans_conv_0  4x4 128->64 : 128*64*16 + 64 = 131,136
      conv_1   2 x 3x3 (32+D)->(32+D) = 96->96 : 2 * (96*96*9 + 96 = 83,040) = 166,080
      trans_conv_1  4x4 96->64 : 96*64*16 + 64 = 98,368
      conv_2   3x3 67->67 : 67*67*9 + 67 = 40,468; 67->64 : 67*64*9 + 64 = 38,656;
               64->64 : 64*64*9 + 64 = 36,928
      total                                                         806,804
    Grand total 3,144,448 + 1 + 281,154 + 806,804 = 4,232,407 (4,232,405 from the tables + 2 scalars).
    """
    net = DPVNet('paper')
    c = count_parameters(net)
    assert c['feature_extraction'] == 3_144_448
    assert c['cost_volume'] == 1
    assert c['knet'] == 281_153 + 1
    assert c['rnet'] == 806_804
    assert c['total'] == 4_232_407

    def n(m):
        return sum(p.numel() for p in m.parameters())
    f = net.features
    assert [n(f.conv0_1), n(f.conv0_2), n(f.conv0_3)] == [896, 9_248, 9_248]
    assert [n(f.conv1), n(f.conv1_1), n(f.conv2), n(f.conv2_1)] == [55_488, 18_496, 1_107_840, 73_856]
    assert [n(f.conv3), n(f.conv4), n(f.branches), n(f.fusion)] == [590_336, 885_504, 16_512, 377_024]
    assert f.concat_channels == 320
    k = net.knet
    assert [n(k.conv0_a), n(k.conv0_b), n(k.conv1), n(k.conv2_a), n(k.conv2_b)] == [3_488, 27_680, 221_440, 27_680, 865]
    r = net.rnet
    assert [n(r.conv0), n(r.trans_conv0), n(r.conv1), n(r.trans_conv1), n(r.conv2)] == \
        [295_168, 131_136, 166_080, 98_368, 40_468 + 38_656 + 36_928]


def test_presets():
    paper, lite = get_preset('paper'), get_preset('lite')
    assert paper.num_planes == 64 and paper.spp_pool_sizes == (64, 32, 16, 8)
    assert (paper.d_min, paper.d_max) == (0.3, 8.0)
    assert lite.num_planes < paper.num_planes
    assert count_parameters(DPVNet('lite'))['total'] < count_parameters(DPVNet('paper'))['total'] / 5
    assert preset_from_dict(lite.to_dict()) == lite
    with pytest.raises(ValueError, match='unknown preset'):
        get_preset('huge')
    with pytest.raises(ValueError, match='d_min < d_max'):
        dataclasses.replace(lite, d_min=9.0).validate()


# ---------------------------------------------------------------------------------------------- D-Net parts
def test_spp_branch_adapts_to_small_maps():
    """Pool windows larger than the map become a global average instead of an error."""
    torch.manual_seed(0)
    b = SPPBranch(4, 2, 64)
    x = torch.randn(1, 4, 6, 9)
    y = b(x)
    assert y.shape == (1, 2, 6, 9)
    expected = torch.relu(b.conv(x.mean(dim=(2, 3), keepdim=True)))
    torch.testing.assert_close(y, expected.expand_as(y))
    # window 4 fits the 8 rows (2 windows) but not the 3 columns (clamped to 3): pooled map 2x1
    b4 = SPPBranch(4, 2, 4)
    x4 = torch.randn(1, 4, 8, 3)
    y4 = b4(x4)
    assert y4.shape == (1, 2, 8, 3)
    top = torch.relu(b4.conv(x4[:, :, :4].mean(dim=(2, 3), keepdim=True)))
    torch.testing.assert_close(y4[:, :, :2], top.expand(1, 2, 2, 3))    # rows 0, 1 clamp to the first window
    # the paper extractor on a tiny image (quarter map 6x8, all four windows clamped)
    with torch.no_grad():
        feats = FeatureExtractor(get_preset('paper'))(torch.randn(1, 3, 24, 32))
    assert feats.fusion.shape == (1, 64, 6, 8) and feats.half.shape == (1, 32, 12, 16)


def test_stride2_grid_matches_feature_intrinsics():
    """conv0_1 (3x3, stride 2, padding 1) centres output pixel i on input 2i, so the quarter grid sits on
    full pixel 4j and K_vol = (fx/4, cx/4)."""
    f = FeatureExtractor(get_preset('lite'))
    conv = f.conv0_1.conv
    with torch.no_grad():
        conv.weight.zero_()
        conv.bias.zero_()
        conv.weight[0, 0, 1, 1] = 1.0                    # centre tap only
    u = torch.arange(11.0).view(1, 1, 1, 11).expand(1, 3, 5, 11)
    out = conv(u)[0, 0, 0]
    torch.testing.assert_close(out, 2.0 * torch.arange(6.0))
    K = torch.tensor([[[500.0, 0.0, 319.5], [0.0, 480.0, 239.5], [0.0, 0.0, 1.0]]])
    Kv = feature_intrinsics(K)
    torch.testing.assert_close(Kv, torch.tensor([[[125.0, 0.0, 319.5 / 4], [0.0, 120.0, 239.5 / 4], [0.0, 0.0, 1.0]]]))
    assert feature_size(480, 640) == (120, 160) and feature_size(250, 251) == (63, 63)


def test_cost_volume_finds_the_plane():
    """A textured fronto-parallel plane at z seen from a translated+rotated source: the cost volume's
    most probable plane (on exact rendered 'features') is the plane at z."""
    H, W = 48, 64
    K = intrinsics(W, H, 60.0)
    T = se3(rot_y(0.03), (0.12, -0.03, 0.02))
    p = dataclasses.replace(get_preset('lite'), num_planes=24, d_min=0.5, d_max=6.0, cost_plane_chunk=7)
    depths = dpv.depth_planes(p.d_min, p.d_max, p.num_planes, dtype=torch.float64)
    z = float(depths[9])
    # 4 channels = the plane's texture at 4 scales: an exact, position-specific 'feature' for matching
    pairs = [render_plane_pair(K, K, T, z, H, W, tex_scale=s) for s in (0.7, 1.3, 2.2, 3.5)]
    ref = torch.cat([a for a, _ in pairs], 1)
    src = torch.cat([b for _, b in pairs], 1)
    cv = CostVolume(p).double()
    with torch.no_grad():
        logp, cost, nvalid = cv(ref, src[:, None], K, T[:, None], depths, return_cost=True)
    assert logp.shape == (1, 24, H, W)
    inner = nvalid[0, 9] > 0                           # pixels whose true plane the source sees
    assert inner.float().mean() > 0.6
    best = logp[0].argmax(0)[inner]
    assert (best == 9).float().mean() > 0.9
    # the learnt temperature: logits = -scale * cost
    torch.testing.assert_close(logp, torch.log_softmax(-cv.scale * cost, 1))


def test_cost_volume_neutral_fill_and_view_average():
    """Voxels no view sees get the pixel's mean seen cost; costs are averaged over the seeing views."""
    torch.manual_seed(0)
    p = dataclasses.replace(get_preset('lite'), num_planes=8, d_min=0.5, d_max=4.0)
    cv = CostVolume(p).double()
    H, W = 10, 12
    K = intrinsics(W, H, 10.0)
    ref = torch.randn(1, 3, H, W, dtype=torch.float64)
    srcs = torch.randn(1, 2, 3, H, W, dtype=torch.float64)
    T = torch.stack([se3(t=(0.8, 0.0, 0.0)), se3(t=(-0.3, 0.0, 0.0))], 1)
    depths = dpv.depth_planes(0.5, 4.0, 8, dtype=torch.float64)
    cost, nvalid = cv.cost(ref, srcs, K, T, depths)
    from dpv_sensor.core.geometry import plane_sweep_warp
    per_view = []
    for n in range(2):
        wp, v = plane_sweep_warp(srcs[:, n], K, K, T[:, n], depths)
        per_view.append(((wp - ref[:, :, None]).abs().mean(1), v))
    num = sum(c * v for c, v in per_view)
    cnt = sum(v.double() for _, v in per_view)
    seen = cnt > 0
    assert (~seen).any() and seen.any()
    torch.testing.assert_close(cost[seen], (num / cnt.clamp_min(1))[seen])
    torch.testing.assert_close(nvalid, cnt)
    mean_seen = (cost * seen).sum(1, keepdim=True) / seen.sum(1, keepdim=True).clamp_min(1)
    torch.testing.assert_close(cost[~seen], mean_seen.expand_as(cost)[~seen])


def test_cost_volume_gradcheck():
    torch.manual_seed(0)
    p = dataclasses.replace(get_preset('lite'), num_planes=3, d_min=1.0, d_max=3.0)
    cv = CostVolume(p).double()
    K = intrinsics(5, 4, 4.0)
    T = se3(t=(0.2, 0.0, 0.0))[:, None]
    depths = dpv.depth_planes(1.0, 3.0, 3, dtype=torch.float64)
    ref = torch.randn(1, 2, 4, 5, dtype=torch.float64, requires_grad=True)
    src = torch.randn(1, 1, 2, 4, 5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: cv(a, b, K, T, depths), (ref, src))


def test_l1_cost_matches_autograd_and_gradcheck():
    """The fused L1 matching cost: values and both gradients equal autograd's sub/abs/sum chain
    (reference broadcast over the planes), and a float64 gradcheck passes."""
    torch.manual_seed(0)
    warped = torch.randn(3, 4, 5, 6, 7, dtype=torch.float64, requires_grad=True)
    ref = torch.randn(3, 4, 1, 6, 7, dtype=torch.float64, requires_grad=True)
    g = torch.randn(3, 5, 6, 7, dtype=torch.float64)
    ours = L1Cost.apply(warped, ref)
    theirs = (warped - ref).abs().sum(1)
    torch.testing.assert_close(ours, theirs)
    ga = torch.autograd.grad(ours, (warped, ref), g)
    gb = torch.autograd.grad(theirs, (warped, ref), g)
    for a, b in zip(ga, gb):
        torch.testing.assert_close(a, b)
    assert torch.autograd.gradcheck(L1Cost.apply, (warped[:1, :2, :2, :3, :3].detach().requires_grad_(),
                                                   ref[:1, :2, :, :3, :3].detach().requires_grad_()))


def test_cached_source_features_give_the_same_measurement():
    torch.manual_seed(0)
    net = DPVNet('lite').eval()
    ref, srcs, K, T = _window(1, 3, 40, 56, seed=3)
    with torch.no_grad():
        a, Ka, fa = net.measure(ref, srcs, K, T)
        cache = [net.extract_features(srcs[:, n]) for n in range(3)]
        b, Kb, fb = net.measure(ref, None, K, T, src_features=cache)
        c, _, _ = net.measure(ref, None, K, T, src_features=torch.stack([f.fusion for f in cache], 1),
                              ref_features=fa)
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(a, c, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(Ka, Kb)


# ---------------------------------------------------------------------------------------------- K-Net
def _in_float64_beside_conv3d(layer):
    """(the layer in float64 with a random bias, an nn.Conv3d with 3x3x3 kernel and padding 1 holding the same
    parameters): the reference of K-Net's convs computed another way."""
    layer = layer.double()
    with torch.no_grad():
        layer.bias.normal_()
    ref = nn.Conv3d(layer.in_channels, layer.out_channels, 3, padding=1).double()
    ref.load_state_dict(layer.state_dict())
    return layer, ref


@pytest.mark.parametrize('D', [1, 2, 5])
def test_expanded_input_conv3d_equals_conv3d(D):
    """The 2-D implementation of conv_0's first layer == nn.Conv3d on concat(residual, expand(image))."""
    torch.manual_seed(0)
    layer, ref_conv = _in_float64_beside_conv3d(ExpandedInputConv3d(6))
    vol = torch.randn(2, D, 5, 7, dtype=torch.float64)
    img = torch.randn(2, 3, 5, 7, dtype=torch.float64)
    x = torch.cat([vol[:, None], img[:, :, None].expand(2, 3, D, 5, 7)], 1)
    torch.testing.assert_close(layer(vol, img), ref_conv(x))
    assert layer.mac_count == 2 * D * 5 * 7 * 6 * 27 + 2 * 5 * 7 * 3 * 6 * 3 * 9
    if D == 2:
        small = ExpandedInputConv3d(2).double()
        v = torch.randn(1, 2, 3, 4, dtype=torch.float64, requires_grad=True)
        i = torch.randn(1, 3, 3, 4, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda a, b: small(a, b), (v, i))


def test_volume_conv3d_runs_onednn_where_pytorch_would_fall_back_with_the_same_values_and_gradients():
    """K-Net's 3-D convs on a 160x128 image's volume (12 channels, 32 planes, 32x40): PyTorch's size rule picks its
    unfold-and-multiply fallback there (1 x 12 x 32 x 32 = 12288 <= 20480; measured 11x slower per conv than
    oneDNN on one thread). VolumeConv3d calls oneDNN instead: the same values and gradients as nn.Conv3d, and
    nn.Conv3d itself under autocast, where autocast casts the inputs."""
    from dpv_sensor.core.nets.knet import VolumeConv3d
    x = torch.randn(1, 12, 32, 32, 40).contiguous(memory_format=torch.channels_last_3d)
    ref = nn.Conv3d(12, 12, 3, padding=1)
    backend = torch._C._select_conv_backend(x, ref.weight, ref.bias, [1, 1, 1], [1, 1, 1], [1, 1, 1], False,
                                            [0, 0, 0], 1, None)
    assert 'Slow3d' in str(backend), backend            # the case this class exists for
    conv = VolumeConv3d(12, 12, 3, padding=1)
    conv.load_state_dict(ref.state_dict())
    seen = []
    original = torch.mkldnn_convolution
    try:
        torch.mkldnn_convolution = lambda *a: seen.append(1) or original(*a)
        with torch.no_grad():
            torch.testing.assert_close(conv(x), ref(x), rtol=1e-5, atol=1e-4)
        assert seen == [1]
        with torch.autocast('cpu', dtype=torch.bfloat16), torch.no_grad():
            y = conv(x)
        assert seen == [1] and y.dtype == torch.bfloat16        # autocast: the ordinary op, cast by autocast
    finally:
        torch.mkldnn_convolution = original
    small = VolumeConv3d(2, 3, 3, padding=1).double()
    xs = torch.randn(1, 2, 3, 4, 5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(small, (xs,))               # float64: the ordinary op, its gradient checked
    xf = torch.randn(1, 12, 6, 5, 4, requires_grad=True)
    ref.zero_grad()
    conv.zero_grad()
    ga = torch.autograd.grad(conv(xf).square().sum(), (xf, conv.weight, conv.bias))
    gb = torch.autograd.grad(ref(xf).square().sum(), (xf, ref.weight, ref.bias))
    for a, b in zip(ga, gb):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-3)
    knet = KNet(get_preset('lite'))
    assert all(isinstance(m, VolumeConv3d) for m in (knet.conv0_b, knet.conv2_a, knet.conv2_b,
                                                     *[c for b in knet.conv1 for c in (b.conv_a, b.conv_b)]))


def test_depth_halves_by_hand():
    """Three output planes, one halo plane each side: halves of 2 planes (the second ends with a zero plane), each
    reading its 2 planes and its halo; planes past the volume are zeros."""
    from dpv_sensor.core.nets.knet import depth_halves
    x = torch.arange(1.0, 4.0).reshape(1, 1, 3, 1, 1)          # input planes 1, 2, 3
    g = torch.arange(10.0, 13.0).reshape(1, 1, 3, 1, 1)        # output-gradient planes 10, 11, 12
    xs, gs = depth_halves(x, g, 1)
    assert xs.flatten(1).tolist() == [[0, 1, 2, 3], [2, 3, 0, 0]]
    assert gs.flatten(1).tolist() == [[10, 11], [12, 0]]


@pytest.mark.parametrize('D,bias', [(1, True), (4, False), (5, True), (32, True)])
def test_volume_conv3d_backward_of_one_sample_runs_onednn_with_the_gradients_of_conv3d(D, bias):
    """One sample's backward (adaptation trains on single keyframes): PyTorch's own would run its fallback on K-Net's
    shapes; VolumeConv3d's goes to oneDNN - the input gradient a forward conv, the weight gradient on the two depth
    halves, a batch the size rule sends to oneDNN - with nn.Conv3d's gradients, with or without the input's.
    Strided convs keep the ordinary backward."""
    from dpv_sensor.core.nets.knet import VolumeConv3d, depth_halves
    torch.manual_seed(D)
    conv, ref = VolumeConv3d(12, 12, 3, padding=1, bias=bias), nn.Conv3d(12, 12, 3, padding=1, bias=bias)
    ref.load_state_dict(conv.state_dict())
    x = torch.randn(1, 12, D, 32, 40, requires_grad=True)
    y = conv(x)
    assert type(y.grad_fn).__name__ == '_OneDnnSameConv3dBackward'
    ga = torch.autograd.grad(y.square().sum(), (x, *conv.parameters()))
    gb = torch.autograd.grad(ref(x).square().sum(), (x, *ref.parameters()))
    for a, b in zip(ga, gb, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5 * float(b.abs().max()))
    xs, gs = depth_halves(x.detach(), y.detach(), 1)
    rule = [1, 1, 1], [0, 1, 1], [1, 1, 1], False, [0, 0, 0], 1, None
    assert 'Mkldnn' in str(torch._C._select_conv_backend(xs, ref.weight, ref.bias, *rule))
    if D == 32:
        assert 'Slow3d' in str(torch._C._select_conv_backend(x, ref.weight, ref.bias, [1, 1, 1], *rule[1:]))
    gw = torch.autograd.grad(conv(x.detach()).sum(), tuple(conv.parameters()))     # no input gradient asked
    for a, b in zip(gw, torch.autograd.grad(ref(x.detach()).sum(), tuple(ref.parameters())), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5 * float(b.abs().max()))
    with torch.no_grad():
        assert conv(x).grad_fn is None
    strided = VolumeConv3d(12, 4, 3, padding=1, stride=2)
    assert type(strided(x).grad_fn).__name__ != '_OneDnnSameConv3dBackward'


@pytest.mark.parametrize('D', [1, 2, 5])
def test_planewise_conv3d_equals_conv3d_with_its_gradients(D):
    """K-Net's last layer (C -> 1, 3x3x3) as 2-D convs over the depth planes, the taps summed shifted along depth:
    the values and gradients of nn.Conv3d, the first and last planes missing one tap each as zero padding does."""
    from dpv_sensor.core.nets.knet import PlanewiseConv3d
    torch.manual_seed(0)
    layer, ref = _in_float64_beside_conv3d(PlanewiseConv3d(4))
    x = torch.randn(2, 4, D, 5, 7, dtype=torch.float64)
    torch.testing.assert_close(layer(x), ref(x))
    xs = torch.randn(1, 2, D, 3, 4, dtype=torch.float64, requires_grad=True)
    small = PlanewiseConv3d(2).double()
    assert torch.autograd.gradcheck(small, (xs,))
    xf = torch.randn(1, 12, D, 6, 8)
    layer32, ref32 = PlanewiseConv3d(12), nn.Conv3d(12, 1, 3, padding=1)
    ref32.load_state_dict(layer32.state_dict())
    y = layer32(xf)
    assert y.dtype == torch.float32 and y.shape == (1, 1, D, 6, 8)
    torch.testing.assert_close(y, ref32(xf), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match='C -> 1 conv'):
        PlanewiseConv3d(4, 2)


def test_knet_starts_as_damped_blend_and_uses_the_image():
    """Step 0: g(dE, I) = dE / (1 + lambda) exactly (the blend with global damping's relative weights)."""
    torch.manual_seed(0)
    k = KNet(get_preset('lite'))
    r = torch.randn(1, 32, 6, 8) * 5
    img = torch.rand(1, 3, 24, 32)
    with torch.no_grad():
        out = k(r, img)
        torch.testing.assert_close(out, r / 1.8)
        k.conv2_b.weight.normal_(0, 0.1)               # once trained, the image matters
        a = k(r, img)
        b = k(r, torch.rand(1, 3, 24, 32))
    assert not torch.allclose(a, b)
    # as a DPVFilter-style callable: E_new = E_pred + g(E_meas - E_pred)
    e_pred, e_meas = torch.rand(1, 4, 2, 2) * 3, torch.rand(1, 4, 2, 2) * 3
    k0 = KNet(dataclasses.replace(get_preset('lite'), num_planes=4))
    with torch.no_grad():
        e_new = e_pred + k0(e_meas - e_pred, torch.rand(1, 3, 8, 8))
    torch.testing.assert_close(e_new, (0.8 * e_pred + e_meas) / 1.8)


def test_knet_memory_layout_changes_speed_not_results():
    """NDHWC (the default, faster on the CPU) and NCDHW give the same correction and the same gradients,
    and a checkpoint loaded into either layout keeps it."""
    torch.manual_seed(0)
    net = DPVNet('lite')
    assert net.knet.channels_last
    assert net.knet.conv0_b.weight.is_contiguous(memory_format=torch.channels_last_3d)
    with torch.no_grad():
        net.knet.conv2_b.weight.normal_(0, 0.1)
    r = (torch.randn(2, 32, 6, 8) * 3).requires_grad_()
    img = torch.rand(2, 3, 24, 32)
    results = []
    for layout_3d in (True, False):
        net.set_channels_last(True, layout_3d)
        net.zero_grad()
        r.grad = None
        out = net.knet(r, img)
        (out * torch.linspace(-1, 1, 8)).sum().backward()
        results.append((out.detach(), r.grad.clone(), net.knet.conv0_b.weight.grad.clone()))
    assert not net.knet.channels_last
    assert net.knet.conv0_b.weight.is_contiguous()
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_image_to_volume_grid_is_centred_on_4j():
    img = torch.arange(20.0).view(1, 1, 1, 20).expand(1, 3, 9, 20)
    out = image_to_volume_grid(img, feature_size(9, 20))
    assert out.shape == (1, 3, 3, 5)
    # interior columns average 4j-2..4j+2 -> exactly 4j; the borders average what exists
    torch.testing.assert_close(out[0, 0, 1, 1:4], torch.tensor([4.0, 8.0, 12.0]))
    assert image_to_volume_grid(img, (9, 20)) is img
    assert image_to_volume_grid(img, (4, 4)).shape == (1, 3, 4, 4)


# ---------------------------------------------------------------------------------------------- R-Net
def test_upsample_logp_samples_the_feature_grid():
    """Full-resolution pixel u = 4j reads quarter pixel j exactly; in between it interpolates."""
    h, w = 3, 5
    ramp = torch.arange(w, dtype=torch.float64).view(1, 1, 1, w).expand(1, 2, h, w)
    logits = torch.cat([ramp[:, :1], torch.zeros_like(ramp[:, :1])], 1)
    logp = torch.log_softmax(logits, 1)
    up = upsample_logp(logp, (10, 18))
    assert up.shape == (1, 2, 10, 18)
    # exact positions: row 0, columns 0, 4, 8, 12, 16 read quarter columns 0..4
    torch.testing.assert_close(up[0, :, 0, ::4], logp[0, :, 0, :])
    # column 2 is halfway between quarter columns 0 and 1 (log space, renormalised)
    mid = torch.log_softmax(0.5 * (logits[0, :, 0, 0] + logits[0, :, 0, 1]), 0)
    torch.testing.assert_close(up[0, :, 0, 2], mid)
    # beyond the last quarter pixel (u > 4(w-1)) the edge is held
    torch.testing.assert_close(up[0, :, 0, 17], logp[0, :, 0, -1])


def test_untrained_rnet_is_exact_upsampling_and_trained_one_uses_the_image():
    torch.manual_seed(0)
    p = get_preset('lite')
    r = RNet(p)
    H, W = 29, 37
    h, w = feature_size(H, W)
    logp = torch.log_softmax(torch.randn(1, p.num_planes, h, w) * 3, 1)
    fusion = torch.randn(1, p.feature_channels, h, w)
    half = torch.randn(1, p.stem_channels, -(-H // 2), -(-W // 2))
    img = normalize_image(torch.rand(1, 3, H, W))
    with torch.no_grad():
        out = r(logp, fusion, half, img)
        torch.testing.assert_close(out, upsample_logp(logp, (H, W)), rtol=1e-5, atol=1e-5)
        r.conv2[-1].weight.normal_(0, 0.05)
        a = r(logp, fusion, half, img)
        b = r(logp, fusion, half, normalize_image(torch.rand(1, 3, H, W)))
    assert not torch.allclose(a, b)
    torch.testing.assert_close(a.exp().sum(1), torch.ones(1, H, W))


# ---------------------------------------------------------------------------------------------- training / precision
def test_backward_reaches_every_stage():
    """Gradients reach every parameter. At step 0 the zero-initialised last layers of K-Net and R-Net
    block the gradient to the layers before them (by design: both start as identity-like maps), so
    take one SGD step first and check the second backward pass."""
    torch.manual_seed(0)
    net = DPVNet('lite').train()
    ref, srcs, K, T = _window(1, 2, 32, 40)
    gt = torch.linspace(0.5, 5.0, 40).expand(1, 32, 40)
    opt = torch.optim.SGD(net.parameters(), lr=1e-2)

    def loss_fn():
        logp, K_vol, feats = net.measure(ref, srcs, K, T)
        prior = torch.log_softmax(torch.linspace(-1, 1, logp.shape[1]).view(1, -1, 1, 1).expand_as(logp), 1)
        e = -prior + net.knet((-logp) - (-prior), ref)
        full = net.refine(torch.log_softmax(-e, 1), feats, ref)
        return dpv.nll(full, net.depths_d, gt) + dpv.nll(logp, net.depths_d, gt[:, ::4, ::4])
    loss_fn().backward()
    grads = {n: p.grad for n, p in net.named_parameters()}
    assert grads['knet.conv0_a.weight'].abs().sum() == 0 and grads['rnet.conv0.0.weight'].abs().sum() == 0
    assert grads['knet.conv2_b.weight'].abs().sum() > 0 and grads['rnet.conv2.4.weight'].abs().sum() > 0
    opt.step()
    opt.zero_grad()
    loss_fn().backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


def test_cpu_autocast_bf16_keeps_float32_dpvs():
    """The autocast path (bf16 convs; cost volume and log-softmaxes in float32). CUDA runs the same code."""
    torch.manual_seed(0)
    net = DPVNet('lite').eval()
    ref, srcs, K, T = _window(1, 2, 32, 48)
    with torch.no_grad(), torch.autocast('cpu', dtype=torch.bfloat16):
        logp, _, feats = net.measure(ref, srcs, K, T)
        corr = net.knet(logp, ref)
        full = net.refine(logp, feats, ref)
    with torch.no_grad():
        logp32, _, _ = net.measure(ref, srcs, K, T)
    for t in (logp, corr, full):
        assert t.dtype == torch.float32 and torch.isfinite(t).all()
    # bf16 features move the DPV but not far (probability L1 per pixel)
    assert (logp.exp() - logp32.exp()).abs().sum(1).mean() < 0.5


@pytest.mark.skipif(not torch.cuda.is_available(), reason='no CUDA device')
@pytest.mark.parametrize('dtype', [torch.bfloat16, torch.float16])
def test_cuda_autocast(dtype):
    torch.manual_seed(0)
    net = DPVNet('paper').cuda().eval()
    ref, srcs, K, T = _window(1, 2, 96, 128, device='cuda')
    with torch.no_grad(), torch.autocast('cuda', dtype=dtype):
        logp, _, feats = net.measure(ref, srcs, K, T)
        corr = net.knet(logp, ref)
        full = net.refine(logp, feats, ref)
    for t in (logp, corr, full):
        assert t.dtype == torch.float32 and torch.isfinite(t).all()
    assert full.shape == (1, 64, 96, 128)


# ---------------------------------------------------------------------------------------------- counting
def test_mac_counter_matches_a_hand_count():
    """MACs of conv layers = (weight elements) x (output pixels); paper extractor at 64x64:
    half-res 32x32 = 1024 px, quarter 16x16 = 256 px; SPP windows 64/32/16 clamp to 16 -> 1 px each, 8 -> 2x2."""
    net = DPVNet('paper').eval()
    macs = count_macs(net, 64, 64, num_sources=4)
    half, quarter = 1024, 256
    expected = (3 * 32 * 9 * half + 8 * 32 * 32 * 9 * half            # conv0_1; conv0_2, conv0_3, conv1 (6)
                + 32 * 64 * 9 * quarter + 30 * 64 * 64 * 9 * quarter   # conv1_1, conv2
                + 64 * 128 * 9 * quarter + 10 * 128 * 128 * 9 * quarter  # conv2_1, conv3 + conv4
                + 128 * 32 * (1 + 1 + 1 + 4)                           # SPP 1x1 convs on pooled maps
                + 320 * 128 * 9 * quarter + 128 * 64 * quarter)        # fusion
    assert macs['feature_extraction'] == expected
    D, h, w = 64, 16, 16
    knet_expected = (h * w * D * 32 * 27 + h * w * 3 * 32 * 3 * 9       # conv_0 first layer (2-D form)
                     + 10 * 32 * 32 * 27 * D * h * w + 32 * 27 * D * h * w)
    assert macs['knet'] == knet_expected
    rnet_expected = (2 * 128 * 128 * 9 * 256 + 128 * 64 * 16 * 256     # conv_0, trans_conv_0 (per input px)
                     + 2 * 96 * 96 * 9 * 1024 + 96 * 64 * 16 * 1024     # conv_1, trans_conv_1
                     + (67 * 67 + 67 * 64 + 64 * 64) * 9 * 4096)        # conv_2
    assert macs['rnet'] == rnet_expected
    assert macs['cost_volume'] == 5 * 64 * 4 * D * h * w
    assert macs['total_window'] == 5 * expected + macs['cost_volume'] + knet_expected + rnet_expected


def test_bfloat16_is_fast_only_where_the_cpu_has_native_bfloat16_arithmetic():
    from dpv_sensor.core.nets.model import cpu_bf16_fast
    # oneDNN calls bfloat16 supported on any AVX-512 CPU, where it is emulated and slower than float32
    assert not cpu_bf16_fast('flags\t\t: fpu sse2 avx2 avx512f avx512bw avx512_vnni')
    assert cpu_bf16_fast('flags\t\t: fpu avx512f avx512_bf16 avx512_vnni')
    assert cpu_bf16_fast('flags\t\t: fpu avx512f amx_bf16 amx_tile')
    assert not cpu_bf16_fast('flags\t\t: avx512_bf16x')
    assert not cpu_bf16_fast('flags\t\t: ')
