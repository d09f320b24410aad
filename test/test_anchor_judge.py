"""The adaptation's depth judge (dpv_sensor.training.anchor_judge): its score and loss by hand, anchors of rendered
keyframes against the true depth, a group's anchors made from that group's images only, a camera turning in place
giving none, and the judge's rules (runs needed, the photometric veto) by hand."""
import math

import numpy as np
import pytest
import torch

from dpv_sensor.core.anchors import Anchors, sample_depth
from dpv_sensor.data.synthetic import SyntheticScene, render_sequence
from dpv_sensor.data.sequence import Sequence
from dpv_sensor.training.adapt_loop import select_keyframes
from dpv_sensor.training.anchor_judge import AnchorScore, JudgeConfig, anchor_loss, frame_anchors
from dpv_sensor.training.heldout_decision import runs_needed, veto
from shared_builds import SMALL_ROOM

W, H = 160, 128


def _anchors(uv, depth, sigma, K=np.eye(3)):
    n = len(depth)
    return Anchors(np.asarray(uv, np.float64), np.asarray(depth, np.float64), np.asarray(sigma, np.float64),
                   np.zeros(n), np.zeros(n, np.int64), K)


def test_score_by_hand():
    depth = np.full((10, 10), 2.0)
    a = _anchors([[2, 3], [5, 5], [7.5, 1.5]], [2.0, 2.0, 2.0], [0.05, 0.1, 0.2])
    cfg = JudgeConfig(min_anchors=3)
    exact = AnchorScore(cfg)
    exact.add(depth, a)
    assert exact.value == 0.0 and exact.count == 3
    # every pixel 1.2 x too far: each |log ratio| is log 1.2, whatever the weights
    far = AnchorScore(cfg)
    far.add(depth * 1.2, a)
    assert far.value == pytest.approx(math.log(1.2), abs=1e-12)
    # one anchor off by log 1.5, weights 1 / (sigma^2 + 0.1^2)
    a2 = _anchors([[2, 3], [5, 5], [7.5, 1.5]], [2.0, 3.0, 2.0], [0.05, 0.1, 0.2])
    one = AnchorScore(cfg)
    one.add(depth, a2)
    w = 1.0 / (np.array([0.05, 0.1, 0.2]) ** 2 + 0.1 ** 2)
    assert one.value == pytest.approx(w[1] * math.log(1.5) / w.sum(), rel=1e-12)
    # too few anchors: the run is not judged
    few = AnchorScore(JudgeConfig(min_anchors=4))
    few.add(depth, a)
    assert math.isnan(few.value)


def test_anchor_loss_is_zero_at_the_anchors_depth_and_its_gradient_checks():
    a = _anchors([[1.5, 1.25], [3.0, 1.0], [0.5, 3.5]], [2.0, 1.5, 3.0], [0.05, 0.02, 0.1])
    d = torch.full((1, 5, 6), 2.0, dtype=torch.float64)
    d[0, :, 3] = 1.5
    d[0, 3:, :2] = 3.0
    # anchors 1 and 2 sit on pixels holding their depth; anchor 0 between 2.0 values
    assert float(anchor_loss(d, [a])) == pytest.approx(0.0, abs=1e-24)
    rng = np.random.default_rng(0)
    x = torch.tensor(rng.uniform(1.0, 3.0, (1, 5, 6)), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: anchor_loss(t, [a]), (x,))
    assert anchor_loss(d, [None]) is None and anchor_loss(d, [Anchors.empty()]) is None


class _Watched:
    """A sequence that records which frames' images were read."""

    def __init__(self, seq):
        self.seq, self.read = seq, set()
        self.K = seq.K

    def __len__(self):
        return len(self.seq)

    def image(self, i):
        self.read.add(int(i))
        return self.seq.image(i)

    def pose(self, i):
        return self.seq.pose(i)


@pytest.fixture(scope='module')
def rendered():
    # the adapt tool's default processing size (at 160x128 the same anchors sit 3 % near in the median)
    return render_sequence(7, 90, width=320, height=256, lazy=True)


def test_rendered_anchors_hold_the_true_depth_and_read_only_the_frames_allowed(rendered):
    kfs = select_keyframes([rendered.pose(i) for i in range(len(rendered))])
    refs = kfs[4:12]
    forbidden = set(kfs[:4]) | set(kfs[12:]) | set(range(60, 90))
    watched = _Watched(rendered)
    anchors = frame_anchors(watched, refs, lambda f: f not in forbidden)
    assert watched.read - set(refs) and not watched.read & forbidden, sorted(watched.read)
    assert sorted(anchors) == refs
    counts = [len(a) for a in anchors.values()]
    assert sum(counts) >= 100, counts
    err = np.concatenate([np.log(a.depth_n) - np.log(sample_depth(rendered.depth(k), a.uv_n2))
                          for k, a in anchors.items() if len(a)])
    err = err[np.isfinite(err)]
    # measured: median |log error| 0.020, 90th percentile 0.072 (1030 anchors)
    assert np.median(np.abs(err)) < 0.03 and np.percentile(np.abs(err), 90) < 0.12, np.percentile(np.abs(err),
                                                                                                    [50, 90])


class _InPlace:
    """A camera turning about its own centre (yaw, 20 deg/s), where the rendered walk starts."""

    def __init__(self, T0):
        self.T0 = T0

    def pose(self, t):
        a = math.radians(20.0) * t
        R = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        T = self.T0.copy()
        T[:3, :3] = self.T0[:3, :3] @ R
        return T


def test_a_camera_turning_in_place_gives_no_anchors():
    scene = SyntheticScene(7, W, H)
    scene.trajectory = _InPlace(scene.trajectory.pose(0.0))
    n = 60
    seq = Sequence.from_arrays([scene.render_frame(i)['image'] for i in range(n)],
                               [scene.render_frame(i)['depth'] for i in range(n)],
                               np.stack([scene.pose(i) for i in range(n)]), scene.K,
                               np.array([scene.stamp(i) for i in range(n)]))
    kfs = select_keyframes([seq.pose(i) for i in range(n)])
    anchors = frame_anchors(seq, kfs, lambda f: True)
    assert len(kfs) >= 5 and sum(len(a) for a in anchors.values()) == 0, [len(a) for a in anchors.values()]


def test_runs_needed_and_the_photometric_veto_by_hand():
    assert runs_needed(0.05) == 5 and runs_needed(0.5) == 1 and runs_needed(0.03125) == 5 and runs_needed(1) == 1
    base = [1.0] * 6
    # photometry worse on every run by 1 %: a sign-flip p of 2^-6 <= 0.05, vetoed
    why = veto(base, [1.01] * 6, 0.05, 'photometric')
    assert why is not None and 'worse by 1.00 %' in why and '6 of 6 runs worse' in why, why
    # better, or worse on too few runs to tell: no veto
    assert veto(base, [0.99] * 6, 0.05, 'photometric') is None
    assert veto(base, [1.01, 0.99, 1.01, 0.99, 1.01, 0.99], 0.05, 'photometric') is None


def test_held_out_anchors_never_enter_training_and_the_sparse_loss_trains(monkeypatch):
    """An Adapter with the sparse loss: the held-out keyframes' anchors are made from frames never trained on (no
    training keyframe), the training keyframes' from frames outside the held-out parts; a training batch's loss has
    the anchor term, finite, with a gradient on the networks."""
    import dpv_sensor.training.adapt_loop as AL
    from dpv_sensor.core.nets.checkpoint import default_weights_path, load_checkpoint
    seq = render_sequence(65, 90, width=W, height=H, **SMALL_ROOM)
    reads = []
    real = AL.frame_anchors

    def watched(sequence, refs, allowed, config):
        w = _Watched(sequence)
        out = real(w, refs, allowed, config)
        reads.append((list(refs), w.read))
        return out
    monkeypatch.setattr(AL, 'frame_anchors', watched)
    model, _ = load_checkpoint(default_weights_path('lite'))
    torch.manual_seed(0)
    ad = AL.Adapter(AL.AdaptConfig(width=W, height=H, holdout=0.35, unroll=1, anchor_loss=0.1, distill=0), model, seq)
    held, train = set(ad.held_kf), set(ad.train_kf)
    held_frames = {f for a, b in ad.held_frames() for f in range(a, b + 1)}
    assert set(ad.held_anchors) == held and set(ad.train_anchors) == train and not held & train
    (held_refs, held_read), (train_refs, train_read) = reads
    # held-out anchors: no training keyframe read; training anchors: nothing of the held-out parts
    assert set(held_refs) == held and held_read - held and not held_read & train, sorted(held_read)
    assert set(train_refs) == train and not train_read & held_frames, sorted(train_read & held_frames)
    assert sum(len(a) for a in ad.train_anchors.values()) > 100
    rng = np.random.default_rng(0)
    for _ in range(20):          # the room's far end gives no anchors (the camera turns there): a batch that has
        loss, stats = ad.loss(ad.training_batch(rng))
        ref = ad._batch_ids[0][int(ad.cfg.layout().indices()[0][0])]
        assert ('anchor' in stats) == (len(ad.train_anchors[ref]) > 0), (ref, stats)
        if 'anchor' in stats:
            break
    assert math.isfinite(stats['anchor']) and stats['anchor'] > 0, stats
    loss.backward()
    assert any(p.grad is not None and float(p.grad.abs().sum()) > 0 for p in model.parameters())
