"""The compiled full-size readout: the eager readout's values (float rounding only), and the eager readout wherever
it cannot or should not compile."""
from __future__ import annotations

import torch

from dpv_sensor.core import dpv as dpv_ops
from dpv_sensor.core.compiled_readout import CompiledReadout

D = 32


def _dpv(seed: int, h: int = 12, w: int = 16) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.log_softmax(3.0 * torch.randn(1, D, h, w, generator=g), 1)


def _planes():
    return dpv_ops.depth_planes(0.3, 8.0, D)


def test_the_compiled_readout_is_the_eager_one_to_float_rounding():
    d = _planes()
    ro = CompiledReadout(d, 'relative', 'ratio', 1.25)
    logp = _dpv(0)
    depth, conf = ro(logp)
    assert ro.compiled is True, ro.failure
    want_depth = dpv_ops.depth_estimate(logp, d, 'relative')
    want_conf = dpv_ops.published_confidence(logp, d, want_depth, 'ratio', 1.25)
    assert torch.allclose(depth, want_depth, rtol=1e-4, atol=0) and torch.allclose(conf, want_conf, atol=1e-4)
    # a sharp DPV: its peak's depth, and nearly all of the mass within the x1.25 band
    sharp = torch.full((1, D, 2, 3), -30.0)
    sharp[:, 20] = 0.0
    depth2, conf2 = ro(torch.log_softmax(sharp, 1))
    assert torch.allclose(depth2, torch.full_like(depth2, float(d[20])), rtol=1e-4)
    assert bool((conf2 > 0.99).all())


def test_any_size_is_compiled_once_and_other_settings_and_autograd_run_eagerly():
    d = _planes()
    ro = CompiledReadout(d, 'relative', 'ratio', 1.25)
    for h, w in ((12, 16), (7, 9)):                                  # dynamic shapes: one compile serves both
        logp = _dpv(h, h, w)
        depth, conf = ro(logp)
        want_depth, want_conf = ro.eager(logp)
        assert ro.compiled is True
        assert torch.allclose(depth, want_depth, rtol=1e-4, atol=0) and torch.allclose(conf, want_conf, atol=1e-4)
    for readout, confidence, ratio in (('median', 'ratio', 1.25), ('relative', 'plane', 1.25),
                                       ('relative', 'ratio', 1.1)):
        other = CompiledReadout(d, readout, confidence, ratio)
        logp = _dpv(2)
        assert torch.equal(other(logp)[1], other.eager(logp)[1]) and other.compiled is False   # eager, bit for bit
    grad_in = _dpv(3).requires_grad_(True)
    depth, _ = ro(grad_in)
    assert depth.requires_grad
    depth.sum().backward()
    assert grad_in.grad is not None and torch.isfinite(grad_in.grad).all()


def test_a_compiler_that_fails_is_reported_once_and_the_readout_runs_eagerly():
    def broken_backend(gm, example_inputs):
        raise RuntimeError('no C++ compiler found')
    notes = []
    d = _planes()
    ro = CompiledReadout(d, 'relative', 'ratio', 1.25, note=notes.append, backend=broken_backend)
    for seed in (4, 5):
        logp = _dpv(seed)
        depth, conf = ro(logp)
        want_depth, want_conf = ro.eager(logp)
        assert torch.equal(depth, want_depth) and torch.equal(conf, want_conf)
    assert ro.compiled is False and 'no C++ compiler found' in ro.failure
    assert len(notes) == 1 and 'compile_readout' in notes[0] and 'eagerly' in notes[0]
