"""The plane-anchors study's maths (studies.plane_anchors) on planes and cameras worked out by hand."""
import numpy as np
import pytest

from dpv_sensor.core.anchors import Anchors
from dpv_sensor.studies import plane_anchors as PA

K = np.array([[100.0, 0.0, 40.0], [0.0, 100.0, 30.0], [0.0, 0.0, 1.0]])                 # an 80x60 camera
K_160 = np.array([[100.0, 0.0, 80.0], [0.0, 100.0, 60.0], [0.0, 0.0, 1.0]])             # a 160x120 camera
# eight pixels spread over the 80x60 image, the fifth the principal point
SPREAD_UV = np.array([[5, 5], [70, 8], [10, 50], [75, 55], [40, 30], [20, 40], [60, 20], [33, 12]], np.float64)


def _anchors(uv, depth, K_33=K, sigma=0.01):
    """Anchors at `uv` with depth `depth` (m), all of std `sigma` in log depth (independent)."""
    n = len(uv)
    return Anchors(np.asarray(uv, np.float64).reshape(n, 2), np.broadcast_to(np.asarray(depth, np.float64), (n,)),
                   np.full(n, sigma), np.zeros(n), np.zeros(n, np.int64), K_33)


def _framed_wall(frame_px=12, H=60, W=80):
    """A blank grey wall framed by a checker border `frame_px` wide (3 px squares)."""
    img = np.full((H, W, 3), 128, np.uint8)
    yy, xx = np.mgrid[0:H, 0:W]
    border = (yy < frame_px) | (yy >= H - frame_px) | (xx < frame_px) | (xx >= W - frame_px)
    img[border & (((yy // 3) + (xx // 3)) % 2 == 0)] = 255
    img[border & (((yy // 3) + (xx // 3)) % 2 == 1)] = 0
    return img


def _checker_with_two_blank_squares():
    """An 80x60 checker with a blank 30 px square and a blank 12 px one."""
    yy, xx = np.mgrid[0:60, 0:80]
    img = np.where((((yy // 3) + (xx // 3)) % 2 == 0)[..., None], 255, 0).astype(np.uint8).repeat(3, axis=2)
    img[5:35, 5:35] = 128
    img[40:52, 50:62] = 128
    return img


def _on_plane(uv_n2, n_3, d):
    """Depth z of the pixels' rays (z = 1) on the plane n . X = d."""
    rays = np.c_[uv_n2, np.ones(len(uv_n2))] @ np.linalg.inv(K).T
    return d / (rays @ n_3)


def test_a_fronto_parallel_wall_and_a_tilted_floor_are_found_exactly():
    uv = SPREAD_UV
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
    uv = SPREAD_UV
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
    img = _framed_wall()
    uv = np.array([[14, 14], [30, 12], [44, 14], [46, 30], [44, 46], [30, 47], [16, 46], [13, 30]], np.float64)
    anchors = _anchors(uv, 2.0)
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
    far = _anchors(uv[:0], 2.0)
    assert not np.isfinite(PA.region_planes(img, far, config)).any()


def test_the_tolerance_grows_with_sigma_up_to_its_cap_and_ransac_finds_the_plane_among_many_outliers():
    uv = SPREAD_UV
    z = np.full(8, 2.0)
    z[4] = 2.0 * np.exp(0.08)            # the centre anchor 0.08 off in log depth: inside the others' outline, so no
    cfg = PA.PlaneConfig(min_inliers=6)  # tilt of a plane within 0.03 of them comes within 0.03 of it
    # sigma 0.01: the tolerance is the floor 0.03, the anchor is out; sigma 0.06: 1.5 sigma = 0.09, it is in
    assert sorted(PA.fit_plane(uv, z, np.full(8, 0.01), K, cfg).inliers) == [0, 1, 2, 3, 5, 6, 7]
    assert len(PA.fit_plane(uv, z, np.full(8, 0.06), K, cfg).inliers) == 8
    # 10 anchors on a wall 2 m away, 6 scattered off it (10 of 16: above the 60 % a plane needs): whatever the seed,
    # the search keeps the largest agreeing set, not the first triple it drew
    rng = np.random.default_rng(5)
    uv16 = np.c_[rng.uniform(0, 80, 16), rng.uniform(0, 60, 16)]
    z16 = np.r_[np.full(10, 2.0), [1.0, 3.1, 0.7, 4.4, 1.4, 2.9]]
    for seed in range(10):
        plane = PA.fit_plane(uv16, z16, np.full(16, 0.01), K, cfg, seed=seed)
        assert plane is not None and sorted(plane.inliers) == list(range(10)), seed


def test_a_plane_behind_the_camera_gives_no_depth():
    """The plane x = 0.1 m (a wall to the right, parallel to the optical axis): the rays right of the principal
    point meet it in front at z = 0.1 / x_ray, those left of it behind the camera: no depth there."""
    wall = PA.Plane(np.array([1.0, 0.0, 0.0]), 0.1, np.arange(3))
    depth = PA.plane_depth(wall, K, np.ones((60, 80), bool))
    assert depth[30, 50] == pytest.approx(0.1 / ((50 - 40) / 100.0))
    assert np.isnan(depth[:, :40]).all() and np.isfinite(depth[:, 41:]).all()


def test_regions_smaller_than_the_minimum_are_dropped():
    """A checkered image with two blank squares, 30 and 12 px: their weakest pixels (13 % of the image) make a
    region of 589 px in the big one and 38 px in the small one; with 100 px as the minimum only the big one is a
    region, with 20 px both are."""
    img = _checker_with_two_blank_squares()
    labels, count = PA.texture_free_regions(img, PA.PlaneConfig(min_region_px=100, weak_share=0.13))
    assert count == 1 and labels[20, 20] == 1 and labels[46, 56] == 0
    labels, count = PA.texture_free_regions(img, PA.PlaneConfig(min_region_px=20, weak_share=0.13))
    assert count == 2 and labels[46, 56] == 2


def test_the_score_counts_covered_texture_free_pixels_and_both_errors_against_the_truth():
    """The bordered blank wall of the hull test, its true depth 2 m: planes through anchors 5 % too far are 5 %
    too far on every pixel they cover, and the anchors themselves too."""
    H, W = 60, 80
    img = _framed_wall()

    class Seq:
        def image(self, k):
            return img

        def depth(self, k):
            return np.full((H, W), 2.0, np.float32)
    uv = np.array([[14, 14], [40, 12], [66, 14], [67, 30], [66, 46], [40, 47], [14, 46], [13, 30]], np.float64)
    anchors = {0: _anchors(uv, 2.1)}
    config = PA.PlaneConfig(min_region_px=100, min_inliers=6, weak_share=0.3)
    s = PA._score(Seq(), [0], anchors, config)
    labels, _ = PA.texture_free_regions(img, config)
    assert s['references'] == 1 and s['texture_free_px'] == int((labels > 0).sum())
    assert 0.5 < s['covered_share'] <= 1.0
    for part in ('planes', 'anchors'):
        assert s[part]['median_log'] == pytest.approx(np.log(1.05)) and s[part]['share_over_10pct'] == 0.0
    assert s['anchors']['n'] == 8 and s['planes']['n'] == round(s['covered_share'] * s['texture_free_px'])


@pytest.mark.parametrize('on_wall, plane', [
    (7, False),              # 7 of 16 agree: above min_inliers (6), but 44 % of the candidates, under 60 %
    (9, False),              # 56 %: still under 60 %
    (10, True),              # 62.5 %: a plane
])
def test_a_plane_needs_60_percent_of_its_candidates(on_wall, plane):
    rng = np.random.default_rng(5)
    uv16 = np.c_[rng.uniform(0, 80, 16), rng.uniform(0, 60, 16)]
    z16 = np.r_[np.full(on_wall, 2.0), [1.0, 3.1, 0.7, 4.4, 1.4, 2.9, 0.5, 5.0, 1.2][:16 - on_wall]]
    found = PA.fit_plane(uv16, z16, np.full(16, 0.01), K, PA.PlaneConfig(min_inliers=6))
    assert (found is not None) is plane
    if plane:
        assert sorted(found.inliers) == list(range(on_wall))


@pytest.mark.parametrize('outside_px, covered', [(15, True), (23, True), (27, False)])
def test_anchors_within_25_px_of_a_region_are_its_candidates(outside_px, covered):
    """Eight anchors on the wall's frame, each `outside_px` from the region (along eight directions from its
    centre): the band is 25 px, so at 15 and 23 px all eight are candidates, at 27 px none is."""
    from scipy import ndimage
    img = _framed_wall(40, 120, 160)
    config = PA.PlaneConfig(min_region_px=100, min_inliers=6, weak_share=0.15)
    labels, count = PA.texture_free_regions(img, config)
    assert count == 1
    dist = ndimage.distance_transform_edt(labels != 1)
    ys, xs = np.nonzero(labels == 1)
    cy, cx = ys.mean(), xs.mean()
    uv = []
    for angle in np.radians(np.arange(0, 360, 45)):
        step = np.array([np.cos(angle), np.sin(angle)])
        r = 0.0
        while dist[int(round(cy + r * step[1])), int(round(cx + r * step[0]))] < outside_px:
            r += 0.25
        uv.append([cx + r * step[0], cy + r * step[1]])
    anchors = _anchors(uv, 2.0, K_160)
    depth = PA.region_planes(img, anchors, config)
    assert bool(np.isfinite(depth).any()) is covered
    if covered:
        assert np.allclose(depth[np.isfinite(depth)], 2.0) and np.isfinite(depth[labels == 1]).mean() > 0.5


@pytest.mark.parametrize('min_region_px, count', [(589, 1), (590, 0)])
def test_a_region_of_exactly_the_minimum_size_is_kept(min_region_px, count):
    """The big blank square of the size test: its region has 589 px."""
    img = _checker_with_two_blank_squares()
    assert PA.texture_free_regions(img, PA.PlaneConfig(min_region_px=min_region_px, weak_share=0.13))[1] == count


def test_regions_are_8_connected_pieces_of_the_weakest_share(monkeypatch):
    """A texture map given by hand (0 on two 5x5 blocks that touch only at a corner, 1 elsewhere, 400 px): the
    weakest 1/8 are the 50 zeros, and the two blocks are one 8-connected region of 50 px."""
    import dpv_sensor.studies.error_breakdown as EB
    tex = np.ones((20, 20))
    tex[0:5, 0:5] = 0.0
    tex[5:10, 5:10] = 0.0
    monkeypatch.setattr(EB, 'local_texture', lambda image: tex)
    labels, count = PA.texture_free_regions(np.zeros((20, 20, 3), np.uint8),
                                            PA.PlaneConfig(min_region_px=30, weak_share=0.125))
    assert count == 1 and (labels == 1).sum() == 50


def test_exactly_min_inliers_anchors_on_a_plane_make_one():
    """The default needs 8 agreeing anchors: 8 on a wall 2 m away are enough."""
    uv = SPREAD_UV
    plane = PA.fit_plane(uv, np.full(8, 2.0), np.full(8, 0.01), K)
    assert PA.PlaneConfig().min_inliers == 8 and plane is not None and len(plane.inliers) == 8


def test_anchors_far_right_of_a_region_stay_there():
    """The framed wall (160x120): 8 anchors on it at 2 m, and 6 at columns 150-158 (over 30 px right of the
    region, off the wall at other depths): those are not candidates, and the wall's plane holds."""
    img = _framed_wall(40, 120, 160)
    config = PA.PlaneConfig(min_region_px=100, min_inliers=6, weak_share=0.15)
    good = np.array([[45, 45], [80, 42], [110, 45], [112, 60], [110, 75], [80, 78], [45, 75], [42, 60]], float)
    bad = np.array([[150, 20], [152, 50], [155, 80], [158, 95], [151, 65], [154, 35]], float)
    z = np.r_[np.full(8, 2.0), [1.0, 3.1, 0.7, 4.4, 1.4, 2.9]]
    anchors = _anchors(np.r_[good, bad], z, K_160)
    depth = PA.region_planes(img, anchors, config)
    assert np.isfinite(depth).sum() > 1000 and np.allclose(depth[np.isfinite(depth)], 2.0)


@pytest.mark.parametrize('too_far, over', [(1.102, 1.0), (1.098, 0.0)])
def test_the_score_counts_only_pixels_with_ground_truth_and_errors_over_10_percent(too_far, over):
    """The bordered wall with no ground truth on its right half: only the left half's texture-free pixels count;
    anchors (and so planes) 10.2 % too far are all over 10 %, 9.8 % too far none."""
    H, W = 60, 80
    img = _framed_wall()
    gt = np.full((H, W), 2.0, np.float32)
    gt[:, 40:] = 0.0

    class Seq:
        def image(self, k):
            return img

        def depth(self, k):
            return gt
    uv = np.array([[14, 14], [40, 12], [66, 14], [67, 30], [66, 46], [40, 47], [14, 46], [13, 30]], np.float64)
    anchors = {0: _anchors(uv, 2.0 * too_far)}
    config = PA.PlaneConfig(min_region_px=100, min_inliers=6, weak_share=0.3)
    s = PA._score(Seq(), [0], anchors, config)
    labels, _ = PA.texture_free_regions(img, config)
    assert s['texture_free_px'] == int((labels[:, :40] > 0).sum())
    assert s['planes']['share_over_10pct'] == over and s['anchors']['n'] == 3     # the three left of x = 40
