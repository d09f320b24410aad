"""The per-window record of the refinement window's choices (studies.window_decisions): every candidate solved
from the default refiner's state, the odometry's own error recomputed by hand, and the summary's oracle."""
import math

import numpy as np
import pytest

from dpv_sensor.studies import window_decisions as WD


def test_rows_on_a_rendered_sequence_with_drift(tmp_path):
    from dpv_sensor.benchmarks import stream_table_inputs as ST
    from dpv_sensor.core.photometric import pose_error
    from dpv_sensor.data.sequence import Sequence, write_sequence
    from dpv_sensor.data.synthetic import render_sequence
    folder = write_sequence(tmp_path / 'seq', render_sequence(51, 30, width=320, height=240), lossless=True)
    rows = WD.run(folder, 'noisy0cov', 0, progress=False)
    assert len(rows) >= 3
    seq = Sequence(folder)
    odom = ST.odometry_poses(seq, 'noisy0cov')
    stamps = np.asarray(seq.stamps)
    for row in rows:
        assert set(row['errors']) == {'off', 'default', *WD.CANDIDATES}
        assert set(row['gates']) == {'default', *WD.CANDIDATES}
        # 'off' is the odometry's relative pose against the ground truth's, by hand
        i = int(np.argmin(np.abs(stamps - row['key'])))
        rot = []
        for s in row['sources']:
            j = int(np.argmin(np.abs(stamps - s)))
            rel = lambda P: np.linalg.inv(P[j]) @ P[i]                     # noqa: E731  T_src_ref
            rot.append(pose_error(rel([seq.pose(k) for k in range(len(seq))]), rel(odom))[1])
        assert row['errors']['off']['rot_deg'] == pytest.approx(float(np.mean(rot)), rel=1e-6)
        f = row['features']
        assert f['baseline_m'] > 0 and math.isfinite(f['depth_m']) and f['odom_source']
        assert all({'ok', 'inliers', 'parallax_px'} <= set(k) for k in f['keypoints'])
    # the photometric candidates aligned something somewhere; the default never does
    assert any(r['features']['photometric'] for r in rows)


def _row(errs):
    return {'errors': {k: {'rot_deg': v, 'trans_mm': 10 * v, 'shift_px': v} for k, v in errs.items()}}


def test_summary_and_the_per_window_best_by_hand():
    rows = [_row({'off': 1.0, 'default': 0.5, 'direction': 0.2, 'photometric': 0.9, 'both': 0.4}),
            _row({'off': 0.1, 'default': 0.3, 'direction': 0.6, 'photometric': 0.2, 'both': 0.7})]
    s = WD.summary_rows({'x gt': rows, 'empty gt': []})
    assert s[0]['windows'] == 2 and s[0]['default']['rot_deg'] == pytest.approx(0.4)
    # best never picks 'off': window 1 direction (0.2), window 2 photometric (0.2)
    assert s[0]['best']['shift_px'] == pytest.approx(0.2) and s[0]['best']['trans_mm'] == pytest.approx(2.0)
    assert s[0]['best_counts'] == {'default': 0, 'direction': 1, 'photometric': 1, 'both': 0}
    assert s[1] == {'run': 'empty gt', 'windows': 0}
    text = WD.markdown(s)
    assert '| x gt | 2 | 0.550 / 5.5 / 0.55 | 0.400 / 4.0 / 0.40 |' in text
