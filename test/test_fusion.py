"""TSDF fusion and mesh scoring (dpv_sensor/evaluation/fusion.py) on a ray-cast box scene with exact depth."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dpv_sensor.evaluation import fusion as F



def test_open3d_is_importable():
    # requirements.txt pins open3d (and the libusb it links against): a failed import is a broken environment, so
    # it fails here instead of skipping the module; every test below fails with the import error too.
    assert F.open3d() is not None

# Axis-aligned boxes (centre, half size) in a world with OpenCV-like axes (y down): floor slab (top at
# y = 1), back wall (front at z = 4) and a 0.8 m box standing on the floor.
BOXES = [
    (np.array([0.0, 1.1, 2.5]), np.array([2.0, 0.1, 2.0])),
    (np.array([0.0, 0.0, 4.1]), np.array([2.0, 1.2, 0.1])),
    (np.array([0.1, 0.6, 2.5]), np.array([0.4, 0.4, 0.4])),
]
VOXEL = 0.02


def _K(w, h, f):
    return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])


def _raycast(K, T_world_cam, w, h):
    """Exact z-depth of the box scene (0 where no box is hit)."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(h * w)])   # z-component 1
    d = T_world_cam[:3, :3] @ rays
    o = T_world_cam[:3, 3:4]
    best = np.full(h * w, np.inf)
    with np.errstate(divide='ignore', invalid='ignore'):
        for c, hs in BOXES:
            t1 = (c[:, None] - hs[:, None] - o) / d
            t2 = (c[:, None] + hs[:, None] - o) / d
            tmin = np.nanmax(np.minimum(t1, t2), 0)
            tmax = np.nanmin(np.maximum(t1, t2), 0)
            hit = (tmax >= tmin) & (tmin > 1e-6)
            best = np.where(hit & (tmin < best), tmin, best)
    return np.where(np.isfinite(best), best, 0.0).reshape(h, w).astype(np.float32)


def _surface_distance(p):
    """Distance of points to the nearest box surface."""
    out = np.full(len(p), np.inf)
    for c, hs in BOXES:
        q = np.abs(p - c) - hs
        sdf = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)
        out = np.minimum(out, np.abs(sdf))
    return out


def _poses(n=8):
    from scipy.spatial.transform import Rotation
    out = []
    for i in range(n):
        a = -1 + 2 * i / (n - 1)
        T = np.eye(4)
        T[:3, 3] = [0.6 * a, -0.1, 0.2 * abs(a)]
        T[:3, :3] = Rotation.from_euler('yx', [-0.15 * a, -0.1]).as_matrix()
        out.append(T)
    return out


def _frames(w, h, f, poses):
    K = _K(w, h, f)
    return [F.FusionFrame(_raycast(K, T, w, h), K, T) for T in poses]


@pytest.fixture(scope='module')
def gt_frames():
    return _frames(80, 60, 60.0, _poses())


@pytest.fixture(scope='module')
def gt_mesh(gt_frames):
    return F.integrate(gt_frames, F.FusionConfig(voxel_size=VOXEL))


def test_fused_exact_depth_lies_on_the_true_surfaces(gt_mesh):
    V, T = F.mesh_arrays(gt_mesh)
    assert len(V) > 10000 and len(T) > 10000
    d = _surface_distance(V)
    # marching cubes on a 2 cm grid: sub-voxel everywhere but at the boxes' silhouette edges
    assert np.mean(d) < 0.25 * VOXEL
    assert np.mean(d < 0.05) > 0.995
    # the wrong pose convention (world-to-camera passed as camera-to-world) is far off
    bad = F.integrate([F.FusionFrame(f.depth_hw, f.K_33, np.linalg.inv(f.T_world_cam_44))
                       for f in _frames(40, 30, 30.0, _poses(4))], F.FusionConfig(voxel_size=0.04))
    assert np.mean(_surface_distance(F.mesh_arrays(bad)[0]) < 0.05) < 0.8


def test_exact_depth_at_another_resolution_matches_the_gt_mesh(gt_mesh):
    # exact depth rendered at 64x48 (other K): another mesh of the same surfaces
    pred = F.integrate(_frames(64, 48, 48.0, _poses()), F.FusionConfig(voxel_size=VOXEL))
    r = F.mesh_distances(pred, gt_mesh, threshold=0.05)
    assert r['accuracy_within'] > 0.98 and r['completeness_within'] > 0.97
    assert r['accuracy_mean'] < 0.5 * VOXEL and r['fscore'] > 0.97


def test_low_confidence_outliers_hurt_only_the_unmasked_mesh(gt_frames, tmp_path):
    rng = np.random.default_rng(0)
    pred = []
    for f in _frames(64, 48, 48.0, _poses()):
        d = f.depth_hw.copy()
        conf = np.full(d.shape, 0.9, np.float32)
        out = rng.random(d.shape) < 0.2                          # 20 % outliers in front of the surface
        d[out] *= rng.uniform(0.3, 0.8, int(out.sum())).astype(np.float32)
        conf[out] = 0.1
        pred.append(F.FusionFrame(d, f.K_33, f.T_world_cam_44, conf))
    cfg = F.FusionConfig(voxel_size=VOXEL, min_confidence=0.5)
    rep = F.fusion_report(pred, gt_frames, cfg, out_dir=tmp_path)
    un, ma = rep['unmasked'], rep['masked']
    assert ma['kept_pixel_fraction'] == pytest.approx(0.8, abs=0.02)
    assert ma['accuracy_within'] > 0.98 and ma['accuracy_mean'] < 0.5 * VOXEL
    assert un['accuracy_within'] < ma['accuracy_within'] - 0.05
    assert un['accuracy_mean'] > 3 * ma['accuracy_mean']
    for name in ('mesh_gt.ply', 'mesh_pred.ply', 'mesh_pred_masked.ply'):
        assert (tmp_path / name).stat().st_size > 1000
    saved = json.loads((tmp_path / 'fusion.json').read_text())
    assert saved['masked']['accuracy_within'] == pytest.approx(ma['accuracy_within'])
    assert saved['config']['sdf_trunc'] == pytest.approx(4 * VOXEL)


def test_tiles_leave_no_seams():
    # one fronto-parallel wall crossing many 8-voxel tiles gives the same surface as one big tile
    K = _K(60, 40, 40.0)
    wall = np.full((40, 60), 1.5, np.float32)
    frames = [F.FusionFrame(wall, K, np.eye(4))]
    small = F.integrate(frames, F.FusionConfig(voxel_size=0.03, block_voxels=8))
    big = F.integrate(frames, F.FusionConfig(voxel_size=0.03, block_voxels=128))
    Vs, Ts = F.mesh_arrays(small)
    Vb, Tb = F.mesh_arrays(big)
    assert len(Vs) == len(Vb) and len(Ts) == len(Tb)
    r = F.mesh_distances(small, big, threshold=1e-4)
    assert r['accuracy_within'] == 1.0 and r['completeness_within'] == 1.0
    assert np.allclose(Vs[:, 2], 1.5, atol=1e-3)
    # seam vertices are merged: the wall is one connected piece
    clusters, _, _ = small.cluster_connected_triangles()
    assert len(np.unique(np.asarray(clusters))) == 1


def test_prepare_depth_masks():
    d = np.array([[1.0, np.nan, -1.0], [0.0, 5.0, 2.0]], np.float32)
    c = np.array([[0.9, 0.9, 0.9], [0.9, 0.9, 0.2]], np.float32)
    f = F.FusionFrame(d, np.eye(3), np.eye(4), c)
    np.testing.assert_array_equal(F.prepare_depth(f), [[1, 0, 0], [0, 5, 2]])
    np.testing.assert_array_equal(F.prepare_depth(f, max_depth=3.0), [[1, 0, 0], [0, 0, 2]])
    np.testing.assert_array_equal(F.prepare_depth(f, min_confidence=0.5), [[1, 0, 0], [0, 5, 0]])
    with pytest.raises(ValueError, match='confidence'):
        F.prepare_depth(F.FusionFrame(d, np.eye(3), np.eye(4)), min_confidence=0.5)


def _quad(z, size=1.0):
    o3d = F.open3d()
    m = o3d.geometry.TriangleMesh()
    s = size / 2
    m.vertices = o3d.utility.Vector3dVector(np.array([[-s, -s, z], [s, -s, z], [s, s, z], [-s, s, z]]))
    m.triangles = o3d.utility.Vector3iVector(np.array([[0, 1, 2], [0, 2, 3]], np.int32))
    return m


def test_mesh_distances_by_hand():
    r = F.mesh_distances(_quad(1.03), _quad(1.0), threshold=0.05)
    assert r['accuracy_mean'] == pytest.approx(0.03, abs=1e-6)
    assert r['completeness_mean'] == pytest.approx(0.03, abs=1e-6)
    assert r['accuracy_within'] == 1.0 and r['fscore'] == 1.0
    r = F.mesh_distances(_quad(1.08), _quad(1.0), threshold=0.05)
    assert r['accuracy_within'] == 0.0 and r['completeness_within'] == 0.0 and r['fscore'] == 0.0
    empty = F.open3d().geometry.TriangleMesh()
    r = F.mesh_distances(empty, _quad(1.0))
    assert r['num_vertices'] == 0 and np.isnan(r['accuracy_mean']) and r['completeness_within'] == 0.0


def test_fuse_tool_on_an_export(tmp_path, capsys):
    """`fuse export`: GT depth exported as if it were the sensor's output fuses onto the GT mesh."""
    import cv2
    from dpv_sensor.data.sequence import Sequence, depth_to_png_mm, write_intrinsics
    from dpv_sensor.tools import fuse as tool
    poses = _poses(6)
    K = _K(64, 48, 48.0)
    depths = [_raycast(K, T, 64, 48) for T in poses]
    images = [np.full((48, 64, 3), 100, np.uint8) for _ in poses]
    seq = Sequence.from_arrays(images, depths, np.stack(poses), K, np.arange(6) * 0.1)
    from dpv_sensor.data.sequence import write_sequence
    gt = write_sequence(tmp_path / 'gt', seq, lossless=True)
    exp = tmp_path / 'export'
    (exp / 'depth').mkdir(parents=True)
    (exp / 'confidence').mkdir()
    for i in range(6):
        cv2.imwrite(str(exp / 'depth' / f'{i:06d}.png'), depth_to_png_mm(depths[i]))
        cv2.imwrite(str(exp / 'confidence' / f'{i:06d}.png'), np.full((48, 64), 65535, np.uint16))
    (exp / 'stamps.txt').write_text(''.join(f'{i * 0.1!r}\n' for i in range(6)))
    write_intrinsics(exp / 'K.txt', K)
    rc = tool.main(['export', str(exp), '--gt', str(gt), '--out', str(tmp_path / 'fused'), '--voxel', '0.04',
                    '--quiet'])
    assert rc == 0
    assert 'conf >= 0.5' in capsys.readouterr().out
    rep = json.loads((tmp_path / 'fused' / 'fusion.json').read_text())
    assert rep['unmasked']['accuracy_within'] > 0.99 and rep['masked']['completeness_within'] > 0.99
    assert rep['input']['matched'] == 6
