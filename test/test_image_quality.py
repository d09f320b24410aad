"""The degenerate-frame detector: each kind of frame is named, real-looking frames pass."""
import numpy as np
import pytest

from dpv_sensor.core.image_quality import assess

H, W = 60, 80


def scene_like():
    """A smooth textured image (neighbouring pixels correlated, as in any camera image)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    g = 0.5 + 0.2 * np.sin(u / 5.0) + 0.15 * np.sin(v / 7.0 + u / 11.0)
    return (np.stack([g, 0.8 * g, 1.0 - g], -1) * 255).round().astype(np.uint8)


@pytest.mark.parametrize('name,image,reason', [
    ('black', np.zeros((H, W, 3), np.uint8), 'black'),
    ('nearly black', np.random.default_rng(0).integers(0, 6, (H, W, 3)).astype(np.uint8), 'black'),
    ('white', np.full((H, W, 3), 255, np.uint8), 'saturated'),
    ('saturated red', np.dstack([np.full((H, W), 255, np.uint8), scene_like()[..., 1:]]), 'saturated'),
    ('flat grey', np.full((H, W, 3), 128, np.uint8), 'flat'),
    ('noise', np.random.default_rng(1).integers(0, 256, (H, W, 3)).astype(np.uint8), 'noise'),
    ('grey noise', np.repeat(np.random.default_rng(2).integers(0, 256, (H, W, 1)), 3, 2).astype(np.uint8), 'noise'),
])
def test_degenerate_frames_are_named(name, image, reason):
    q = assess(image)
    assert not q.ok, name
    assert q.reason.startswith(reason), q.reason
    assert set(q.stats) >= {'dark_fraction', 'saturated_fraction', 'grey_std', 'neighbour_ratio'}


def test_scene_like_frames_pass_also_dark_or_bright_ones():
    img = scene_like()
    assert assess(img).ok and assess(img).reason is None
    dim = (img.astype(np.float64) * 0.3).astype(np.uint8)         # an underexposed but real frame
    assert assess(dim).ok
    bright = np.clip(img.astype(np.int32) + 60, 0, 255).astype(np.uint8)
    assert assess(bright).ok
    noisy = np.clip(img + np.random.default_rng(3).normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    assert assess(noisy).ok                                          # sensor noise on a scene is no noise frame


def test_bad_input_is_an_error():
    with pytest.raises(ValueError, match='uint8 HxWx3'):
        assess(np.zeros((H, W), np.uint8))


# --- frames just either side of each threshold: a threshold moved by more than the margin fails one of them -----
# the thresholds as designed (dpv_sensor.core.image_quality), written out so that a changed constant fails a test
DARK_LEVEL, DARK_FRACTION, SATURATED_LEVEL, SATURATED_FRACTION, FLAT_STD, NOISE_RATIO = 10, 0.97, 250, 0.9, 2.0, 0.92

HT = 100          # rows: fractions in steps of 1 %


def _textured(h=HT, w=W):
    """A smooth colour ramp well inside every threshold (not dark, not saturated, not flat, not noise)."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    g = 60 + 120 * (u / w) + 40 * np.sin(v / 9.0)
    return np.repeat(g[..., None], 3, 2).round().astype(np.uint8)


def _rows(share: float, fill: np.ndarray) -> np.ndarray:
    """The textured frame with its first round(share * HT) rows replaced by `fill` (rows x W x 3)."""
    img = _textured()
    n = int(round(share * HT))
    img[:n] = fill[:n]
    return img


def _lens_cap(level: int, noise: float, seed: int = 0) -> np.ndarray:
    """A covered lens: `level` plus Gaussian sensor noise, clipped to [0, level + 2 * noise]."""
    rng = np.random.default_rng(seed)
    return np.clip(rng.normal(level, noise, (HT, W, 3)), 0, level + 2 * noise).round().astype(np.uint8)


@pytest.mark.parametrize('share,expect', [(DARK_FRACTION + 0.01, 'black'), (DARK_FRACTION - 0.01, None)])
def test_dark_fraction_either_side(share, expect):
    cap = np.clip(_lens_cap(DARK_LEVEL - 4, 2.0), 0, DARK_LEVEL)       # a lens cap with sensor noise
    q = assess(_rows(share, cap))
    assert (q.reason or '').split(':')[0] == (expect or '') and q.ok == (expect is None), (q.reason, q.stats)


@pytest.mark.parametrize('level,expect', [(DARK_LEVEL, 'black'), (DARK_LEVEL + 1, None)])
def test_dark_level_either_side(level, expect):
    q = assess(_rows(DARK_FRACTION + 0.01, np.full((HT, W, 3), level, np.uint8)))
    assert (q.reason or '').split(':')[0] == (expect or ''), (q.reason, q.stats)


@pytest.mark.parametrize('share,expect', [(SATURATED_FRACTION + 0.01, 'saturated'),
                                          (SATURATED_FRACTION - 0.01, None)])
def test_saturated_fraction_either_side(share, expect):
    rng = np.random.default_rng(1)             # nearly saturated: the sensor clips at 255 with noise below it
    near = np.clip(rng.normal(254, 1.0, (HT, W, 3)), SATURATED_LEVEL, 255).round().astype(np.uint8)
    q = assess(_rows(share, near))
    assert (q.reason or '').split(':')[0] == (expect or ''), (q.reason, q.stats)


@pytest.mark.parametrize('level,expect', [(SATURATED_LEVEL, 'saturated'), (SATURATED_LEVEL - 1, None)])
def test_saturated_level_either_side(level, expect):
    q = assess(_rows(SATURATED_FRACTION + 0.01, np.full((HT, W, 3), level, np.uint8)))
    assert (q.reason or '').split(':')[0] == (expect or ''), (q.reason, q.stats)


def _ramp(std: float) -> np.ndarray:
    """A smooth horizontal grey ramp whose grey-level std is `std` (a uniform ramp of width a has std a/sqrt(12))."""
    a = std * np.sqrt(12.0)
    u = np.linspace(-a / 2, a / 2, W)
    g = np.repeat((128 + u)[None, :], HT, 0)
    return np.repeat(g[..., None], 3, 2).astype(np.float64)


@pytest.mark.parametrize('factor,expect', [(0.9, 'flat'), (1.1, None)])
def test_flat_std_either_side(factor, expect):
    img = _ramp(FLAT_STD * factor).round().astype(np.uint8)
    q = assess(img)
    assert abs(q.stats['grey_std'] / FLAT_STD - factor) < 0.06, q.stats
    assert (q.reason or '').split(':')[0] == (expect or ''), (q.reason, q.stats)


def _noise_with_structure(target_ratio: float) -> np.ndarray:
    """Independent noise (std 40 around 128) plus a smooth pattern scaled so that the neighbour ratio is
    `target_ratio` (ratio ~ noise var / (noise var + pattern var)), found by bisection on this seed."""
    rng = np.random.default_rng(5)
    noise = rng.normal(0, 40, (HT, W, 1))
    v, u = np.mgrid[0:HT, 0:W].astype(np.float64)
    pattern = np.sin(u / 6.0 + v / 10.0)[..., None]

    def frame(scale):
        return np.repeat(np.clip(128 + noise + scale * pattern, 0, 255), 3, 2).round().astype(np.uint8)
    lo, hi = 0.0, 200.0                  # ratio falls as the pattern grows
    for _ in range(40):
        mid = (lo + hi) / 2
        if assess(frame(mid)).stats['neighbour_ratio'] > target_ratio:
            lo = mid
        else:
            hi = mid
    return frame((lo + hi) / 2)


@pytest.mark.parametrize('delta,expect', [(0.02, 'noise'), (-0.02, None)])
def test_noise_ratio_either_side(delta, expect):
    q = assess(_noise_with_structure(NOISE_RATIO + delta))
    assert abs(q.stats['neighbour_ratio'] - (NOISE_RATIO + delta)) < 0.01, q.stats
    assert (q.reason or '').split(':')[0] == (expect or ''), (q.reason, q.stats)
