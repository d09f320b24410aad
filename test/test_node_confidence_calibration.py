"""The confidence_calibration parameter through the node process: with a calibration file the node publishes the
same depth images, byte for byte, and the map applied to the confidence it publishes without one; /diagnostics
names the file. A malformed, mismatched or oversized file stops the node at start: exit 2, one message naming the
parameter and what is wrong, no traceback."""
import json
import re

import numpy as np
import pytest

from ros_helpers import forked_node_starts, wait_for
from stream_driver import FAST_PARAMS, H, W, StreamDriver, params_args
from dpv_sensor.core import confidence_calibration as CC
from dpv_sensor.ros import msgs as M

REMAPS = {'image': '/cam/image', 'camera_info': '/cam/camera_info', 'odom': '/odom'}
FRAMES = 12
# what the node at FAST_PARAMS estimates with: the classical model, 32 planes over the default 0.3-8 m
FAST_SIGNATURE = CC.signature('classical', None, (W, H), (0.3, 8.0), FAST_PARAMS['num_planes'], 'ratio 1.25')


def _run(name: str, params: dict) -> tuple[dict, dict, str]:
    """Send FRAMES frames one at a time to a node at FAST_PARAMS + params; ({stamp: (depth, confidence)},
    diagnostics, log)."""
    drv = StreamDriver(params_args({**FAST_PARAMS, **params}, REMAPS), topics=REMAPS, frames=FRAMES, name=name)
    try:
        drv.wait_ready()
        for i in range(FRAMES):
            drv.send(i, drv.stamp_ns(i))
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics

        def complete():
            return [r for r in drv.outputs.by_stamp.values() if r.depth is not None and r.confidence is not None]
        # every output the node counted has arrived here
        assert wait_for(lambda: drv.diag('outputs_published', -1) == len(complete()), timeout=30.0, spin=drv.spin), \
            drv.outputs.diagnostics
        diagnostics = dict(drv.outputs.diagnostics)
        out = {r.stamp_ns: (r.depth, r.confidence) for r in complete()}
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    assert 'Traceback' not in log, log
    return out, diagnostics, log


def test_the_node_publishes_the_calibrated_confidence_and_the_same_depth(tmp_path):
    cal = CC.ConfidenceCalibration((0.0, 0.3, 1.0), (0.1, 0.6, 0.95), FAST_SIGNATURE, {'source': 'by hand'})
    path = CC.save(cal, tmp_path / 'cal.json')
    raw, diag_raw, _ = _run('calibration_off', {})
    calibrated, diag_cal, log = _run('calibration_on', {'confidence_calibration': str(path)})
    assert diag_raw['confidence_calibration'] == 'off' and diag_cal['confidence_calibration'] == 'cal.json'
    assert f'confidence calibration {path}: 3 knots, fitted on by hand' in log
    assert len(raw) >= 4 and set(calibrated) == set(raw)
    for stamp, (depth, conf) in calibrated.items():
        raw_depth, raw_conf = raw[stamp]
        assert bytes(depth.data) == bytes(raw_depth.data)                   # the depth image, byte for byte
        d, c, c_raw = M.image_to_float(depth), M.image_to_float(conf), M.image_to_float(raw_conf)
        est = np.isfinite(d)
        assert est.mean() > 0.3
        np.testing.assert_allclose(c[est], cal.apply(c_raw[est]), atol=1e-6)
        assert (c[~est] == 0).all()


BAD_KNOTS = {'format': CC.FORMAT, 'version': 1, 'estimator': FAST_SIGNATURE,
             'knots': {'confidence': [0.0, 0.5, 1.0], 'probability': [0.2, 0.7, 0.4]}}
OTHER_SIZE = {**BAD_KNOTS, 'knots': {'confidence': [0.0, 1.0], 'probability': [0.2, 0.9]},
              'estimator': {**FAST_SIGNATURE, 'processing_size': [320, 256]}}
TOO_LARGE = 300 * 1024 * 1024      # written sparse: refused from its size, never read
REFUSED = [
    ('decreasing', BAD_KNOTS, 'knots.probability decreases (0.7 then 0.4 at confidence 1): the map must be monotone'),
    ('mismatched', OTHER_SIZE, f'fitted for another estimator: processing_size 320x256 (the estimator: {W}x{H})'),
    ('missing', None, 'no such file'),
    ('too_large', TOO_LARGE, f'{TOO_LARGE} bytes, larger than the {CC.MAX_FILE_BYTES} bytes a calibration file may '
     'have (a map is a few kB); not read'),
]


@pytest.fixture(scope='module')
def refusals(tmp_path_factory):
    """{case: (exit code, output)} of one node start per bad calibration file, forked from one parent."""
    folder = tmp_path_factory.mktemp('calibrations')
    starts = []
    for case, data, _ in REFUSED:
        path = folder / f'{case}.json'
        if isinstance(data, int):
            with path.open('wb') as f:
                f.truncate(data)
        elif data is not None:
            path.write_text(json.dumps(data))
        starts.append(('module', params_args({**FAST_PARAMS, 'confidence_calibration': str(path)})))
    return dict(zip((case for case, _, _ in REFUSED), forked_node_starts(starts)))


@pytest.mark.parametrize('case,message', [(c, m) for c, _, m in REFUSED], ids=[c for c, _, _ in REFUSED])
def test_a_bad_calibration_file_is_refused_at_start_naming_the_parameter(case, message, refusals):
    code, out = refusals[case]
    assert code == 2, out
    assert "invalid parameter: parameter 'confidence_calibration' = '" in out and f"{case}.json' refused: " in out
    assert message in out, out
    assert out.count('invalid parameter') == 1, out
    assert 'Traceback' not in out and not re.search(r'\bready\b', out), out
