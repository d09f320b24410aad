"""The adapt tool (dpv_sensor.tools.adapt) on rendered recordings: it never reads depth (a folder with depth/ and
the same folder without give the same weights), refuses weights that score worse on its held-out keyframes, leaves
no weights when interrupted, writes the metadata the node checks, and - the point of it - lowers the depth error
on the rest of a recording of a world the shipped weights never saw."""
import dataclasses
import json
import os

import pytest
import torch

from dpv_sensor.core.nets.checkpoint import (CheckpointError, default_weights_path, load_checkpoint,
                                             read_metadata)
from dpv_sensor.data.sequence import Sequence, write_sequence
from dpv_sensor.data.synthetic import render_sequence
from dpv_sensor.tools import adapt as tool
from shared_builds import ADAPT_FAST as FAST
from shared_builds import SMALL_ROOM, H, W, adapt_recording


@pytest.fixture(scope='module')
def folders(tmp_path_factory):
    """A 90-frame rendered recording at 160x128 written with depth/, and the same folder without depth/."""
    rec = adapt_recording(tmp_path_factory)
    return rec.with_depth, rec.without_depth


def _run(source, out, *extra, capsys=None):
    code = tool.main([str(source), '--out', str(out), *FAST, *extra])
    err = capsys.readouterr().err if capsys is not None else ''
    return code, err


def _files(folder):
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []


@pytest.fixture(scope='module')
def adapted(tmp_path_factory):
    """The tool run on the folder without depth/ (ADAPT_FAST): (out folder, exit code)."""
    rec = adapt_recording(tmp_path_factory)
    return rec.adapted, rec.code


@pytest.fixture(scope='module')
def adapted_with_depth_and_gt(folders, tmp_path_factory):
    """The tool run the same way on the folder with depth/, scored against that folder as --gt: (out, code, stderr).
    The depth the GT scores read must not reach the weights (below)."""
    import contextlib
    import io
    out, err = tmp_path_factory.mktemp('with_depth') / 'out', io.StringIO()
    with contextlib.redirect_stderr(err):
        code = tool.main([str(folders[0]), '--out', str(out), *FAST, '--gt', str(folders[0])])
    return out, code, err.getvalue()


def test_writes_weights_report_and_metadata(adapted, folders):
    out, code = adapted
    assert code == tool.EXIT_WRITTEN
    assert _files(out) == ['report.json', 'report.png', 'weights.safetensors']
    report = json.loads((out / 'report.json').read_text())
    assert report['written'] and report['steps'] == 4 and report['held_out']['score'] == 'anchors'
    # the photometric score is reported beside the anchors' judge, with its own verdict
    photometric = report['held_out']['beside']['photometric']
    assert photometric['base'] > 0 and photometric['verdict']['runs'] == report['held_out']['verdict']['runs']
    anchors = report['held_out']['anchors']
    assert anchors['runs_judged'] >= 5 and min(anchors['per_run']) >= anchors['min_anchors'], anchors
    assert report['held_out']['adapted'] < report['held_out']['base']
    # written on the per-run comparison: enough runs, better on enough of them to pass the sign-flip test at 0.05
    verdict = report['held_out']['verdict']
    assert verdict['better'] and verdict['runs'] >= 5 and verdict['p_value'] <= verdict['significance'] == 0.05
    assert verdict['p_value'] >= 2.0 ** -verdict['runs'] and verdict['mean_change'] < 0
    assert [h['step'] for h in report['history']] == [1, 2, 3, 4]
    meta = read_metadata(out / 'weights.safetensors')
    ad = meta['adaptation']
    base = default_weights_path('lite')
    base_meta = read_metadata(base)
    assert ad['base_weights']['tensors_sha256'] == base_meta['tensors_sha256']
    import hashlib
    assert ad['base_weights']['sha256'] == hashlib.sha256(base.read_bytes()).hexdigest()
    assert ad['processing_size'] == [W, H] and meta['input_size'] == [W, H]
    assert ad['steps'] == 4 and meta['steps'] == base_meta['steps'] + 4
    assert ad['recording']['name'] == 'without_depth' and ad['recording']['frames'] == 90
    assert 'evidence' in ad['loss'] and ad['config']['evidence'] == 1.0 and ad['config']['readout'] == 'relative'
    assert ad['recording']['depth_read'] is False and 0 < ad['minutes'] < 5
    assert ad['held_out']['adapted'] == report['held_out']['adapted']
    assert ad['held_out']['p_value'] == verdict['p_value'] and ad['held_out']['runs'] == verdict['runs']
    assert ad['config']['poses'] == 'odometry' and report['poses'] == {'source': 'odometry'}
    # the weights moved, and they load for the size they were adapted at
    model, _ = load_checkpoint(out / 'weights.safetensors', preset='lite', processing_size=(W, H))
    shipped, _ = load_checkpoint(base, preset='lite')
    assert any(not torch.equal(a, b) for a, b in zip(model.state_dict().values(), shipped.state_dict().values()))


def test_depth_is_never_read_same_weights_with_and_without_depth_folder(adapted, adapted_with_depth_and_gt, folders,
                                                                         tmp_path):
    out, code = adapted
    assert code == tool.EXIT_WRITTEN
    with_depth, with_code, err = adapted_with_depth_and_gt
    assert with_code == tool.EXIT_WRITTEN, err
    a = read_metadata(out / 'weights.safetensors')
    b = read_metadata(with_depth / 'weights.safetensors')
    assert a['tensors_sha256'] == b['tensors_sha256']
    assert b['adaptation']['recording']['depth_read'] is False
    # depth read (--supervised, the trainer's loss) does change them: the comparison above can fail
    assert tool.main([str(folders[0]), '--out', str(tmp_path / 'sup'), *FAST, '--supervised', '--lr', '1e-4']) == \
        tool.EXIT_WRITTEN
    c = read_metadata(tmp_path / 'sup' / 'weights.safetensors')
    assert c['tensors_sha256'] != a['tensors_sha256']
    assert c['adaptation']['held_out']['score'] == 'nll' and c['adaptation']['recording']['depth_read'] is True


def test_poses_window_warps_with_the_keyframe_poses_the_node_used(folders, tmp_path):
    """--poses window: the recording runs once through the node's pipeline and refinement window, and the report
    says how many keyframes it refined and how far their steps' rotations moved (exact poses here: little)."""
    assert tool.main([str(folders[1]), '--out', str(tmp_path), *FAST, '--steps', '1', '--poses', 'window']) == \
        tool.EXIT_WRITTEN
    report = json.loads((tmp_path / 'report.json').read_text())
    poses = report['poses']
    assert poses['source'] == 'window' and report['config']['poses'] == 'window'
    assert poses['keyframes'] >= 10 and poses['refined'] >= poses['keyframes'] - 2
    assert poses['kept_as_recorded'] == poses['keyframes'] - poses['refined']
    assert 0.0 <= poses['step_rotation_change_deg']['median'] < 0.5
    assert sum(poses['refiner_windows'].values()) >= poses['refined']


def test_supervised_needs_depth(folders, tmp_path, capsys):
    code, err = _run(folders[1], tmp_path / 'out', '--supervised', capsys=capsys)
    assert code == tool.EXIT_BAD_INPUT and 'has no depth/' in err
    assert _files(tmp_path / 'out') == []
    code, err = _run(folders[0], tmp_path / 'out', '--depth-topic', '/depth', capsys=capsys)
    assert code == tool.EXIT_BAD_INPUT and '--depth-topic is read only with --supervised' in err


def test_supervised_on_a_bag_reads_its_depth_topic(folders, tmp_path, capsys):
    from dpv_sensor.data import rosbag_io as R
    bag = tmp_path / 'fleet.mcap'
    R.write_sequence_bag(bag, Sequence(folders[0]), depth_topic='/camera/aligned_depth/image', progress=False)
    code, err = _run(bag, tmp_path / 'none', '--supervised', capsys=capsys)
    assert code == tool.EXIT_BAD_INPUT and '--supervised on a bag needs --depth-topic' in err
    code = tool.main([str(bag), '--out', str(tmp_path / 'out'), *FAST, '--supervised', '--lr', '1e-4',
                      '--depth-topic', '/camera/aligned_depth/image'])
    assert code == tool.EXIT_WRITTEN
    ad = read_metadata(tmp_path / 'out' / 'weights.safetensors')['adaptation']
    rec = ad['recording']
    assert rec['kind'] == 'bag' and rec['depth_read'] is True and rec['frames'] == 90
    assert rec['depth_topic'] == '/camera/aligned_depth/image' and rec['topics']['image'] == '/image'
    assert ad['held_out']['score'] == 'nll'


def test_refuses_weights_that_score_worse(folders, tmp_path, capsys):
    # a learning rate far too high for the networks: the held-out score gets worse
    code, err = _run(folders[1], tmp_path / 'out', '--lr', '1.0', '--penalty', '0', capsys=capsys)
    assert code == tool.EXIT_REFUSED
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith('adapt: weights not written: the adapted weights scored no better')
    assert _files(tmp_path / 'out') == ['report.json', 'report.png']
    report = json.loads((tmp_path / 'out' / 'report.json').read_text())
    assert not report['written'] and report['held_out']['adapted'] > report['held_out']['base']
    assert report['refused'] == report['held_out']['verdict']['reason'] and not report['held_out']['verdict']['better']


def test_refuses_a_gain_too_few_held_out_runs_can_show(folders, tmp_path, capsys):
    """The last 20 % of the 90-frame recording hold fewer than 5 held-out runs: whatever they score, a sign-flip
    test at 0.05 cannot pass (its smallest p is 2^-runs), so the weights are refused, saying why; at significance 1
    the lower mean alone writes them. (Judged by photometry: the anchors' judge refuses such a recording before it
    trains, below.)"""
    code, err = _run(folders[1], tmp_path / 'out', '--holdout-layout', 'end', '--holdout', '0.2', '--judge',
                     'photometric', capsys=capsys)
    report = json.loads((tmp_path / 'out' / 'report.json').read_text())
    verdict = report['held_out']['verdict']
    assert verdict['runs'] < 5 and verdict['p_value'] >= 2.0 ** -verdict['runs'] > 0.05, verdict
    assert verdict['mean_change'] < 0, verdict                  # the premise: a lower mean (the run is seeded)
    assert code == tool.EXIT_REFUSED and 'runs cannot tell from noise' in err and not report['written'], err
    mean_only = _run(folders[1], tmp_path / 'mean', '--holdout-layout', 'end', '--holdout', '0.2',
                     '--significance', '1', '--judge', 'photometric')
    assert mean_only[0] == tool.EXIT_WRITTEN
    # the anchors' judge: fewer judged runs than a sign-flip test at 0.05 needs: refused at once, nothing trained
    code, err = _run(folders[1], tmp_path / 'anchors', '--holdout-layout', 'end', '--holdout', '0.2', capsys=capsys)
    report = json.loads((tmp_path / 'anchors' / 'report.json').read_text())
    assert code == tool.EXIT_REFUSED and 'too few metric anchors to judge the depth' in err, err
    assert '5 are needed at significance 0.05' in err and report['steps'] == 0 and not report['written'], err


def test_no_step_within_minutes_writes_no_weights(folders, tmp_path, capsys):
    code, err = _run(folders[1], tmp_path / 'out', '--minutes', '0.001', capsys=capsys)
    assert code == tool.EXIT_REFUSED and 'no adaptation step fitted in --minutes 0.001' in err
    assert 'weights.safetensors' not in _files(tmp_path / 'out')


def test_interrupted_run_leaves_no_weights(folders, tmp_path, monkeypatch, capsys):
    from dpv_sensor.training.adapt_loop import Adapter
    calls = []
    real = Adapter.loss

    def interrupted(self, batch):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(self, batch)
    monkeypatch.setattr(Adapter, 'loss', interrupted)
    code, err = _run(folders[1], tmp_path / 'out', capsys=capsys)
    assert code == tool.EXIT_INTERRUPTED and 'interrupted; no weights written' in err
    assert len(calls) == 3 and _files(tmp_path / 'out') == []


def test_interrupted_while_writing_leaves_no_half_written_weights(folders, tmp_path, monkeypatch, capsys):
    import dpv_sensor.core.nets.checkpoint as C
    real_replace = os.replace

    def replace(src, dst):
        if str(dst).endswith('weights.safetensors'):
            assert os.path.getsize(src) > 100_000          # the temp file was complete; the rename never happens
            raise KeyboardInterrupt
        return real_replace(src, dst)
    monkeypatch.setattr(C.os, 'replace', replace)
    code, _ = _run(folders[1], tmp_path / 'out', capsys=capsys)
    assert code == tool.EXIT_INTERRUPTED
    assert _files(tmp_path / 'out') == []                  # neither the weights nor their temp file


def test_adapted_weights_refused_at_another_processing_size(adapted):
    from dpv_sensor.stream.estimator import Estimator, EstimatorConfig
    out, code = adapted
    assert code == tool.EXIT_WRITTEN
    path = out / 'weights.safetensors'
    with pytest.raises(CheckpointError, match=f'adapted to a recording at processing size {W}x{H}, but the nets '
                                              'run at 320x256'):
        load_checkpoint(path, preset='lite', processing_size=(320, 256))
    with pytest.raises(CheckpointError, match=f'{W}x{H}.*{W}x{H + 4}'):
        load_checkpoint(path, preset='lite', processing_size=(W, H + 4))
    est = Estimator(EstimatorConfig(weights=str(path), processing_width=W, processing_height=H,
                                    measurement='network', pose_refinement='off'))
    assert est.status.measurement == 'network' and est.status.weights == str(path)
    with pytest.raises(CheckpointError, match='adapted to a recording'):
        Estimator(EstimatorConfig(weights=str(path), measurement='network', pose_refinement='off'))
    # measurement auto: the node's fallback to the classical model, with the reason in its status
    st = Estimator(EstimatorConfig(weights=str(path), measurement='auto', pose_refinement='off')).status
    assert st.measurement == 'classical' and f'processing size {W}x{H}' in st.measurement_reason


def test_adapting_on_the_first_half_lowers_the_second_half_abs_rel(tmp_path):
    """A world the shipped weights never saw - a room 2-2.8 m across: adapting on the first 80 frames (no depth)
    lowers abs_rel on the next 60, through the node's pipeline. 6 steps (the tool's warm-up) already move it well
    past the margins below: 50 steps, which took two minutes, gave a smaller gain."""
    from dpv_sensor.evaluation.offline import EvalOptions, evaluate_sequence
    seq = render_sequence(65, 140, width=W, height=H, **SMALL_ROOM)
    first = write_sequence(tmp_path / 'first', seq.subset(range(80)), lossless=True, write_depth=False)
    out = tmp_path / 'out'
    code = tool.main([str(first), '--out', str(out), '--width', str(W), '--height', str(H), '--threads', '1',
                      '--quiet', '--holdout', '0.4', '--steps', '6'])
    assert code == tool.EXIT_WRITTEN
    second = Sequence.from_arrays([seq.image(i) for i in range(80, 140)], [seq.depth(i) for i in range(80, 140)],
                                  seq.poses[80:], seq.K, seq.stamps[80:])
    scores = {}
    for name, path in (('shipped', default_weights_path('lite')), ('adapted', out / 'weights.safetensors')):
        s = evaluate_sequence(second, {'weights': str(path), 'processing_width': W, 'processing_height': H,
                                       'pose_refinement': 'off'},
                              options=EvalOptions(progress=False, consumer_odometry=False))
        scores[name] = s['metric']['frame_mean']['abs_rel']
    # measured: 0.110 -> 0.093 after 6 steps (on the 80 frames after these, 0.104 -> 0.089 after 6 steps, 0.086
    # after 12, 0.094 after 50; 0.089 after 50 without the tie to what the base network is sure of: it is sure of
    # some of this room's depth and the default keeps it). Weights that do not move or that move the wrong way fail
    # both margins.
    assert scores['adapted'] < scores['shipped'] - 0.007 and scores['adapted'] < 0.94 * scores['shipped'], scores


def test_gt_folder_adds_the_held_out_metrics_before_and_after(adapted_with_depth_and_gt, folders, tmp_path, capsys):
    out, code, err = adapted_with_depth_and_gt
    assert code == tool.EXIT_WRITTEN, err
    report = json.loads((out / 'report.json').read_text())
    gt, held = report['ground_truth'], report['held_out']['keyframes']['held_out_frames']
    # scored on the held-out frames: a block of keyframes inside the recording (not its end), as the tool held out
    assert gt['frames'] == held and len(held) == 1 and 0 < held[0][0] < held[0][1] < 89, held
    for name in ('base', 'adapted'):
        assert 0 < gt[name]['abs_rel'] < 1 and 0 < gt[name]['delta1'] <= 1 and 0 <= gt[name]['ece'] <= 1
        assert gt[name]['keyframes'] >= 3
    assert gt['base']['abs_rel'] != gt['adapted']['abs_rel']
    meta = read_metadata(out / 'weights.safetensors')
    assert meta['adaptation']['ground_truth']['adapted']['abs_rel'] == gt['adapted']['abs_rel']
    # a GT folder that does not match the recording is refused before any work
    short = tmp_path / 'short'
    write_sequence(short, Sequence(folders[0]).subset(range(40)), lossless=True)
    code, err = _run(folders[1], tmp_path / 'out2', '--gt', str(short), capsys=capsys)
    assert code == tool.EXIT_BAD_INPUT and 'has 40 frames, the recording 90' in err
    assert _files(tmp_path / 'out2') == []


def test_held_out_split_by_hand():
    from dpv_sensor.training.adapt_loop import split_keyframes
    from dpv_sensor.training.dataset import WindowLayout
    layout = WindowLayout(steps=2, window=5)                  # M = 6 keyframes a run, references at slots 2 and 3
    # a long recording: the last 30 % (6 keyframes) held out; each of them that can be a reference is one: three runs,
    # the first two borrowing their first sources (60, 65) from the training part
    split, train, held, runs = split_keyframes(list(range(0, 100, 5)), 100, 0.3, layout)
    assert split == 70 and held == [70, 75, 80, 85, 90, 95] and len(train) == 14
    assert runs == [[60, 65, 70, 75, 80, 85], [65, 70, 75, 80, 85, 90], held]
    assert all(run[2] in held and run[3] in held for run in runs)        # the references (slots 2, 3): held out
    # a 50-frame fragment (11 keyframes): 20 % would hold 2, so the last 4 are held out and the one run borrows its
    # first two sources from the training part; its references (34, 38) and later keyframes are all held out
    kfs = [0, 5, 9, 14, 19, 24, 29, 34, 38, 42, 47]
    split, train, held, runs = split_keyframes(kfs, 50, 0.2, layout)
    assert split == 34 and train == kfs[:7] and held == [34, 38, 42, 47]
    assert runs == [[24, 29, 34, 38, 42, 47]]
    # 6 keyframes cannot be split into 6 to adapt on and 4 to score
    with pytest.raises(ValueError, match='training part has 5 keyframes .*6 are needed \\(10 in all\\)'):
        split_keyframes(kfs[:6], 25, 0.2, layout)


def test_spread_held_out_blocks_by_hand():
    from dpv_sensor.training.adapt_loop import spread_keyframes
    from dpv_sensor.training.dataset import WindowLayout
    layout = WindowLayout(steps=2, window=5)                  # M = 6, references at slots 2 and 3, 2 per run
    kfs = list(range(0, 400, 5))                              # 80 keyframes
    # 20 % in 4 blocks: 4 keyframes each, centred at 1/8, 3/8, 5/8, 7/8 of the keyframes (indices 8, 28, 48, 68)
    segments, held, runs = spread_keyframes(kfs, 0.2, layout, 4)
    assert held == [kfs[i] for st in (8, 28, 48, 68) for i in range(st, st + 4)]
    assert segments == [kfs[0:8], kfs[12:28], kfs[32:48], kfs[52:68], kfs[72:80]]
    assert not set(held) & {k for sg in segments for k in sg}   # nothing held out is trained on
    # every run's two references lie in one block; three runs a block, the sources around them from the segments
    assert len(runs) == 12 and runs[0] == kfs[6:12] and runs[2] == kfs[8:14]
    assert all(run[2] in held and run[3] in held for run in runs)
    # 20 keyframes: two blocks would leave a middle segment of fewer than 6, so one block in the middle
    segments, held, runs = spread_keyframes(kfs[:20], 0.2, layout, 4)
    assert held == kfs[8:12] and segments == [kfs[0:8], kfs[12:20]] and len(runs) == 3
    # (two blocks of two would leave 4 keyframes before the first and after the last: too few to train on)
    with pytest.raises(ValueError, match='too short for a spread held-out part: 9 keyframes'):
        spread_keyframes(kfs[:9], 0.2, layout, 4)


def test_spread_adapter_trains_only_on_its_segments(folders):
    from dpv_sensor.training.adapt_loop import AdaptConfig, Adapter
    model, _ = load_checkpoint(default_weights_path('lite'), preset='lite')
    seq = Sequence(folders[0], depth=False)
    cfg = AdaptConfig(width=96, height=64, holdout_layout='spread', holdout_blocks=2, max_steps=1)
    ad = Adapter(cfg, model, seq)
    held = set(ad.held_kf)
    assert held and ad.split is None and not held & set(ad.train_kf)
    assert all(not held & set(run) for run in ad.train_runs)
    assert all(run[2] in held and run[3] in held for run in ad.held_runs)
    ranges = ad.held_frames()
    assert len(ranges) >= 1 and all(a <= b for a, b in ranges)
    assert {k for k in held} <= {f for a, b in ranges for f in range(a, b + 1)}
    # a recording too short for blocks is refused, and the error says how to adapt it anyway; 'end' holds out its
    # last frames
    with pytest.raises(ValueError, match="too short for a spread held-out part.*holdout_layout 'end'"):
        Adapter(cfg, model, seq.subset(range(40)))
    short = Adapter(dataclasses.replace(cfg, holdout_layout='end'), model, seq.subset(range(40)))
    assert short.holdout_layout == 'end' and short.split is not None and short.held_runs


def test_confident_tie_weights_the_kl_by_the_base_networks_confidence(folders):
    """``distill_pixels='confident'``: the KL to the base DPV counts only where the base network is sure, so it is
    at most the plain KL, and nothing where no base confidence reaches the threshold."""
    import numpy as np

    from dpv_sensor.core import dpv as dpvops
    from dpv_sensor.training.adapt_loop import AdaptConfig, Adapter
    from dpv_sensor.training.self_supervised import confidence_tie_weight
    seq = Sequence(folders[0], depth=False).resized(96, 64).materialize()
    with pytest.raises(ValueError, match='distill_pixels'):
        AdaptConfig(distill_pixels='textured').check()
    with pytest.raises(ValueError, match='distill_threshold'):
        AdaptConfig(distill_pixels='confident', distill_threshold=1.0).check()
    kl = {}
    for pixels, threshold in (('all', 0.5), ('confident', 0.5), ('confident', 0.999)):
        model, _ = load_checkpoint(default_weights_path('lite'), preset='lite')
        cfg = AdaptConfig(width=96, height=64, holdout_layout='spread', holdout_blocks=2, unroll=1, distill=1.0,
                          distill_pixels=pixels, distill_threshold=threshold, photometric=0.0, penalty=0.0)
        ad = Adapter(cfg, model, seq)
        with torch.no_grad():                     # move the adapted network away from the base
            for p in model.parameters():
                p.add_(0.02 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
        torch.manual_seed(0)
        batch = ad.training_batch(np.random.default_rng(0))
        kl[(pixels, threshold)] = ad.loss(batch)[1]['distill']
        if pixels == 'confident':                 # the weight is the base's published confidence through the map
            noise = torch.randn(1, ad.depths_d.numel(), 4, 5, generator=torch.Generator().manual_seed(1))
            lp = torch.log_softmax(noise, 1)
            d = dpvops.depth_estimate(lp, ad.depths_d, cfg.readout)
            conf = dpvops.published_confidence(lp, ad.depths_d, d)
            assert torch.allclose(ad._tie_weight(lp), confidence_tie_weight(conf, threshold))
    assert kl[('all', 0.5)] > 0
    assert 0 < kl[('confident', 0.5)] < kl[('all', 0.5)]
    assert kl[('confident', 0.999)] < 0.01 * kl[('all', 0.5)]
