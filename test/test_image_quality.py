"""The degenerate-frame detector: each kind of frame is named, real-looking frames pass."""
import numpy as np
import pytest

from dpv_sensor.image_quality import assess

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
