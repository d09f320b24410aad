"""studies.error_breakdown: the groups on hand-made frames, the window's view count on a pure translation."""
import json

import numpy as np
import pytest
import torch

from dpv_sensor.studies import error_breakdown as eb


def _K(fx=100.0, w=64, h=48):
    return np.array([[fx, 0, (w - 1) / 2], [0, fx, (h - 1) / 2], [0, 0, 1]], np.float64)


def _pose(x=0.0, z=0.0):
    T = np.eye(4)
    T[0, 3], T[2, 3] = x, z
    return T


def test_views_of_a_sideways_step_leave_the_leading_columns_unseen():
    """Plane at 2 m, fx 100: a camera 0.205 m to the right of the other sees u in the other at
    u + 100*0.205/2 = u + 10.25, so columns 53..63 (u + 10.25 > 63) lie outside the other image; a second,
    identical other camera doubles the count."""
    gt = np.full((48, 64), 2.0)
    K = _K()
    views = eb.views_of_window(gt, K, _pose(0.205), [_pose(0.0)])
    assert (views[:, :53] == 1).all() and (views[:, 53:] == 0).all()
    views2 = eb.views_of_window(gt, K, _pose(0.205), [_pose(0.0), _pose(0.0)])
    assert (views2 == 2 * views).all()
    # a camera behind the plane's far side (moved 3 m forward, past the plane) sees nothing; no GT -> 0
    assert (eb.views_of_window(gt, K, _pose(0.0), [_pose(0.0, z=3.0)]) == 0).all()
    gt[0, 0] = np.nan
    assert eb.views_of_window(gt, K, _pose(0.0), [_pose(0.0)])[0, 0] == 0


def test_window_sources_follow_the_mode():
    kfs = [0, 3, 7, 12, 15, 20, 24]
    assert eb.window_others(kfs, 0, 5, 'causal') == []
    assert eb.window_others(kfs, 2, 5, 'causal') == [0, 3]
    assert eb.window_others(kfs, 6, 5, 'causal') == [7, 12, 15, 20]
    assert eb.window_others(kfs, 3, 5, 'centered') == [3, 7, 15, 20]
    assert eb.window_others(kfs, 6, 5, 'centered') == [15, 20]
    assert eb.window_others(kfs, 6, 3, 'causal') == [15, 20]


def test_keyframe_frames_replays_the_selector():
    """A straight walk at 2 cm a frame with the 5 cm baseline: keyframes every third frame (6 cm > 5 cm)."""
    from dpv_sensor.stream.estimator import EstimatorConfig
    poses = [_pose(0.02 * i) for i in range(10)]
    assert eb.keyframe_frames(poses, EstimatorConfig()) == [0, 3, 6, 9]


def test_breakdown_groups_on_a_frame_with_one_wrong_block():
    """GT: 1.2 m on the left half, 3.5 m on the right; the prediction is exact except for a top-left 8x8 block that
    is 50 % too far. Everything wrong is gross, near, on the left: the shares and the cell map say so."""
    gt = np.full((48, 64), 1.2)
    gt[:, 32:] = 3.5
    pred = gt.copy()
    pred[:8, :8] *= 1.5
    views = np.full(gt.shape, 2)
    views[:, :8] = 0
    acc = eb.ErrorBreakdown(0.3, 8.0, edge_radius=2)
    acc.add(pred, gt, views)
    s = acc.summary()
    n = 48 * 64
    assert s['pixels'] == n and s['abs_rel'] == pytest.approx(64 * 0.5 / n)
    g = s['groups']
    gross, unseen = g['size']['gross'], g['views']['0']
    assert gross['pixel_fraction'] == pytest.approx(64 / n) and gross['abs_rel'] == pytest.approx(0.5)
    assert g['size']['gross']['error_share'] == pytest.approx(1.0) and g['size']['fine']['abs_rel'] == 0.0
    assert g['gt_depth']['1-1.5']['error_share'] == pytest.approx(1.0)
    assert g['gt_depth']['3-4']['pixel_fraction'] == pytest.approx(0.5)
    assert unseen['error_share'] == pytest.approx(1.0) and unseen['abs_rel'] == pytest.approx(64 * 0.5 / (48 * 8))
    # the GT jump between columns 31 and 32 is the only edge; dilated by 2 px it covers columns 29..34
    assert g['edge']['edge']['pixel_fraction'] == pytest.approx(6 * 48 / n) and g['edge']['edge']['abs_rel'] == 0.0
    for group in g.values():
        assert sum(r['pixel_fraction'] for r in group.values()) == pytest.approx(1.0)
        assert sum(r['error_share'] for r in group.values()) == pytest.approx(1.0)
    assert 'texture' not in g                    # no image given
    cells = np.array(s['cells_abs_rel'])
    assert cells[0, 0] == pytest.approx(0.5) and cells[1, 0] == pytest.approx(0.5 * 16 / 48)   # cells are 6 x 8 px
    assert np.count_nonzero(cells) == 2
    # pixels without a prediction or outside the depth range are not scored
    pred2 = pred.copy()
    pred2[40:, :] = np.nan
    acc2 = eb.ErrorBreakdown(0.3, 3.0)
    acc2.add(pred2, gt)
    assert acc2.summary()['pixels'] == 40 * 32 and 'views' not in acc2.summary()['groups']


def test_texture_thirds_put_a_flat_wall_in_the_weak_third():
    """Left half a uniform grey wall, right half a 4-px checkerboard; the prediction is 20 % off on a block inside
    the wall, far from the checkerboard: the weak third holds all of the error."""
    gt = np.full((48, 64), 2.0)
    image = np.full((48, 64, 3), 128, np.uint8)
    checker = ((np.arange(32)[None, :] // 4) + (np.arange(48)[:, None] // 4)) % 2 == 0
    image[:, 32:] = np.where(checker, 30, 220)[..., None]
    assert eb.local_texture(image)[:, :24].max() == 0.0 and eb.local_texture(image)[:, 36:].min() > 0.1
    pred = gt.copy()
    pred[10:30, 4:20] *= 1.2
    acc = eb.ErrorBreakdown(0.3, 8.0)
    acc.add(pred, gt, image_hw3=image)
    t = acc.summary()['groups']['texture']
    assert t['weak']['error_share'] == pytest.approx(1.0) and t['weak']['pixel_fraction'] >= 1 / 3
    assert t['strong']['abs_rel'] == 0.0
    assert sum(r['pixel_fraction'] for r in t.values()) == pytest.approx(1.0)


def test_cli_streams_rendered_seeds_and_writes_json_and_png(tmp_path, capsys, monkeypatch):
    """The CLI on a short rendered sequence with random lite weights: its pooled abs_rel equals the pooled abs_rel
    of the depth the estimator published in that run, computed by hand; bad seeds and unreadable weights are refused
    (exit 2)."""
    from keyframe_spy import KeyframeSpy, pooled_abs_rel
    from dpv_sensor.data.synthetic import render_sequence
    from dpv_sensor.core.nets.checkpoint import save_checkpoint
    from dpv_sensor.core.nets.model import DPVNet
    torch.manual_seed(5)
    model = DPVNet('lite').eval()
    w = tmp_path / 'w.safetensors'
    save_checkpoint(str(w), model, metadata={'steps': 1})
    out = tmp_path / 'eb'
    spy = KeyframeSpy(monkeypatch)
    assert eb.main(['--weights', str(w), '--seeds', '22', '--frames', '14', '--threads', '1', '--out', str(out)]) == 0
    s = json.loads((out / 'error_breakdown.json').read_text())
    assert (out / 'error_breakdown.png').stat().st_size > 10_000
    assert set(s['groups']) == {'gt_depth', 'edge', 'size', 'texture', 'views'} and s['seeds'] == [22]
    assert 'pixel-pooled abs_rel' in capsys.readouterr().out
    # the pooled abs_rel of the depth the estimator published with these weights, computed here
    ((pipe, outputs),) = spy.runs()
    loaded = pipe.estimator.model.state_dict()
    assert all(torch.equal(v, loaded[k]) for k, v in model.state_dict().items()) and outputs
    by_hand = pooled_abs_rel(outputs, render_sequence(22, 14, width=320, height=240, lazy=True), pipe.estimator)
    assert s['abs_rel'] == pytest.approx(by_hand, rel=1e-6)
    # a sequence folder (the format of the shared development data) gives the same figures as the rendered seed it holds
    from dpv_sensor.data.sequence import write_sequence
    folder = write_sequence(tmp_path / 'seq22', render_sequence(22, 14, width=320, height=240), lossless=True)
    assert eb.main(['--weights', str(w), '--seeds', '', '--seqs', str(folder), '--threads', '1',
                    '--out', str(tmp_path / 'eb2')]) == 0
    s2 = json.loads((tmp_path / 'eb2' / 'error_breakdown.json').read_text())
    assert s2['seqs'] == [str(folder)] and s2['abs_rel'] == pytest.approx(s['abs_rel'], rel=2e-3)
    assert eb.main(['--weights', str(w), '--seeds', '', '--seqs', str(tmp_path / 'missing')]) == 2
    assert 'cannot read sequence folder' in capsys.readouterr().err
    assert eb.main(['--weights', str(w), '--seeds', '']) == 2
    assert 'no sequences given' in capsys.readouterr().err
    assert eb.main(['--weights', str(w), '--seeds', '120']) == 2
    assert 'not held out' in capsys.readouterr().err
    bad = tmp_path / 'bad.safetensors'
    bad.write_bytes(b'nope')
    assert eb.main(['--weights', str(bad), '--seeds', '22']) == 2
    assert 'cannot load weights' in capsys.readouterr().err
