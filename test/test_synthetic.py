"""The procedural renderer: determinism, exact depth and pose conventions (photometric warping), depth
limits and camera clearance, intrinsics across resolutions, trajectory smoothness, options and the CLI.
Small images throughout (speed is measured by dpv_sensor/benchmarks/render.py, not here)."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from reprojection import reproject
from dpv_sensor.data.sequence import Sequence, scale_intrinsics_np
from dpv_sensor.data.synthetic import SceneConfig, SyntheticScene, main, render_sequence

NOISE_FREE = dict(read_noise=(0.0, 0.0), shot_noise=(0.0, 0.0), vignetting=(0.0, 0.0))


def _warp_error(seq, i, j, T_i_j):
    """Mean |I_i(warp(p)) - I_j(p)| (0..255) over pixels p of frame j that are valid, land inside frame i,
    are not occluded there (z-test against depth i) and are not flagged view dependent (specular_mask) in
    either frame. Plain numpy + cv2.remap."""
    mx, my, z_in_i, valid = reproject(seq, j, T_i_j, min_z=0.05)
    valid &= ~seq.extra('specular_mask', j)
    spec_i = cv2.remap(seq.extra('specular_mask', i).astype(np.uint8), mx, my, cv2.INTER_NEAREST)
    valid &= spec_i == 0
    z_i = cv2.remap(seq.depth(i), mx, my, cv2.INTER_NEAREST)
    valid &= np.abs(z_in_i - z_i) < 0.03 * z_i                # visible in frame i too
    warped = cv2.remap(seq.image(i).astype(np.float32), mx, my, cv2.INTER_LINEAR)
    err = np.abs(warped - seq.image(j).astype(np.float32)).mean(-1)
    return float(err[valid].mean()), float(valid.mean())


def _three_errors(seq, i, j):
    Ti, Tj = seq.pose(i), seq.pose(j)
    correct, frac = _warp_error(seq, i, j, np.linalg.inv(Ti) @ Tj)     # T_i_j = T_i_world T_world_j
    none, _ = _warp_error(seq, i, j, np.eye(4))
    inverted, _ = _warp_error(seq, i, j, Ti @ np.linalg.inv(Tj))      # poses read as world-to-camera
    return correct, none, inverted, frac


def test_same_seed_same_data_and_different_seeds_differ():
    a = render_sequence(5, 3, 48, 36)
    b = render_sequence(5, 3, 48, 36)
    c = render_sequence(6, 3, 48, 36)
    for i in range(3):
        np.testing.assert_array_equal(a.image(i), b.image(i))
        np.testing.assert_array_equal(a.depth(i), b.depth(i))
        np.testing.assert_array_equal(a.pose(i), b.pose(i))
        np.testing.assert_array_equal(a.extra('specular_mask', i), b.extra('specular_mask', i))
    np.testing.assert_array_equal(a.K, b.K)
    assert a.meta == b.meta
    # another seed is another room, camera and trajectory
    assert a.meta['room_size_m'] != c.meta['room_size_m']
    assert not np.allclose(a.K, c.K)
    assert not np.allclose(a.pose(0), c.pose(0))
    assert np.abs(a.image(0).astype(int) - c.image(0).astype(int)).mean() > 5


def test_lazy_rendering_is_order_independent_and_equals_eager():
    eager = render_sequence(2, 4, 40, 30)
    lazy = render_sequence(2, 4, 40, 30, lazy=True)
    for i in (3, 0, 2):                      # out of order
        np.testing.assert_array_equal(lazy.image(i), eager.image(i))
        np.testing.assert_array_equal(lazy.depth(i), eager.depth(i))
    np.testing.assert_array_equal(lazy.poses, eager.poses)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_depth_and_poses_are_exact_by_photometric_warping(seed):
    """Warping frame i into frame i+3 and i+9 with the GT depth and poses explains the image almost
    perfectly on visible non-specular pixels (noise-free rendering), far better than no warp or the
    inverted pose convention."""
    seq = render_sequence(seed, 10, 96, 72, lazy=True, **NOISE_FREE)
    for j in (3, 9):
        correct, none, inverted, frac = _three_errors(seq, 0, j)
        assert frac > 0.4
        assert correct < 2.0, (j, correct, none, inverted)      # grey levels of 255 (bilinear resampling)
    assert correct < 0.4 * none and correct < 0.4 * inverted, (correct, none, inverted)


def test_warping_with_sensor_noise_still_favours_the_true_geometry():
    seq = render_sequence(3, 7, 96, 72)
    correct, none, inverted, _ = _three_errors(seq, 0, 6)
    assert correct < 0.5 * none and correct < 0.5 * inverted, (correct, none, inverted)


def test_depth_limits_and_camera_clearance():
    cfg = SceneConfig()
    for seed in (0, 4, 9):
        scene = SyntheticScene(seed, 32, 24)
        # the clearance guarantees z >= min_depth for every pixel ray (corner rays included)
        assert scene.clearance * math.cos(scene.max_ray_angle) >= cfg.min_depth
        t = np.arange(0.0, 120.0, 1 / 30)                     # four minutes of walking, every frame
        centres = scene.trajectory.position(t)
        assert scene.distance_to_surfaces(centres).min() >= scene.clearance
        assert np.all((centres > 0) & (centres < scene.room))
        for i in range(0, 3600, 450):
            f = scene.render_frame(i)
            d = f['depth']
            assert d.dtype == np.float32 and d.shape == (24, 32)
            assert np.all(np.isfinite(d))
            assert d.min() >= cfg.min_depth and d.max() <= cfg.max_depth, (seed, i, d.min(), d.max())


def test_intrinsics_and_depth_are_consistent_across_resolutions():
    """Render the same scene at 96x72 and 32x24: a third of the size puts each small pixel centre exactly on a
    big pixel centre ((u+0.5)*3-0.5 = 3u+1), so back-projecting small-image depth with the small K and
    projecting with the big K must land on integer pixels with the same depth."""
    big = render_sequence(4, 1, 96, 72, **NOISE_FREE)
    small = render_sequence(4, 1, 32, 24, **NOISE_FREE)
    # the renderer's K at a third of the size is the project's K scaling of the full-size K
    np.testing.assert_allclose(small.K, scale_intrinsics_np(big.K, 1 / 3, 1 / 3), rtol=0, atol=1e-12)
    np.testing.assert_allclose(big.resized(32, 24).K, small.K, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(small.pose(0), big.pose(0))
    d_small = small.depth(0).astype(np.float64)
    u, v = np.meshgrid(np.arange(32), np.arange(24))
    X = (np.linalg.inv(small.K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])) * d_small.ravel()
    p = big.K @ X
    ub, vb = p[0] / p[2], p[1] / p[2]
    ui, vi = np.round(ub).astype(int), np.round(vb).astype(int)
    assert np.abs(ub - ui).max() < 1e-6 and np.abs(vb - vi).max() < 1e-6   # centres land on centres
    np.testing.assert_array_equal(ui.reshape(24, 32), 3 * u + 1)
    z_big = big.depth(0)[vi, ui]
    np.testing.assert_allclose(z_big, X[2], rtol=1e-5)                    # the very same rays and surfaces
    # any landscape size of a seed shows the same room and furniture
    wide = SyntheticScene(4, 64, 36)
    assert big.meta['objects'] == small.meta['objects'] == wide.describe()['objects']
    assert big.meta['room_size_m'] == wide.describe()['room_size_m']


def test_trajectory_is_a_smooth_walk():
    scene = SyntheticScene(7, 32, 24)
    t = np.arange(0.0, 60.0, 1 / 30)
    T = scene.trajectory.pose(t)
    R = T[:, :3, :3]
    np.testing.assert_allclose(np.einsum('nji,njk->nik', R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    speed = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) * 30
    lo, hi = scene.config.speed
    assert speed.min() > lo - 0.05 and speed.max() < hi + 0.1               # hand shake on top of walking
    cos_step = (np.einsum('nij,nij->n', R[1:], R[:-1]) - 1) / 2
    step_deg = np.degrees(np.arccos(np.clip(cos_step, -1, 1)))
    assert step_deg.max() < 4.0 and step_deg.mean() > 0.1                   # it turns, smoothly
    # roll (image x axis vs horizontal) stays small
    roll = np.degrees(np.arcsin(np.abs(R[:, 2, 0])))
    assert roll.max() < scene.config.roll_deg + 2 * scene.config.tremor_deg + 0.5
    # sequence poses and stamps follow the 30 Hz clock
    seq = render_sequence(7, 2, 32, 24, lazy=True)
    np.testing.assert_allclose(seq.stamps, [0.0, 1 / 30])
    np.testing.assert_allclose(seq.pose(1), scene.trajectory.pose(1 / 30))


def test_options_blur_shutter_dynamic():
    base = render_sequence(8, 2, 48, 36, speed=(0.8, 0.8))
    blur = render_sequence(8, 2, 48, 36, speed=(0.8, 0.8), motion_blur=True)
    rs = render_sequence(8, 2, 48, 36, speed=(0.8, 0.8), rolling_shutter=True, readout_time=(0.03, 0.03))
    for other in (blur, rs):
        np.testing.assert_array_equal(other.depth(1), base.depth(1))      # depth/pose of the mid-exposure
        np.testing.assert_array_equal(other.pose(1), base.pose(1))
        assert not np.array_equal(other.image(1), base.image(1))
    # motion blur removes high-frequency energy
    def sharpness(img):
        g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32)
        return float(np.abs(cv2.Laplacian(g, cv2.CV_32F)).mean())
    assert sharpness(blur.image(1)) < sharpness(base.image(1))
    dyn = render_sequence(8, 2, 48, 36, static=False)
    assert 'dynamic_mask' in dyn.extra_names and 'dynamic_mask' not in base.extra_names
    assert dyn.extra('dynamic_mask', 0).shape == (36, 48)
    with pytest.raises(TypeError, match='unknown synthetic scene option'):
        render_sequence(8, 1, 16, 12, no_such_option=1)


def test_command_line_writes_a_sequence_folder(tmp_path, capsys):
    out = tmp_path / 'seq'
    assert main(['--seed', '3', '--frames', '3', '--width', '48', '--height', '36', '--out', str(out),
                 '--lossless', '--set', 'fov_deg=60,60']) == 0
    back = Sequence(out)
    ref = render_sequence(3, 3, 48, 36, fov_deg=(60, 60))
    assert len(back) == 3 and back.size == (48, 36)
    np.testing.assert_array_equal(back.K, ref.K)
    assert back.K[0, 0] == pytest.approx(24 / math.tan(math.radians(30)))
    np.testing.assert_allclose(back.poses, ref.poses, rtol=0, atol=1e-12)
    for i in range(3):
        np.testing.assert_array_equal(back.image(i), ref.image(i))
        assert np.abs(back.depth(i) - ref.depth(i)).max() <= 0.0005 + 1e-6
        np.testing.assert_array_equal(back.extra('specular_mask', i), ref.extra('specular_mask', i))
    assert back.meta['seed'] == 3 and back.meta['generator'] == 'dpv_sensor.data.synthetic'
