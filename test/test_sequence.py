"""Sequence folders: write/read round trip, resized views and their intrinsics, keyframe windows, and the
real SUN3D fragment from the shared development data folder (skipped when absent)."""
from __future__ import annotations


import cv2
import numpy as np
import pytest

from reprojection import reproject
from dpv_sensor.data.sequence import (Sequence, SequenceFormatError, keyframe_windows, scale_intrinsics_np,
                                      write_sequence)


def _rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _random_sequence(n=4, w=40, h=30, seed=0) -> Sequence:
    rng = np.random.default_rng(seed)
    # smooth images so JPEG stays close to the original
    base = cv2.resize(rng.integers(0, 256, (3, 4, 3)).astype(np.uint8), (w, h), interpolation=cv2.INTER_LINEAR)
    images = [np.roll(base, i, axis=1) for i in range(n)]
    depths = []
    for _ in range(n):
        d = rng.uniform(0.3, 9.0, (h, w)).astype(np.float32)
        d[rng.random((h, w)) < 0.2] = 0.0          # invalid
        d[0, 0] = np.nan                             # also invalid
        depths.append(d)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        poses[i, :3, :3] = _rotation(rng)
        poses[i, :3, 3] = rng.normal(size=3) * np.pi   # irrational-looking values test exact round trip
    K = np.array([[41.123456789012345, 0.0, 19.7], [0.0, 40.9876543210987, 14.2], [0.0, 0.0, 1.0]])
    stamps = 1700000000.0 + np.arange(n) / 29.97 + rng.uniform(0, 1e-3, n)
    masks = [rng.random((h, w)) < 0.1 for _ in range(n)]
    return Sequence.from_arrays(images, depths, poses, K, stamps, meta={'source': 'unit test', 'n': n},
                                extras={'specular_mask': masks})


@pytest.mark.parametrize('lossless', [True, False])
def test_write_read_round_trip(tmp_path, lossless):
    seq = _random_sequence()
    folder = write_sequence(tmp_path / 'seq', seq, lossless=lossless)
    ext = '.png' if lossless else '.jpg'
    assert sorted(p.name for p in (folder / 'images').iterdir()) == [f'{i:06d}{ext}' for i in range(len(seq))]
    back = Sequence(folder)
    assert len(back) == len(seq)
    assert back.size == seq.size == (40, 30)
    np.testing.assert_array_equal(back.K, seq.K)                        # K exact
    np.testing.assert_allclose(back.poses, seq.poses, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(back.stamps, seq.stamps)
    assert back.meta == {'source': 'unit test', 'n': 4}
    for i in range(len(seq)):
        assert back.image(i).dtype == np.uint8 and back.image(i).shape == (30, 40, 3)
        diff = np.abs(back.image(i).astype(int) - seq.image(i).astype(int))
        if lossless:
            assert diff.max() == 0
        else:
            assert diff.mean() < 5.0          # JPEG q95 (chroma subsampled) of a tiny colourful image
        d0, d1 = seq.depth(i), back.depth(i)
        assert d1.dtype == np.float32
        valid = d0 > 0
        assert np.array_equal(d1 > 0, valid), 'invalid (0 / NaN) depth must stay invalid'
        assert np.max(np.abs(d1[valid] - d0[valid])) <= 0.0005 + 1e-6   # within 1 mm (rounded to mm)
        np.testing.assert_array_equal(back.extra('specular_mask', i), seq.extra('specular_mask', i))
        np.testing.assert_array_equal(back.pose(i), back.poses[i])
        assert back.stamp(i) == seq.stamp(i)


def test_defaults_when_optional_files_are_absent(tmp_path):
    seq = _random_sequence(n=3)
    folder = write_sequence(tmp_path / 'seq', seq, lossless=True)
    (folder / 'stamps.txt').unlink()
    (folder / 'meta.json').unlink()
    back = Sequence(folder)
    np.testing.assert_allclose(back.stamps, np.arange(3) / 30.0)
    assert back.meta == {}


def test_format_errors(tmp_path):
    folder = write_sequence(tmp_path / 'seq', _random_sequence(n=3), lossless=True)
    with open(folder / 'poses.txt', 'a') as f:
        f.write(' '.join(['0'] * 15 + ['1']) + '\n')
    with pytest.raises(SequenceFormatError, match='3 images but 4 poses'):
        Sequence(folder)
    (folder / 'K.txt').unlink()
    with pytest.raises(SequenceFormatError, match='K.txt'):
        Sequence(folder)
    with pytest.raises(IndexError):
        _random_sequence(n=2).image(2)


def test_resized_intrinsics_follow_the_pixel_centre_convention():
    seq = _random_sequence(w=40, h=30)
    small = seq.resized(20, 10)
    K, Ks = seq.K, small.K
    assert Ks[0, 0] == pytest.approx(K[0, 0] * 0.5) and Ks[1, 1] == pytest.approx(K[1, 1] / 3)
    assert Ks[0, 2] == pytest.approx((K[0, 2] + 0.5) * 0.5 - 0.5)
    assert Ks[1, 2] == pytest.approx((K[1, 2] + 0.5) / 3 - 0.5)
    np.testing.assert_allclose(scale_intrinsics_np(K, 0.5, 1 / 3), Ks)
    assert small.size == (20, 10)
    assert small.image(0).shape == (10, 20, 3) and small.depth(0).shape == (10, 20)
    np.testing.assert_array_equal(small.poses, seq.poses)
    assert small.extra('specular_mask', 1).dtype == np.bool_


def test_resized_depth_back_projects_to_the_same_3d_points():
    """Downscaling by 3 puts every new pixel centre exactly on an old pixel centre: (u'+0.5)*3-0.5 = 3u'+1.
    Nearest-neighbour depth there, back-projected with the scaled K, must give the very same 3-D point as
    the old pixel with the old K (any other K convention is off by a pixel). Invalid depth stays invalid and
    no depth is interpolated."""
    w, h = 90, 60
    K = np.array([[70.0, 0.0, 44.3], [0.0, 71.0, 28.9], [0.0, 0.0, 1.0]])
    # a tilted plane n . X = 2 seen by the camera, plus invalid holes
    n = np.array([0.2, -0.3, 1.0])
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    depth = (2.0 / (n @ rays)).reshape(h, w).astype(np.float32)
    depth[::7, ::5] = 0.0
    seq = Sequence.from_arrays([np.zeros((h, w, 3), np.uint8)], [depth], np.eye(4)[None], K)
    small = seq.resized(30, 20)
    ds = small.depth(0)
    us, vs = np.meshgrid(np.arange(30), np.arange(20))
    src_u, src_v = 3 * us + 1, 3 * vs + 1
    np.testing.assert_array_equal(ds, depth[src_v, src_u])              # nearest, centre aligned
    valid = ds > 0
    assert (~valid).any() and valid.mean() > 0.8
    P_small = (np.linalg.inv(small.K) @ np.stack([us.ravel(), vs.ravel(), np.ones(us.size)])) * ds.ravel()
    P_big = (np.linalg.inv(K) @ np.stack([src_u.ravel(), src_v.ravel(), np.ones(us.size)])) * ds.ravel()
    np.testing.assert_allclose(P_small[:, valid.ravel()], P_big[:, valid.ravel()], atol=1e-6)
    # and the points lie on the plane
    np.testing.assert_allclose(n @ P_small[:, valid.ravel()], 2.0, rtol=1e-5)


def test_keyframes_and_windows():
    seq = _random_sequence(n=23, w=8, h=6)
    kf = seq.keyframe_indices(every=4)
    np.testing.assert_array_equal(kf, [0, 4, 8, 12, 16, 20])
    centered = seq.windows(every=4, size=5, mode='centered')
    assert [w.ref for w in centered] == [8, 12]
    np.testing.assert_array_equal(centered[0].frames, [0, 4, 8, 12, 16])
    assert all(w.frames[w.ref_pos] == w.ref and w.ref_pos == 2 for w in centered)
    causal = seq.windows(every=4, size=5, mode='causal')
    assert [w.ref for w in causal] == [16, 20]
    np.testing.assert_array_equal(causal[1].frames, [4, 8, 12, 16, 20])
    assert all(w.ref_pos == 4 for w in causal)
    assert keyframe_windows([0, 1, 2], size=5) == []
    with pytest.raises(ValueError):
        keyframe_windows([0, 1, 2, 3], size=4, mode='centered')
    with pytest.raises(ValueError):
        keyframe_windows([0, 1, 2, 3], size=3, mode='sideways')
    sub = seq.subset(centered[1].frames)
    assert len(sub) == 5
    np.testing.assert_array_equal(sub.pose(2), seq.pose(12))


def _photometric_error(seq, i, j, T_i_j):
    """Mean |I_i(warp(p)) - I_j(p)| over pixels of frame j that land inside frame i, using depth of j."""
    mx, my, _z, valid = reproject(seq, j, T_i_j, min_z=0.1)
    warped = cv2.remap(seq.image(i).astype(np.float32), mx, my, cv2.INTER_LINEAR)
    err = np.abs(warped - seq.image(j).astype(np.float32)).mean(-1)
    return float(err[valid].mean()), float(valid.mean())


def test_sun3d_fragment(sun3d_frag1):
    seq = Sequence(sun3d_frag1)
    assert len(seq) == 50
    assert seq.size == (640, 480)
    assert seq.image(0).shape == (480, 640, 3) and seq.image(0).dtype == np.uint8
    K = seq.K
    assert 400 < K[0, 0] < 700 and abs(K[0, 2] - 320) < 20 and abs(K[1, 2] - 240) < 20
    for i in (0, 25, 49):
        d = seq.depth(i)
        assert d.shape == (480, 640) and d.dtype == np.float32
        valid = d > 0
        assert valid.mean() > 0.5
        assert 0.3 < np.median(d[valid]) < 6.0 and d.max() < 10.0
        R = seq.pose(i)[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-4)
    assert np.all(np.diff(seq.stamps) > 0)
    # conventions: warping with the camera-to-world poses beats no warp and the inverted convention
    small = seq.resized(160, 120)
    Ti, Tj = small.pose(10), small.pose(20)
    e_ok, frac = _photometric_error(small, 10, 20, np.linalg.inv(Ti) @ Tj)
    e_none, _ = _photometric_error(small, 10, 20, np.eye(4))
    e_inv, _ = _photometric_error(small, 10, 20, Ti @ np.linalg.inv(Tj))
    assert frac > 0.3
    assert e_ok < 0.8 * e_none and e_ok < 0.8 * e_inv, (e_ok, e_none, e_inv)


def test_world_scaled_view_scales_depths_and_translations_and_keeps_the_images():
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (3, 8, 10, 3), dtype=np.uint8)
    depths = rng.uniform(0.5, 4.0, (3, 8, 10)).astype(np.float32)
    depths[0, 0, 0] = 0.0                                           # invalid stays invalid
    poses = np.stack([np.eye(4)] * 3)
    poses[:, :3, 3] = [[0, 0, 0], [0.1, 0.0, 0.0], [0.2, 0.05, -0.1]]
    poses[2, :3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    seq = Sequence.from_arrays(images, depths, poses, np.diag([8.0, 8.0, 1.0]))
    half = seq.world_scaled(0.5)
    assert len(half) == 3 and half.size == seq.size and np.array_equal(half.K, seq.K)
    assert np.array_equal(half.image(2), seq.image(2)) and np.array_equal(half.stamps, seq.stamps)
    assert np.allclose(half.depth(1), depths[1] * 0.5) and half.depth(0)[0, 0] == 0.0
    assert np.allclose(half.pose(2)[:3, 3], [0.1, 0.025, -0.05])
    assert np.array_equal(half.pose(2)[:3, :3], poses[2, :3, :3])
    assert np.array_equal(seq.pose(2)[:3, 3], [0.2, 0.05, -0.1])   # the original is untouched
    assert seq.world_scaled(1.0) is seq
    with pytest.raises(ValueError, match='positive'):
        seq.world_scaled(0.0)
