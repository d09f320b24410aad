"""The calibration benchmark (dpv_sensor.benchmarks.calibration) on tiny sizes."""
import json
import math

import numpy as np
import pytest
import torch

from dpv_sensor.benchmarks import calibration as cal
from dpv_sensor.common import to_jsonable
from dpv_sensor.training.dataset import TRAIN_SEED_BASE

from conftest import SHARED_DATA

W, H = 64, 48
TEMPS = (0.05, 0.15)


@pytest.fixture(scope='module', autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)            # tiny tensors: more threads only add overhead (and contention)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope='module')
def model():
    from dpv_sensor.core.nets.model import DPVNet
    torch.manual_seed(0)
    return DPVNet('lite').eval()        # random init: the benchmark's plumbing, not the weights' quality


def _check_rows(res, datasets):
    rows = res['rows']
    assert {r['dataset'] for r in rows} == set(datasets)
    for ds in datasets:
        sources = {(r['source'], r['mode']) for r in rows if r['dataset'] == ds}
        assert {('net', m) for m in ('none', 'global', 'knet')} <= sources
        assert sum(s.startswith('classical') for s, _ in sources) >= 2    # tuned (and default) x none/global
    for r in rows:
        assert math.isfinite(r['nll_meas_q']) and math.isfinite(r['nll_filtered_q']), r
        assert math.isfinite(r['abs_rel']) and math.isfinite(r['confident_half_ratio']), r
        if r['source'] == 'net':
            assert math.isfinite(r['nll_full']), r
        if r['mode'] == 'none':       # no filter: the belief is the measurement
            assert r['nll_filtered_q'] == pytest.approx(r['nll_meas_q'])
        # 'below random' means below at every removed fraction: the share of such fractions is then 1
        assert isinstance(r['below_random'], bool) and 0.0 <= r['below_random_share'] <= 1.0, r
        assert r['below_random'] == (r['below_random_share'] == 1.0), r


def test_below_random_hand_made_curves():
    # the first point (nothing removed) is the same for both curves and is not judged
    c = {'sparsification': np.array([1.0, 0.5, 0.2]), 'random': np.array([1.0, 0.8, 0.6])}
    assert cal._below_random(c) == (True, 1.0)
    c = {'sparsification': np.array([1.0, 0.9, 0.2, 0.7]), 'random': np.array([1.0, 0.8, 0.6, 0.6])}
    assert cal._below_random(c) == (False, pytest.approx(1 / 3))
    c = {'sparsification': np.array([1.0, np.nan]), 'random': np.array([1.0, 0.5])}
    assert cal._below_random(c)[0] is None and cal._below_random(None)[0] is None


def test_synthetic_tiny(model, tmp_path, capsys):
    res = cal.run(model, synthetic_seeds=[0], width=W, height=H, tune_seeds=[TRAIN_SEED_BASE],
                  temperatures=TEMPS, skip_sun3d=True, out=str(tmp_path), progress=False)
    t = res['temperature']
    assert t['tuned'] in TEMPS
    assert t['default'] == pytest.approx(0.07)
    assert set(t['tuning_nll_meas_q']) == {f'{x:g}' for x in TEMPS}
    assert t['tuned'] == min(TEMPS, key=lambda x: t['tuning_nll_meas_q'][f'{x:g}'])
    _check_rows(res, ['synthetic'])
    tuned = [r for r in res['rows'] if '(tuned)' in r['source']]
    assert tuned and all(r['temperature'] == t['tuned'] for r in tuned)
    assert (tmp_path / 'sparsification_synthetic.png').stat().st_size > 0
    json.dumps(to_jsonable(res), allow_nan=False)                     # JSON-ready
    out = capsys.readouterr().out
    assert 'NLL meas 1/4' in out and 'synthetic' in out and f"tuned {t['tuned']:g}" in out


@pytest.mark.parametrize('seeds', [[0], [TRAIN_SEED_BASE, 5], [TRAIN_SEED_BASE - 1], []])
def test_refuses_non_training_tuning_seeds(model, seeds):
    with pytest.raises(ValueError, match='training seed|tuning seed'):
        cal.run(model, synthetic_seeds=[0], width=W, height=H, tune_seeds=seeds, temperatures=TEMPS,
                skip_sun3d=True, progress=False, quiet=True)


def test_refuses_training_seeds_as_heldout(model):
    with pytest.raises(ValueError, match='not held out'):
        cal.run(model, synthetic_seeds=[TRAIN_SEED_BASE], width=W, height=H, tune_seeds=[TRAIN_SEED_BASE],
                temperatures=TEMPS, skip_sun3d=True, progress=False, quiet=True)


def test_render_batches_split_guard():
    from dpv_sensor.training.validation import render_validation_batches
    lay = cal._layout(5)
    with pytest.raises(ValueError):
        render_validation_batches([3], 5, 2, W, H, lay, split='train')
    with pytest.raises(ValueError):
        render_validation_batches([TRAIN_SEED_BASE], 5, 2, W, H, lay, split='val')


def test_sun3d_tiny(model, tmp_path):
    for n in cal.SUN3D_SEQUENCES:
        if not (SHARED_DATA / n / 'poses.txt').is_file():
            pytest.skip(f'{SHARED_DATA / n} is absent (the shared data folder is only on development machines)')
    batches, info = cal.sun3d_batches([str(SHARED_DATA / cal.SUN3D_SEQUENCES[0])], 2, 8, W, H)
    assert len(batches) == 2 and info[0]['frames'] != info[1]['frames']
    assert batches[0]['images'].shape[-2:] == (H, W)
    res = cal.run(model, synthetic_seeds=[], sun3d_windows=1, width=W, height=H, tune_seeds=[TRAIN_SEED_BASE],
                  temperatures=TEMPS, data_dir=SHARED_DATA, out=str(tmp_path), progress=False, quiet=True)
    _check_rows(res, ['sun3d'])
    assert res['datasets']['sun3d']['num_windows'] == 2               # one per fragment
    assert (tmp_path / 'sparsification_sun3d.png').is_file()
