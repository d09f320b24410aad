"""The confidence cues (core/confidence_features.py), the logistic map on them (core/confidence_map.py) and its fit
(evaluation/calibration_fit.fit_logistic), on small cases whose answer is known by hand."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dpv_sensor.core import confidence_features as C
from dpv_sensor.core import confidence_map as CM
from dpv_sensor.core import dpv as dpv_ops
from dpv_sensor.evaluation import calibration_fit as F
from dpv_sensor.evaluation import metrics as M

D = 32
DEPTHS = dpv_ops.depth_planes(0.5, 8.0, D, dtype=torch.float64)


def _one_hot(k: int, h=2, w=3) -> torch.Tensor:
    p = torch.full((1, D, h, w), 1e-12, dtype=torch.float64)
    p[:, k] = 1.0
    return torch.log(p / p.sum(1, keepdim=True))


def test_entropy_share_is_zero_for_one_plane_and_one_for_uniform():
    assert float(C.entropy_share(_one_hot(5)).max()) < 1e-6
    uniform = torch.full((1, D, 2, 2), -math.log(D), dtype=torch.float64)
    assert torch.allclose(C.entropy_share(uniform), torch.ones(1, 2, 2, dtype=torch.float32), atol=1e-6)


def test_second_mode_mass_finds_the_mass_beyond_the_band():
    p = torch.full((1, D, 1, 1), 0.0, dtype=torch.float64)
    p[:, 20] = 0.6      # the published depth's mode
    p[:, 3] = 0.25      # a far second mode, two adjacent planes
    p[:, 4] = 0.15
    logp = torch.log(p.clamp_min(1e-30))
    depth = DEPTHS[20].reshape(1, 1, 1)
    got = float(C.second_mode_mass(logp, DEPTHS, depth, 1.25))
    assert got == pytest.approx(0.40, abs=1e-6)
    # one mode: nothing outside the band
    assert float(C.second_mode_mass(_one_hot(20, 1, 1), DEPTHS, depth, 1.25)) < 1e-9


def test_second_mode_mass_leaves_out_planes_inside_the_band():
    p = torch.zeros((1, D, 1, 1), dtype=torch.float64)
    p[:, 20] = 0.7
    p[:, 21] = 0.3      # the neighbour plane is within x1.25 of plane 20's depth
    assert float(C.second_mode_mass(torch.log(p.clamp_min(1e-30)), DEPTHS, DEPTHS[20].reshape(1, 1, 1), 1.25)) < 1e-9


def test_image_texture_of_a_ramp_is_its_slope():
    x = torch.arange(20, dtype=torch.float32) * 0.01        # 0.01 per pixel along x
    img = x.expand(3, 16, 20)[None].clone()
    tex = C.image_texture(img, box=1)
    assert torch.allclose(tex[0, 2:-2, 2:-2], torch.full((12, 16), 0.01), atol=1e-6)
    assert float(C.image_texture(torch.full((1, 3, 8, 8), 0.4)).abs().max()) < 1e-7


def _camera(h=12, w=16, f=10.0):
    return torch.tensor([[[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]]], dtype=torch.float32)


def test_photometric_residual_counts_views_and_measures_a_brightness_change():
    torch.manual_seed(0)
    ref = torch.rand(1, 3, 12, 16)
    depth = torch.full((1, 12, 16), 2.0)
    K = _camera()
    T = torch.eye(4).expand(2, 4, 4).clone()
    srcs = torch.stack([ref[0], ref[0] + 0.1])             # same view; same view 0.1 brighter
    residual, views = C.photometric_residual(ref, srcs, depth, K, T)
    assert torch.all(views == 2)
    assert torch.allclose(residual, torch.full_like(residual, 0.05), atol=1e-5)
    # a source that looks away sees nothing: no view, no residual
    away = torch.eye(4)[None].clone()
    away[0, 2, 3] = -10.0                                   # the points end up behind it
    residual, views = C.photometric_residual(ref, ref, depth, K, away)
    assert torch.all(views == 0) and torch.all(torch.isnan(residual))


def test_innovation_is_the_plane_distance_and_nan_without_prediction():
    got = C.innovation_planes(_one_hot(10), _one_hot(13), DEPTHS.float(), 'median')
    assert torch.allclose(got, torch.full_like(got, 3.0), atol=1e-3)
    assert torch.all(torch.isnan(C.innovation_planes(_one_hot(10), None, DEPTHS.float(), 'median')))


def _cues(n, rng):
    conf = rng.uniform(0.05, 0.95, n)
    tex = rng.uniform(0.001, 0.1, n)
    return {'confidence': conf, 'texture': tex}


def test_fit_logistic_recovers_a_known_map_and_is_calibrated():
    rng = np.random.default_rng(1)
    cues = _cues(200_000, rng)
    z = 1.5 * CM.logit(cues['confidence']) + 0.8 * np.log(cues['texture'] + CM.TEXTURE_FLOOR) + 2.0
    hit = rng.uniform(size=z.size) < 1.0 / (1.0 + np.exp(-z))
    m = F.fit_logistic(cues, hit, ('logit_confidence', 'log_texture'), l2=0.0)
    assert m.weights == pytest.approx((1.5, 0.8), abs=0.05)
    assert m.intercept == pytest.approx(2.0, abs=0.15)
    test = _cues(100_000, np.random.default_rng(2))
    zt = 1.5 * CM.logit(test['confidence']) + 0.8 * np.log(test['texture'] + CM.TEXTURE_FLOOR) + 2.0
    hit_t = np.random.default_rng(3).uniform(size=zt.size) < 1.0 / (1.0 + np.exp(-zt))
    assert M.expected_calibration_error(m.apply(test), hit_t) < 0.01
    # the raw confidence, which ignores the texture, is far off
    assert M.expected_calibration_error(test['confidence'], hit_t) > 0.05


def test_the_map_never_falls_with_the_confidence():
    rng = np.random.default_rng(4)
    cues = _cues(50_000, rng)
    hit = rng.uniform(size=50_000) < 1.0 - cues['confidence']        # labels that fall with the confidence
    m = F.fit_logistic(cues, hit, ('logit_confidence', 'log_texture'))
    assert m.weights[0] == 0.0
    grid = {'confidence': np.linspace(0.01, 0.99, 50), 'texture': np.full(50, 0.02)}
    assert np.all(np.diff(CM.ConfidenceMap(('logit_confidence',), (0.7,), -0.2).apply(grid)) > 0)
    with pytest.raises(ValueError, match='must not be negative'):
        CM.ConfidenceMap(('logit_confidence',), (-0.1,), 0.0)
    with pytest.raises(KeyError, match='unknown map inputs'):
        CM.design_matrix(grid, ('no_such_cue',))


def test_the_estimator_gathers_the_cues_of_a_keyframe_only_when_asked():
    from dpv_sensor.core.nets import DPVNet
    from dpv_sensor.stream.confidence_features import FEATURES
    from dpv_sensor.stream.estimator import Estimator
    from test_estimator import push_all, sideways, small_config
    torch.manual_seed(0)
    net = DPVNet('lite')
    net.eval()
    cfg = dict(measurement='auto', filter_mode='knet', output_resolution='processing')
    plain = [o for o in push_all(Estimator(small_config(**cfg), model=net), sideways(8)) if o is not None]
    assert plain and all(o.features is None for o in plain)
    est = Estimator(small_config(**cfg), model=net)
    est.collect_features = True
    outs = [o for o in push_all(est, sideways(8)) if o is not None]
    kfs = [o for o in outs if o.is_keyframe]
    assert len(kfs) >= 2
    for a, b in zip(plain, outs):       # the cues change nothing that is published
        assert np.array_equal(a.depth_hw, b.depth_hw, equal_nan=True)
        assert np.array_equal(a.confidence_hw, b.confidence_hw)
    for o in kfs:
        assert set(o.features) == set(FEATURES)
        for k, v in o.features.items():
            assert v.shape == o.depth_hw.shape and v.dtype == np.float32, k
        has = np.isfinite(o.depth_hw)
        # the confidence cue is the published confidence where there is an estimate
        assert np.allclose(o.features['confidence'][has], o.confidence_hw[has], atol=1e-6)
        assert np.all(o.features['views'] <= est.config.window_size - 1)
        assert np.all((o.features['entropy'] >= 0) & (o.features['entropy'] <= 1 + 1e-6))
    # the first keyframe of a belief has no prediction: its innovation is NaN; later ones have one
    assert np.all(np.isnan(kfs[0].features['innovation']))
    assert np.isfinite(kfs[-1].features['innovation']).all()


def test_auroc_by_hand():
    from dpv_sensor.evaluation.confidence_study import auroc
    assert auroc(np.array([0.1, 0.2, 0.8, 0.9]), np.array([0, 0, 1, 1])) == 1.0
    assert auroc(np.array([0.9, 0.8, 0.2, 0.1]), np.array([0, 0, 1, 1])) == 0.0
    assert auroc(np.array([0.5, 0.5, 0.5, 0.5]), np.array([0, 1, 0, 1])) == 0.5
    # one positive above one of two negatives: 1 of 2 pairs ordered; a NaN score is left out
    assert auroc(np.array([0.3, 0.1, 0.5, np.nan]), np.array([1, 0, 0, 1])) == 0.5
    assert np.isnan(auroc(np.array([0.1, 0.2]), np.array([1, 1])))


def test_study_scores_maps_on_a_sequence_they_were_not_fitted_on(tmp_path):
    """Three fake sequences whose hits follow one known law of the confidence and the texture: every held-out map
    that sees the texture is calibrated, the raw confidence is not."""
    from dpv_sensor.evaluation import confidence_study as S
    from dpv_sensor.stream.confidence_features import FEATURES
    rng = np.random.default_rng(5)
    names = ['a', 'b', 'c']
    for i, n in enumerate(names):
        m = 30_000
        cues = {k: rng.uniform(0.1, 0.9, m).astype(np.float32) for k in FEATURES}
        cues['texture'] = rng.uniform(0.001, 0.05, m).astype(np.float32) * (i + 1)
        cues['innovation'] = rng.uniform(0, 3, m).astype(np.float32)
        z = 2.0 * CM.logit(cues['confidence']) + 1.0 * np.log(cues['texture'] + CM.TEXTURE_FLOOR) + 3.0
        hit = rng.uniform(size=m) < 1.0 / (1.0 + np.exp(-z))
        extra = {'depth': rng.uniform(1, 3, m), 'frame_confidence': np.full(m, 0.5), 'frame_parallax_px':
                 np.full(m, 3.0), 'frame_texture': np.full(m, 0.01), 'frame_photometric': np.full(m, 0.02),
                 'rel_err': np.where(hit, 0.05, 0.5), 'keyframe': np.repeat(np.arange(30), 1000), 'hit': hit}
        np.savez(tmp_path / f'{n}__gt.npz', **cues, **extra)
    study = S.run_study(tmp_path, names, ['gt'])
    loso = study['json']['loso']['real only']
    for n in names:
        row = loso[f'{n} gt']
        assert row['cues']['ece'] < 0.03, n
        assert row['raw']['ece'] > 0.05, n
    assert '## Maps held out' in study['markdown']
