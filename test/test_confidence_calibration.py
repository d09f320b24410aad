"""The confidence calibration map (core/confidence_calibration.py), its fit (evaluation/calibration_fit.py) and where
the estimator applies it, on small cases computed by hand."""
from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch

from dpv_sensor import params as P
from dpv_sensor.core import confidence_calibration as CC
from dpv_sensor.evaluation import calibration_fit as F
from dpv_sensor.evaluation import metrics as M
from dpv_sensor.stream.estimator import Estimator
from dpv_sensor.stream.estimator_config import calibration_signature

from test_estimator import push_all, sideways, small_config

SIG = CC.signature('classical', None, (64, 48), (0.5, 8.0), 16, 'ratio 1.25')


def _map(x, y, estimator=None):
    return CC.ConfidenceCalibration(tuple(x), tuple(y), dict(estimator or SIG))


def _file(tmp_path, data, name='cal.json'):
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return path


def _ece_by_hand(conf, hit, bins=10):
    """sum over equal-width bins of (share of pixels) x |mean confidence - share of hits|, written out."""
    total = 0.0
    for b in range(bins):
        lo, hi = b / bins, (b + 1) / bins
        inside = (conf >= lo) & ((conf < hi) if b < bins - 1 else (conf <= hi))
        if inside.any():
            total += inside.mean() * abs(conf[inside].mean() - hit[inside].mean())
    return total


# ----------------------------------------------------------------------------------------------------
# the map
# ----------------------------------------------------------------------------------------------------

def test_map_is_linear_between_knots_flat_outside_and_same_for_numpy_and_torch():
    cal = _map([0.2, 0.5, 0.9], [0.1, 0.4, 0.8])
    assert cal.apply(0.35) == pytest.approx(0.25)           # halfway between 0.2 and 0.5
    assert cal.apply(0.7) == pytest.approx(0.6)
    assert cal.apply(0.0) == pytest.approx(0.1) and cal.apply(1.0) == pytest.approx(0.8)
    c = np.linspace(0, 1, 1001).astype(np.float32)
    out = cal.apply(c)
    assert out.dtype == np.float32 and out.shape == c.shape
    t = cal.apply(torch.from_numpy(c).reshape(1, 7, 143))
    assert t.dtype == torch.float32 and t.shape == (1, 7, 143)
    np.testing.assert_allclose(t.reshape(-1).numpy(), out, atol=1e-7)


def test_fitted_map_is_monotone_in_the_band_mass():
    """Hits that fall with the confidence in places (noise, a dip) still give a non-decreasing map."""
    rng = np.random.default_rng(3)
    c = rng.uniform(0, 1, 20000)
    p = np.clip(0.3 + 0.5 * c + 0.25 * np.sin(9 * c), 0, 1)     # not monotone itself
    hit = rng.uniform(0, 1, c.size) < p
    cal = F.fit_calibration(c, hit, SIG)
    grid = np.linspace(0, 1, 5001)
    assert np.all(np.diff(cal.apply(grid)) >= 0)
    assert np.all(np.diff(cal.confidence) > 0) and np.all(np.diff(cal.probability) >= 0)
    assert cal.confidence[0] == 0.0 and cal.confidence[-1] == 1.0
    assert len(cal.confidence) <= F.FIT_BINS + 2


def test_pool_adjacent_violators_by_hand():
    # 0.5 (w 1) > 0.2 (w 3): pooled to (0.5 + 0.6) / 4 = 0.275; then 0.9, and 0.8 (w 2) < 0.9 (w 2): 0.85 each
    np.testing.assert_allclose(F.pool_adjacent_violators([0.1, 0.5, 0.2, 0.9, 0.8], [1, 1, 3, 2, 2]),
                               [0.1, 0.275, 0.275, 0.85, 0.85])
    # a violation that reaches back: 0.3, 0.6, 0.4 -> 0.3, 0.5, 0.5; then 0.1 (w 2) pools the last three to
    # (0.5 * 2 + 0.1 * 2) / 4 = 0.3, which no longer falls below the first
    np.testing.assert_allclose(F.pool_adjacent_violators([0.3, 0.6, 0.4, 0.1], [1, 1, 1, 2]), [0.3] * 4)
    with pytest.raises(ValueError, match='positive'):
        F.pool_adjacent_violators([0.1, 0.2], [1, 0])


def test_fit_by_hand_on_four_groups():
    """Four confidences, 100 pixels each, with hit shares 0.2, 0.5, 0.8, 0.6: four bins; the last two violate
    and pool to 0.7. Knots: flat end at 0, the bins, the pooled run's two ends, flat end at 1."""
    conf = np.repeat([0.1, 0.3, 0.6, 0.9], 100)
    hit = np.concatenate([np.arange(100) < k for k in (20, 50, 80, 60)])
    cal = F.fit_calibration(conf, hit, SIG, bins=4)
    np.testing.assert_allclose(cal.confidence, [0.0, 0.1, 0.3, 0.6, 0.9, 1.0])
    np.testing.assert_allclose(cal.probability, [0.2, 0.2, 0.5, 0.7, 0.7, 0.7])
    assert cal.fitted_on['pixels'] == 400 and cal.fitted_on['bins'] == 4
    # ECE by hand, 10 equal-width bins: raw |0.1-0.2| + |0.3-0.5| + |0.6-0.8| + |0.9-0.6| over four equal groups
    assert M.expected_calibration_error(conf, hit) == pytest.approx((0.1 + 0.2 + 0.2 + 0.3) / 4)
    # calibrated: 0.2, 0.5, 0.7, 0.7 -> groups 3 and 4 share the bin [0.7, 0.8): |0.7 - (0.8 + 0.6) / 2| = 0
    assert M.expected_calibration_error(cal.apply(conf), hit) == pytest.approx(0.0, abs=1e-12)
    report = F.calibration_report(conf, hit, cal)
    assert report['raw']['ece'] == pytest.approx(0.2) and report['calibrated']['ece'] == pytest.approx(0.0, abs=1e-12)


def test_equal_count_bins_merge_a_shared_confidence():
    """Half of the pixels at confidence exactly 0 (no parallax support) fill several equal-count bins: one knot."""
    conf = np.concatenate([np.zeros(600), np.linspace(0.5, 1.0, 600)])
    hit = np.concatenate([np.arange(600) % 3 == 0, np.ones(600, bool)])
    x, y, w = F.equal_count_bins(conf, hit, 12)
    assert x[0] == 0.0 and w[0] == 600 and y[0] == pytest.approx(1 / 3)
    assert np.all(np.diff(x) > 0) and w.sum() == 1200
    with pytest.raises(ValueError, match='no'):
        F.equal_count_bins([], [])


def test_fit_on_a_known_hit_probability_is_calibrated():
    """Hits drawn with probability c^2 at confidence c (c uniform): the fitted map follows c^2 and its output is
    calibrated on fresh pairs (ECE computed by hand, 10 equal-width bins) where the raw confidence is not."""
    rng = np.random.default_rng(0)
    c_fit = rng.uniform(0, 1, 200_000)
    cal = F.fit_calibration(c_fit, rng.uniform(0, 1, c_fit.size) < c_fit ** 2, SIG)
    grid = np.linspace(0.05, 0.95, 19)
    assert np.abs(cal.apply(grid) - grid ** 2).max() < 0.03
    c = rng.uniform(0, 1, 200_000)
    hit = rng.uniform(0, 1, c.size) < c ** 2
    # raw: E|c - c^2| over c uniform = 1/6
    assert _ece_by_hand(c, hit) == pytest.approx(1 / 6, abs=0.01)
    ece = _ece_by_hand(cal.apply(c), hit)
    assert ece < 0.01
    assert M.expected_calibration_error(cal.apply(c), hit) == pytest.approx(ece, abs=1e-9)


def test_confidence_events_are_the_scored_pixels_and_the_delta1_event():
    gt = np.array([[1.0, 2.0, 0.0], [4.0, np.nan, 10.0]])
    pred = np.array([[1.2, 3.0, 1.0], [np.nan, 1.0, 12.0]])
    conf = np.array([[0.9, 0.4, 0.5], [0.7, 0.6, np.nan]])
    c, hit = M.confidence_events(pred, gt, conf)
    np.testing.assert_array_equal(c, [0.9, 0.4, 0.0])          # valid GT and a prediction; NaN confidence -> 0
    np.testing.assert_array_equal(hit, [True, False, True])      # 1.2/1 < 1.25, 3/2 > 1.25, 12/10 < 1.25
    c, hit = M.confidence_events(pred, gt, conf, max_depth=8.0)  # GT 10 not scored
    np.testing.assert_array_equal(c, [0.9, 0.4])


# ----------------------------------------------------------------------------------------------------
# the file
# ----------------------------------------------------------------------------------------------------

def _good():
    return _map([0.0, 0.5, 1.0], [0.2, 0.6, 0.9]).to_dict() | {'fitted_on': {'source': 'hand'}}


def test_save_and_load_round_trip(tmp_path):
    cal = F.fit_calibration(np.linspace(0, 1, 500), np.arange(500) % 2 == 0, SIG, fitted_on={'source': 'x'})
    path = CC.save(cal, tmp_path / 'sub' / 'c.json')
    back = CC.load(path)
    assert back.confidence == cal.confidence and back.probability == cal.probability
    assert back.estimator == SIG and back.fitted_on['source'] == 'x' and back.name == 'c.json'


def _without(key):
    d = _good()
    del d[key]
    return d


def _with(path, value):
    d = copy.deepcopy(_good())
    target = d
    for k in path[:-1]:
        target = target[k]
    target[path[-1]] = value
    return d


MALFORMED = [
    ('not json {', 'not JSON'),
    ([1, 2], 'not an object'),
    (_without('knots'), 'missing key knots'),
    (_without('estimator'), 'missing key estimator'),
    (_with(['format'], 'other'), "format is 'other'"),
    (_with(['version'], 2), 'version 2 is not supported'),
    (_with(['knots', 'confidence'], [0.0, 0.7, 0.5]), 'not strictly increasing (0.7 then 0.5)'),
    # equal knots: the torch path would divide 0 by 0 between them (at the last two, for every confidence above)
    (_with(['knots', 'confidence'], [0.0, 0.5, 0.5]), 'not strictly increasing (0.5 then 0.5)'),
    (_with(['knots', 'confidence'], [0.0, 0.0, 1.0]), 'not strictly increasing (0 then 0)'),
    (_with(['knots', 'probability'], [0.2, 0.6, 0.5]), 'decreases (0.6 then 0.5'),
    (_with(['knots', 'probability'], [0.2, 0.6, 1.5]), 'holds 1.5, outside [0, 1]'),
    (_with(['knots', 'confidence'], [-0.1, 0.5, 1.0]), 'holds -0.1, outside [0, 1]'),
    ('{"format": "dpv_sensor.confidence_calibration", "version": 1, "estimator": {}, '
     '"knots": {"confidence": [0, NaN], "probability": [0, 1]}}', 'non-finite'),
    (_with(['knots', 'probability'], [0.2, 0.6]), 'knots.confidence has 3 values but knots.probability 2'),
    (_with(['knots', 'confidence'], [0.5]) | {'knots': {'confidence': [0.5], 'probability': [0.5]}}, 'two knots'),
    (_with(['knots', 'confidence'], '0,1'), 'must be a list of numbers'),
    (_with(['knots', 'confidence'], [0, 'a', 1]), 'numbers only'),
    (_with(['estimator'], {'measurement': 'network'}), "'estimator' lacks weights, processing_size"),
    (_with(['estimator', 'processing_size'], [320]), "'estimator' is malformed"),
    (_with(['fitted_on'], 'yesterday'), "'fitted_on' must be an object"),
]


@pytest.mark.parametrize('data,message', MALFORMED, ids=[m for _, m in MALFORMED])
def test_load_refuses_a_malformed_file_saying_what_is_wrong(tmp_path, data, message):
    with pytest.raises(CC.CalibrationError) as info:
        CC.load(_file(tmp_path, data))
    assert message in str(info.value)


def test_load_refuses_a_missing_file(tmp_path):
    with pytest.raises(CC.CalibrationError, match='no such file'):
        CC.load(tmp_path / 'absent.json')


def test_knots_just_apart_are_taken_and_the_torch_path_stays_finite(tmp_path):
    """The next float above an equal knot is strictly increasing: loaded, and the torch path (which divides by the
    knots' spacing) agrees with numpy on both sides of and between the close pair, and at the last knot."""
    close = float(np.nextafter(0.5, 1.0))
    cal = CC.load(_file(tmp_path, _with(['knots', 'confidence'], [0.0, 0.5, close])))
    assert cal.confidence == (0.0, 0.5, close)
    c = np.array([0.0, 0.25, 0.5, close, 0.75, 1.0])
    out = cal.apply(c)
    np.testing.assert_allclose(out, [0.2, 0.4, 0.6, 0.9, 0.9, 0.9])     # 0.2 + 0.4 * c below 0.5, a step to 0.9
    t = cal.apply(torch.from_numpy(c))
    assert torch.isfinite(t).all()
    np.testing.assert_allclose(t.numpy(), out, atol=1e-12)


def _padded_to(tmp_path, size, name):
    """A valid calibration file of exactly `size` bytes (the JSON, then spaces)."""
    text = json.dumps(_good())
    return _file(tmp_path, text + ' ' * (size - len(text)), name)


def test_load_takes_a_file_at_the_size_bound_and_refuses_one_byte_more(tmp_path):
    at = _padded_to(tmp_path, CC.MAX_FILE_BYTES, 'at.json')
    assert at.stat().st_size == CC.MAX_FILE_BYTES and CC.load(at).probability == (0.2, 0.6, 0.9)
    above = _padded_to(tmp_path, CC.MAX_FILE_BYTES + 1, 'above.json')
    with pytest.raises(CC.CalibrationError) as info:
        CC.load(above)
    assert str(info.value).startswith(f'{CC.MAX_FILE_BYTES + 1} bytes, larger than the {CC.MAX_FILE_BYTES} bytes')


def test_load_refuses_a_large_file_from_its_size_without_reading_it(tmp_path):
    """A 64 MB file (sparse: no disk used) is refused with its size while the load allocates under 1 MB: the
    size was judged before anything was read (reading it, or its first MAX_FILE_BYTES, would allocate that much)."""
    import tracemalloc
    big = tmp_path / 'big.json'
    with big.open('wb') as f:
        f.truncate(64 * 1024 * 1024)
    tracemalloc.start()
    try:
        with pytest.raises(CC.CalibrationError, match=f'^{64 * 1024 * 1024} bytes, larger than'):
            CC.load(big)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1024 * 1024, peak
    with pytest.raises(CC.CalibrationError, match='^not a regular file'):
        CC.load(tmp_path)                                   # a folder


def test_signature_mismatch_names_each_setting():
    cal = _map([0.0, 1.0], [0.0, 1.0])
    cal.check_signature(CC.signature('classical', None, (64, 48), (0.5, 8.0 + 1e-9), 16, 'ratio 1.25'))
    other = CC.signature('network', '/x/lite.safetensors', (320, 256), (0.5, 8.0), 64, 'ratio 1.25')
    assert other['weights'] == 'lite.safetensors'
    with pytest.raises(CC.CalibrationError) as info:
        cal.check_signature(other)
    text = str(info.value)
    assert "measurement 'classical' (the estimator: 'network')" in text
    assert "weights none (the estimator: 'lite.safetensors')" in text
    assert 'processing_size 64x48 (the estimator: 320x256)' in text
    assert 'depth_planes 16 planes 0.5-8 m (the estimator: 64 planes 0.5-8 m)' in text
    assert 'confidence' not in text.split('the estimator: 64 planes')[1]


# ----------------------------------------------------------------------------------------------------
# the estimator
# ----------------------------------------------------------------------------------------------------

def test_estimator_applies_the_map_before_min_confidence_and_keeps_the_depth(tmp_path):
    est = Estimator(small_config())
    sig = calibration_signature(est.status)
    assert sig == SIG
    raw = push_all(est, sideways(5))[-1]
    cal = _map([0.0, 0.3, 1.0], [0.1, 0.6, 0.95], sig)
    path = CC.save(cal, tmp_path / 'cal.json')
    est_cal = Estimator(small_config(confidence_calibration=str(path)))
    assert est_cal.status.confidence_calibration == str(path)
    out = push_all(est_cal, sideways(5))[-1]
    np.testing.assert_array_equal(out.depth_hw, raw.depth_hw)            # bit-identical depth
    ok = np.isfinite(raw.depth_hw)
    assert ok.mean() > 0.5
    np.testing.assert_allclose(out.confidence_hw[ok], cal.apply(raw.confidence_hw[ok]), atol=1e-6)
    assert (out.confidence_hw[~ok] == 0).all()                            # no estimate: confidence 0, as before
    # min_confidence acts on the calibrated confidence
    thr = 0.6
    cut = push_all(Estimator(small_config(confidence_calibration=str(path), min_confidence=thr)), sideways(5))[-1]
    np.testing.assert_array_equal(np.isfinite(cut.depth_hw), ok & (out.confidence_hw >= thr))


def test_estimator_refuses_a_malformed_or_mismatched_file_naming_the_parameter(tmp_path):
    bad = _file(tmp_path, _with(['knots', 'probability'], [0.2, 0.6, 0.5]))
    with pytest.raises(P.ParameterError, match=r"parameter 'confidence_calibration' = .*cal.json' refused: "
                                                r'knots.probability decreases'):
        Estimator(small_config(confidence_calibration=str(bad)))
    other = CC.save(_map([0.0, 1.0], [0.0, 1.0], CC.signature('classical', None, (320, 256), (0.5, 8.0), 16,
                                                                'ratio 1.25')), tmp_path / 'other.json')
    with pytest.raises(P.ParameterError, match=r'confidence_calibration.*processing_size 320x256 \(the estimator: '
                                                r'64x48\)'):
        Estimator(small_config(confidence_calibration=str(other)))


# ----------------------------------------------------------------------------------------------------
# the calibrate tool
# ----------------------------------------------------------------------------------------------------

TOOL_CONFIG = ['measurement=classical', 'processing_width=64', 'processing_height=48', 'num_planes=16',
               'keyframe_max_interval=2']


def test_calibrate_tool_on_a_small_rendered_scene(tmp_path, capsys):
    from dpv_sensor.tools import calibrate as tool
    out = tmp_path / 'cal'
    rc = tool.main(['synthetic:5:24', '--width', '80', '--height', '60', '--config', *TOOL_CONFIG, '--out', str(out),
                    '--quiet'])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert '| fit |' in text and '| held-out |' in text and 'confidence_calibration:=' in text
    cal = CC.load(out / 'calibration.json')
    report = json.loads((out / 'report.json').read_text())
    assert (out / 'reliability.png').stat().st_size > 10_000
    assert cal.estimator == CC.signature('classical', None, (64, 48), (0.3, 8.0), 16, 'ratio 1.25')
    assert cal.fitted_on['source'] == 'synthetic:5:24' and cal.fitted_on['parameters']['num_planes'] == 16
    fit, held = report['fit'], report['held_out']
    # the first half of the keyframes in time to fit on, the rest to score on
    assert fit['frames'][1] < held['frames'][0] and abs(fit['keyframes'] - held['keyframes']) <= 1
    assert cal.fitted_on['pixels'] == fit['pixels'] > 1000
    # on the pixels it was fitted on, the map is calibrated up to the 10 equal-width bins' share of mixing
    assert fit['calibrated']['ece'] < min(0.05, fit['raw']['ece'])
    assert held['calibrated']['ece'] == pytest.approx(cal.fitted_on['held_out_ece_calibrated'])
    # the estimator with the same settings takes the file
    config = {k: v for k, v in (item.split('=') for item in TOOL_CONFIG)}
    est = Estimator(small_config(**{k: (v if k == 'measurement' else int(v)) for k, v in config.items()},
                                 d_min=0.3, confidence_calibration=str(out / 'calibration.json')))
    assert est.calibration is not None and est.calibration.probability == cal.probability


@pytest.mark.parametrize('args,message', [
    (['synthetic:5:24', '--fit-fraction', '1.5'], 'fit fraction must lie strictly between 0 and 1'),
    (['synthetic:5:24', '--config', 'confidence_calibration=x.json'], 'leave it unset'),
    (['synthetic:5:24', '--config', 'damping=3'], "parameter 'damping' = 3.0 is above its maximum 1.0"),
    (['/nonexistent/folder'], 'is not a sequence folder'),
])
def test_calibrate_tool_refuses_bad_arguments(tmp_path, capsys, args, message):
    from dpv_sensor.tools import calibrate as tool
    config = [] if '--config' in args else ['--config', *TOOL_CONFIG]
    assert tool.main(args + config + ['--out', str(tmp_path / 'x'), '--quiet']) == 2
    assert message in capsys.readouterr().err


def test_calibrate_tool_needs_one_source():
    from dpv_sensor.tools import calibrate as tool
    for args in ([], ['synthetic:1', '--bag', 'x.mcap', '--gt', 'y'], ['--bag', 'x.mcap']):
        with pytest.raises(SystemExit) as info:
            tool.main(args)
        assert info.value.code == 2


def test_calibrate_tool_replays_a_bag_through_the_node(tmp_path, capsys, monkeypatch):
    """--bag BAG --gt GT: the recording goes through the node process (lockstep replay), its depth images are
    matched to the GT frames; the map carries the settings the node ran with."""
    import os
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.data.sequence import write_sequence
    from dpv_sensor.data.synthetic import render_sequence
    from dpv_sensor.tools import calibrate as tool
    for name in ('ROS_DOMAIN_ID', 'ROS_LOG_DIR'):       # the replay sets them for its node: restored afterwards
        monkeypatch.setenv(name, os.environ.get(name, ''))
    seq = render_sequence(5, 24, width=80, height=60)
    write_sequence(tmp_path / 'seq', seq, lossless=True)
    R.write_sequence_bag(tmp_path / 'bag', seq, odom_rate=100.0)
    rc = tool.main(['--bag', str(tmp_path / 'bag'), '--gt', str(tmp_path / 'seq'), '--config', *TOOL_CONFIG,
                    '--out', str(tmp_path / 'cal'), '--domain-id', os.environ['ROS_DOMAIN_ID'], '--quiet'])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert '| held-out |' in text
    cal = CC.load(tmp_path / 'cal' / 'calibration.json')
    assert cal.estimator == CC.signature('classical', None, (64, 48), (0.3, 8.0), 16, 'ratio 1.25')
    assert str(tmp_path / 'bag') in cal.fitted_on['source'] and cal.fitted_on['pixels'] > 1000
