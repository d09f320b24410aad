"""studies.anchor_overrule's figures on a hand-made keyframe: abs_rel of the planted pixels and of the image, the
confident share of the planted pixels and how many of those were right, the keyframes counted."""
import numpy as np
import pytest

from dpv_sensor.stream.metric_anchors import AnchorReport
from dpv_sensor.studies import anchor_overrule as S


def _row():
    gt = np.full((4, 4), 2.0)
    near = np.zeros((4, 4), bool)
    near[2:] = True                                      # 8 planted pixels of 16
    planted = np.where(near, 4.0, 2.0)
    judged = np.where(near, 3.0, 2.0)                    # half the way back (abs_rel 0.5 on the planted pixels)
    sweep = np.where(near, 2.2, 2.0)
    conf = np.full((4, 4), 0.95)
    judged_conf = np.where(near, 0.3, 0.95)
    sweep_conf = np.where(near, 0.3, 0.95)
    sweep_conf[3, :2] = 0.92                             # 2 planted pixels confident again, within x1.25 (2.2 / 2)
    return {'gt': gt, 'valid': np.ones((4, 4), bool), 'near': near, 'net': (gt.copy(), conf),
            'defaults': (gt.copy(), conf), 'planted': (planted, conf), 'judged': (judged, judged_conf),
            'sweep': (sweep, sweep_conf), 'near_anchors': 5,
            'judged_report': AnchorReport(anchors=30, applied='dense', overruled_pixels=8),
            'sweep_report': AnchorReport(anchors=30, applied='dense', overruled_pixels=8)}


def test_summary_by_hand():
    quiet = _row()
    quiet['judged_report'] = AnchorReport(anchors=0, reason='too few anchors (0 < 20)')
    s = S.summarise([_row(), quiet])
    assert s['keyframes'] == 2 and s['checked'] == 1 and s['overruled'] == 1 and s['near_anchors'] == 5
    assert s['near']['net'] == 0.0 and s['near']['planted'] == pytest.approx(1.0)
    assert s['near']['judged'] == pytest.approx(0.5) and s['near']['sweep'] == pytest.approx(0.1)
    assert s['whole']['planted'] == pytest.approx(0.5) and s['whole']['judged'] == pytest.approx(0.25)
    # planted: all 16 planted pixels (both keyframes) at 0.95 and all wrong; judged: none; the sweep: 4 of 16, right
    assert s['confident']['planted'] == (1.0, 0.0)
    assert s['confident']['judged'] == (0.0, None)
    assert s['confident']['sweep'] == (0.25, 1.0)
    assert S._row('x', s).startswith('| x | 0.000 / 1.000 / 0.500 / 0.100 | 100 % (0.00) / 0 % / 25 % (1.00) |')
