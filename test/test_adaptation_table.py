"""The adaptation table's parts: the folders it adapts on and scores (halves without and with depth, pairs both
ways), the tool's decision read from a real run, and the summary the acceptance reads, computed by hand."""
import json

import numpy as np
import pytest

from dpv_sensor.benchmarks import adaptation_table as AT
from dpv_sensor.data.sequence import Sequence, write_sequence


def _folder(path, n, depth_m):
    rng = np.random.default_rng(n)
    images = [rng.integers(0, 255, (24, 32, 3), dtype=np.uint8) for _ in range(n)]
    depths = [np.full((24, 32), depth_m, np.float32) for _ in range(n)]
    poses = []
    for i in range(n):
        T = np.eye(4)
        T[0, 3] = 0.01 * i
        poses.append(T)
    K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    seq = Sequence.from_arrays(images, depths, np.stack(poses), K, stamps=np.arange(n) * 0.1 + 5.0)
    return write_sequence(path, seq, lossless=True)


def test_halves_have_no_depth_to_adapt_on_and_the_other_half_with_depth_to_score(tmp_path):
    data = tmp_path / 'data'
    _folder(data / 'a', 10, 2.0)
    _folder(data / 'b', 7, 3.0)
    evals = AT.evaluations(data, None, ['a:b'], [], tmp_path / 'out', 60)
    assert [e.name for e in evals] == ['a (2nd half)', 'b (2nd half)', 'b (adapted on a)', 'a (adapted on b)']
    assert [e.kind for e in evals] == ['halves', 'halves', 'pair', 'pair']
    a_first, a_second = Sequence(evals[0].recording, depth=False), Sequence(evals[0].scored)
    assert not (evals[0].recording / 'depth').exists() and not a_first.has_depth
    assert (len(a_first), len(a_second)) == (5, 5)
    assert a_first.pose(4)[0, 3] == pytest.approx(0.04) and a_second.pose(0)[0, 3] == pytest.approx(0.05)
    assert a_second.stamps[0] == pytest.approx(5.5)
    np.testing.assert_array_equal(a_second.image(0), Sequence(data / 'a').image(5))   # PNG: no second JPEG loss
    assert np.allclose(a_second.depth(0), 2.0)
    b_halves = Sequence(evals[1].recording, depth=False), Sequence(evals[1].scored)
    assert (len(b_halves[0]), len(b_halves[1])) == (3, 4)
    # pairs: the whole of one adapted on (no depth), the whole of the other scored
    assert len(Sequence(evals[2].recording, depth=False)) == 10 and not (evals[2].recording / 'depth').exists()
    assert len(Sequence(evals[2].scored)) == 7 and np.allclose(Sequence(evals[2].scored).depth(0), 3.0)
    assert evals[3].recording.name == 'b_all' and evals[3].scored.name == 'a_all'
    # cached results of a folder's old content go when it is written anew (here: the source grew)
    runs = tmp_path / 'out' / 'stream' / 'runs'
    runs.mkdir(parents=True)
    (runs / 'a_second__gt__defaults.json').write_text('{}')
    (runs / 'b_second__gt__defaults.json').write_text('{}')
    (tmp_path / 'out' / 'weights' / 'a_first').mkdir(parents=True)
    AT.evaluations(data, ['b'], [], [], tmp_path / 'out', 60)              # unchanged: nothing goes
    assert (runs / 'b_second__gt__defaults.json').is_file()
    _folder(data / 'a', 12, 2.0)
    AT.evaluations(data, ['a'], [], [], tmp_path / 'out', 60)
    assert not (runs / 'a_second__gt__defaults.json').exists()
    assert not (tmp_path / 'out' / 'weights' / 'a_first').exists()
    assert (runs / 'b_second__gt__defaults.json').is_file()
    assert len(Sequence(tmp_path / 'out' / 'scored' / 'a_second')) == 6
    with pytest.raises(ValueError, match='no sequence folder'):
        AT.evaluations(data, ['c'], [], [], tmp_path / 'out', 60)
    with pytest.raises(ValueError, match='--pairs'):
        AT.evaluations(data, None, ['a:c'], [], tmp_path / 'out', 60)


def test_recordings_with_odometry_carry_the_stream_tables_noisy_poses_and_the_scored_halves_the_truth(tmp_path):
    """--recording-odometry SEED: the recordings adapted on carry the stream table's odometry-like corruption of
    that seed (as a robot's recording does), under their own names; the scored halves keep the dataset's poses."""
    from dpv_sensor.benchmarks.stream_table_inputs import odometry_poses
    data = tmp_path / 'data'
    _folder(data / 'a', 10, 2.0)
    _folder(data / 'b', 8, 3.0)
    evals = AT.evaluations(data, None, ['a:b'], [], tmp_path / 'out', 60, odometry_seed=1)
    assert [e.recording.name for e in evals] == ['a_first_odom1', 'b_first_odom1', 'a_all_odom1', 'b_all_odom1']
    truth = Sequence(data / 'a', depth=False)
    first = Sequence(evals[0].recording, depth=False)
    expected = odometry_poses(truth.subset(range(5)), 'noisy1')
    np.testing.assert_allclose(first.poses, np.stack(expected), atol=1e-9)
    assert not np.allclose(first.poses, truth.poses[:5], atol=1e-4)
    np.testing.assert_allclose(Sequence(evals[0].scored).poses, truth.poses[5:], atol=1e-9)
    np.testing.assert_allclose(Sequence(evals[2].scored).poses, Sequence(data / 'b').poses, atol=1e-9)


def test_a_recording_the_tool_refuses_is_not_adapted_and_its_message_kept(tmp_path):
    data = tmp_path / 'data'
    _folder(data / 'short', 12, 2.0)
    ev = AT.evaluations(data, None, [], [], tmp_path / 'out', 60)[0]
    tool = AT.adapt(ev, tmp_path / 'out', ['--steps', '1'])
    assert tool['decision'] == 'not run' and tool['weights'] is None
    assert 'too short' in tool['why']
    cached = json.loads((tmp_path / 'out' / 'weights' / 'short_first' / 'command.json').read_text())
    assert cached['rc'] == 2 and '--steps 1' in cached['command']


def _line(name, kind, shipped, adapted):
    keys = ('abs_rel', 'd1', 'ECE')
    return {'name': name, 'kind': kind, 'tool': {'decision': 'written', 'steps': 3, 'minutes': 1.0, 'why': None},
            'shipped': {'gt': dict(zip(keys, shipped))}, 'adapted': {'gt': dict(zip(keys, adapted))}}


def test_summary_by_hand():
    lines = [_line('x', 'halves', (0.20, 0.50, 0.10), (0.18, 0.56, 0.12)),    # -10 %, +6 points, ECE +0.02
             _line('y', 'pair', (0.40, 0.60, 0.05), (0.41, 0.60, 0.04)),      # +2.5 %, 0 points
             _line('r', 'render', (0.10, 0.90, 0.05), (0.107, 0.90, 0.05))]   # a render: apart
    s = AT.summary(lines)['gt']
    assert s['evaluations'] == 2
    assert s['mean_abs_rel_change_pct'] == pytest.approx(-3.75)
    assert s['mean_abs_rel'] == pytest.approx([0.30, 0.295])
    assert s['mean_d1_change_points'] == pytest.approx(3.0)
    assert s['worst_abs_rel_change'] == pytest.approx(0.01)
    assert s['worst_ece_change'] == pytest.approx(0.02)
    assert s['renders_worst_abs_rel_change'] == pytest.approx(0.007)
    text = AT.markdown(lines, AT.summary(lines), 'cmd')
    assert '| x | gt | 0.200 → 0.180 |' in text and '-3.8 %' in text and '+3.0 points' in text
