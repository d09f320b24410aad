"""Weights written by the adapt tool through the node process: `-p weights:=DIR/weights.safetensors` loads them
(diagnostics name the file, depth is published), and a node whose processing size differs from the one they were
adapted at refuses them at start with one message saying which sizes (exit 2 with measurement:=network)."""
import re

import pytest

import shared_builds
from ros_helpers import forked_node_starts, wait_for
from stream_driver import FAST_PARAMS, H, W, StreamDriver, params_args

from dpv_sensor.tools import adapt as tool

FRAMES = 10


@pytest.fixture(scope='module')
def adapted_weights(tmp_path_factory):
    """Weights adapted (4 steps) to a rendered 90-frame recording at the stream driver's size (the adapt tool's
    tests check them)."""
    rec = shared_builds.adapt_recording(tmp_path_factory)
    assert rec.code == tool.EXIT_WRITTEN and (shared_builds.W, shared_builds.H) == (W, H)
    return rec.adapted / 'weights.safetensors'


def test_the_node_runs_the_adapted_weights(adapted_weights):
    params = {**FAST_PARAMS, 'measurement': 'network', 'weights': str(adapted_weights)}
    drv = StreamDriver(params_args(params), frames=FRAMES, name='adapted_weights')
    try:
        drv.wait_ready()
        diag = dict(drv.outputs.diagnostics)
        assert diag['measurement_model'] == 'network', diag
        assert f'network weights loaded from {adapted_weights}' in diag['measurement_reason'], diag
        for i in range(FRAMES):
            drv.send(i, drv.stamp_ns(i))
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics
        assert wait_for(lambda: any(r.depth is not None for r in drv.outputs.by_stamp.values()), timeout=30.0,
                        spin=drv.spin), drv.outputs.diagnostics
    finally:
        log = drv.stop()
    assert drv.code == 0 and 'Traceback' not in log, log


def test_the_node_refuses_weights_adapted_at_another_processing_size(adapted_weights):
    params = {**FAST_PARAMS, 'measurement': 'network', 'weights': str(adapted_weights),
              'processing_width': 2 * W, 'processing_height': 2 * H}
    [(code, out)] = forked_node_starts([('module', params_args(params))])
    assert code == 2, out
    assert out.count('cannot build the estimator') == 1, out
    assert (f'adapted to a recording at processing size {W}x{H}, but the nets run at {2 * W}x{2 * H}: set '
            f'processing_width:={W} processing_height:={H}') in out, out
    assert 'Traceback' not in out and not re.search(r'\bready\b', out), out
