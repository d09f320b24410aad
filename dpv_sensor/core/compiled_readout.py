"""The full-size readout (depth and published confidence of a DPV) compiled with ``torch.compile`` (torch only).

Reading a depth and its confidence out of R-Net's full-size DPV (32 planes at 320x256) is a chain of some fifteen
element-wise passes over 2.6 M values (``dpv.depth_estimate`` then ``dpv.published_confidence``); eager PyTorch runs
each as its own loop over memory. ``torch.compile`` fuses them into a few C++ loops: about 2.5x faster in the
node's keyframe on a 2-core CPU, within 1e-5 m of the eager depth (float rounding only; docs/estimator.md).

What is compiled is the default readout only (``depth_readout`` relative, ``confidence`` ratio, ``confidence_ratio``
1.25), once per process, with dynamic shapes (any size, any number of planes). The first call compiles it (about
20 s; PyTorch keeps the result in its on-disk cache, so a later process loads it in under a second);
``python -m dpv_sensor.core.compiled_readout`` fills that cache ahead (``make test`` and ``make demo`` do). Other
readouts, autograd and non-CPU tensors run eagerly. Where compiling fails (no C++ compiler, an unsupported PyTorch)
the failure is reported once through ``note`` and the eager functions run from then on: the readout never fails
because of the compiler.
"""
from __future__ import annotations

import logging
import time
from typing import Callable, Optional, Tuple

import torch

from dpv_sensor import params as _params
from dpv_sensor.core import dpv as dpv_ops

__all__ = ['CompiledReadout', 'COMPILED', 'warm']

#: the readout settings that are compiled (the node's defaults): (depth_readout after 'auto', confidence, ratio)
COMPILED = ('relative', _params.default('confidence'), float(_params.default('confidence_ratio')))


def _default_readout(logp_bdhw: torch.Tensor, depths_d: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    depth = dpv_ops.depth_estimate(logp_bdhw, depths_d, COMPILED[0])
    return depth, dpv_ops.published_confidence(logp_bdhw, depths_d, depth, COMPILED[1], COMPILED[2])


_compiled_fns = {}     # backend -> the compiled _default_readout (one per process)


def _compiled(backend) -> Callable:
    if backend not in _compiled_fns:
        # PyTorch warns on the first compile that GPU flop counting needs triton: nothing to do with a CPU readout
        logging.getLogger('torch.utils.flop_counter').setLevel(logging.ERROR)
        _compiled_fns[backend] = torch.compile(_default_readout, dynamic=True, backend=backend)
    return _compiled_fns[backend]


class CompiledReadout:
    """``readout(logp_bdhw) -> (depth_bhw, confidence_bhw)`` for one estimator's planes and settings: compiled
    where the settings are the default ones (module docstring), else eager. ``compiled`` says whether the compiled
    version runs (None: not tried yet); ``failure`` why it does not."""

    def __init__(self, depths_d: torch.Tensor, readout: str, confidence: str, ratio: float,
                 note: Optional[Callable[[str], None]] = None, backend='inductor'):
        self.depths_d = depths_d
        self.readout = readout
        self.confidence = confidence
        self.ratio = float(ratio)
        self.note = note
        self.backend = backend
        self.applies = (readout, confidence, self.ratio) == COMPILED
        self.compiled: Optional[bool] = None if self.applies else False
        self.failure: Optional[str] = None if self.applies else 'not the default readout'

    def eager(self, logp_bdhw: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        depth = dpv_ops.depth_estimate(logp_bdhw, self.depths_d, self.readout)
        conf = dpv_ops.published_confidence(logp_bdhw, self.depths_d, depth, self.confidence, self.ratio)
        return depth, conf

    def __call__(self, logp_bdhw: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        if self.compiled is False or logp_bdhw.requires_grad or logp_bdhw.device.type != 'cpu':
            return self.eager(logp_bdhw)
        try:
            out = _compiled(self.backend)(logp_bdhw, self.depths_d.to(logp_bdhw.dtype))
        except Exception as exc:  # the compiler is optional: any failure means the eager readout
            self.compiled = False
            cause = getattr(exc, 'inner_exception', None) or exc.__cause__ or exc   # the compiler's own error
            lines = str(cause).strip().splitlines()
            self.failure = f'{type(cause).__name__}: {lines[0] if lines else ""}'.strip()
            if self.note is not None:
                self.note(f'compile_readout: torch.compile failed ({self.failure}); the readout runs eagerly')
            return self.eager(logp_bdhw)
        self.compiled = True
        return out


def warm() -> Tuple[Optional[bool], float, Optional[str]]:
    """Compile the default readout (filling PyTorch's on-disk cache); (compiled, seconds, failure)."""
    t = time.perf_counter()
    ro = CompiledReadout(dpv_ops.depth_planes(0.3, 8.0, 32), *COMPILED)
    with torch.no_grad():
        ro(torch.log_softmax(torch.zeros(1, 32, 16, 20), 1))
    return ro.compiled, time.perf_counter() - t, ro.failure


if __name__ == '__main__':
    ok, seconds, why = warm()
    print(f'compiled readout: {"ready" if ok else "unavailable (" + str(why) + "), the eager readout runs"} '
          f'({seconds:.1f} s)')
