"""The plane-anchors study's maths (studies.plane_anchors) on planes and cameras worked out by hand."""
import numpy as np
import pytest

from dpv_sensor.core.anchors import Anchors
from dpv_sensor.studies import plane_anchors as PA

K = np.array([[100.0, 0.0, 40.0], [0.0, 100.0, 30.0], [0.0, 0.0, 1.0]])


def _on_plane(uv_n2, n_3, d):
    """Depth z of the pixels' rays (z = 1) on the plane n . X = d."""
    rays = np.c_[uv_n2, np.ones(len(uv_n2))] @ np.linalg.inv(K).T
    return d / (rays @ n_3)


def test_a_fronto_parallel_wall_and_a_tilted_floor_are_found_exactly():
    uv = np.array([[5, 5], [70, 8], [10, 50], [75, 55], [40, 30], [20, 40], [60, 20], [33, 12]], np.float64)
    # a wall 2 m ahead: z = 2 everywhere
    wall = PA.fit_plane(uv, np.full(8, 2.0), np.full(8, 0.01), K, PA.PlaneConfig(min_inliers=6))
    assert wall is not None and len(wall.inliers) == 8
    assert np.allclose(wall.n_3, [0, 0, 1], atol=1e-9) and wall.d == pytest.approx(2.0)
    # the pixel (40, 30) is the principal point: its ray is (0, 0, 1), so z = d / n_z
    n = np.array([0.0, -0.6, 0.8])                          # a plane tilted 37 degrees about x, 1.6 m along n
    z = _on_plane(uv, n, 1.6)
    assert z[4] == pytest.approx(1.6 / 0.8)
    floor = PA.fit_plane(uv, z, np.full(8, 0.01), K, PA.PlaneConfig(min_inliers=6))
    assert np.allclose(floor.n_3, n, atol=1e-9) and floor.d == pytest.approx(1.6)
    depth = PA.plane_depth(floor, K, np.ones((60, 80), bool))
    assert depth[30, 40] == pytest.approx(2.0) and depth[int(uv[0, 1]), int(uv[0, 0])] == pytest.approx(z[0])


def test_an_outlier_is_left_out_and_too_few_agreeing_anchors_give_no_plane():
    uv = np.array([[5, 5], [70, 8], [10, 50], [75, 55], [40, 30], [20, 40], [60, 20], [33, 12]], np.float64)
    z = np.full(8, 2.0)
    z[3] = 3.0                                               # log(1.5) = 0.41 off: outside every tolerance
    plane = PA.fit_plane(uv, z, np.full(8, 0.01), K, PA.PlaneConfig(min_inliers=6))
    assert sorted(plane.inliers) == [0, 1, 2, 4, 5, 6, 7] and plane.d == pytest.approx(2.0)
    # 7 of 8 agree: a plane needs 8 here
    assert PA.fit_plane(uv, z, np.full(8, 0.01), K, PA.PlaneConfig(min_inliers=8)) is None
    # the tolerance widens with an anchor's sigma (1.5 sigma, at most 0.1): with sigma 0.3 the outlier is 0.41 off,
    # still outside the cap
    assert len(PA.fit_plane(uv, z, np.full(8, 0.3), K, PA.PlaneConfig(min_inliers=6)).inliers) == 7
    # anchors on one image line are one ray fan: no plane through them is determined
    line = np.c_[np.linspace(5, 75, 8), np.full(8, 30.0)]
    assert PA.fit_plane(line, np.full(8, 2.0), np.full(8, 0.01), K, PA.PlaneConfig(min_inliers=6)) is None


def test_a_plane_speaks_only_inside_its_anchors_hull_on_its_region():
    """A blank grey wall 2 m away with a textured frame around it (a checker border): the blank centre is the one
    texture-free region; eight anchors on the left of it fix the wall, and its depth is given inside their hull
    only, unless the hull is switched off."""
    H, W = 60, 80
    img = np.full((H, W, 3), 128, np.uint8)
    yy, xx = np.mgrid[0:H, 0:W]
    border = (yy < 12) | (yy >= H - 12) | (xx < 12) | (xx >= W - 12)
    img[border & (((yy // 3) + (xx // 3)) % 2 == 0)] = 255
    img[border & (((yy // 3) + (xx // 3)) % 2 == 1)] = 0
    uv = np.array([[14, 14], [30, 12], [44, 14], [46, 30], [44, 46], [30, 47], [16, 46], [13, 30]], np.float64)
    anchors = Anchors(uv, np.full(8, 2.0), np.full(8, 0.01), np.zeros(8), np.zeros(8, np.int64), K)
    config = PA.PlaneConfig(min_region_px=100, min_inliers=6, weak_share=0.3)
    labels, count = PA.texture_free_regions(img, config)
    assert count == 1 and labels[30, 40] == 1 and labels[2, 2] == 0
    depth = PA.region_planes(img, anchors, config)
    assert depth[30, 40] == pytest.approx(2.0)
    inside = np.isfinite(depth)
    assert inside.sum() > 0 and np.allclose(depth[inside], 2.0)
    assert not inside[labels == 0].any()                    # never on the textured border
    assert labels[30, 55] == 1 and not inside[30, 55]       # on the region, outside the anchors' hull (x < 47)...
    whole = PA.region_planes(img, anchors, PA.PlaneConfig(min_region_px=100, min_inliers=6, weak_share=0.3,
                                                          hull=False))
    assert np.isfinite(whole[labels == 1]).all()            # ...given there when the hull is off
    # no anchor near the region: no plane
    far = Anchors(uv[:0], np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, np.int64), K)
    assert not np.isfinite(PA.region_planes(img, far, config)).any()
