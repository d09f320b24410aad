"""The live mount check (stream.mount_check) and the calibrate_mount tool: a flow pair keeps only the matches the
flow back returns; the check WARNs once, naming the mount, when the pairs say the mount is off, and never with the
exact mount; the tool on a rendered bag whose odometry is seen through a mount 2 deg and 3 cm off and stamped 30 ms
early finds both, and finds nothing with the exact mount.

The render is 320x240: there the fit's error on the exact mount was 0.37 deg (0.15 at 640x480, the size of the
development folders, where the acceptance figures are measured), so the rotation is asked within 0.5 deg here."""
import json
import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dpv_sensor.core.mount_calibration import MountFitConfig
from dpv_sensor.stream.mount_check import MountCheck, MountCheckConfig, pair_matches
from dpv_sensor.stream.window_refiner_config import PairMatches

from test_mount_calibration import K, _synthetic


def _texture(h=240, w=320, seed=0):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 2.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def test_a_flow_pair_keeps_the_matches_the_flow_back_returns():
    a = _texture()
    b = np.roll(a, 3, axis=1)                               # everything moved 3 px right
    ys, xs = np.mgrid[40:200:8, 40:280:8]
    pa = np.c_[xs.ravel(), ys.ravel()].astype(np.float64)
    pb = pa + [3.0, 0.0]
    pb[:20] += [0.0, 6.0]                                   # 20 matches 6 px off: the flow back misses them
    Ks = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])
    pair, why = pair_matches(0.0, 0.1, pa, pb, Ks, np.zeros((240, 320, 2), np.float32), a, b)
    assert why is None
    n = len(pair.xa_n3)
    assert n == min(100, len(pa) - 20)
    # none of the planted matches is among those kept (their normalised y is 6 px / f off the flow's)
    kept_px = pair.xb_n3[:, :2] * 200.0 + [160, 120]
    assert np.all(np.abs(kept_px[:, 1] - (pair.xa_n3[:, 1] * 200.0 + 120)) < 0.5)
    assert pair_matches(0.0, 0.1, pa, pb, Ks, np.zeros((240, 320, 2), np.float32), None, None) == (None,
                                                                                                   'no_images')
    assert pair_matches(0.0, 0.1, pa[:10], pb[:10], Ks)[1] == 'few_matches'


class _Log:
    def __init__(self):
        self.warnings = []

    def warning(self, text, *args, **kw):
        self.warnings.append(text)


def _feed(check: MountCheck, pairs, track):
    for t, T in zip(track._t, track._T):
        check.observe_frame(t, T)
    for p in pairs:
        pa = (p.xa_n3 @ K.T)[:, :2]
        pb = (p.xb_n3 @ K.T)[:, :2]
        check.observe_window(SimpleNamespace(matches=[PairMatches(p.t_a, p.t_b, pa, pb, K)], match_images={}))
    check.wait()


def test_the_check_warns_once_naming_the_mount_and_the_offset():
    pairs, track = _synthetic(np.array([1.0, 1.6, 0.6]), np.array([0.03, -0.01, 0.0]), 0.030)
    log = _Log()
    check = MountCheck(MountCheckConfig(background=False), logger=log,
                       mount_text=lambda fit: 'set T_base_camera:=[...]')
    _feed(check, pairs, track)
    st = check.status
    assert st.fits >= 3 and st.pairs == len(pairs)
    assert st.rotation_off and st.offset_off
    mount_warnings = [w for w in log.warnings if 'turned' in w]
    offset_warnings = [w for w in log.warnings if 'time offset' in w]
    assert len(mount_warnings) == 1 and len(offset_warnings) == 1      # the estimate did not move: said once
    assert 'set T_base_camera:=[...]' in mount_warnings[0]
    assert 'stamped 30 ms late' in offset_warnings[0]
    d = st.as_dict()
    assert d['fit']['ok'] and abs(d['fit']['time_offset_ms'] - 30.0) < 2.0


def test_the_exact_mount_gives_no_warning():
    pairs, track = _synthetic(np.zeros(3), np.zeros(3), 0.0, seed=3)
    log = _Log()
    check = MountCheck(MountCheckConfig(background=False), logger=log)
    _feed(check, pairs, track)
    assert check.status.fits >= 3 and check.status.fit.ok
    assert not (check.status.rotation_off or check.status.translation_off or check.status.offset_off)
    assert log.warnings == []


def test_a_fit_on_the_background_thread_reaches_the_status():
    pairs, track = _synthetic(np.zeros(3), np.zeros(3), 0.0, seed=4)
    check = MountCheck(MountCheckConfig(background=True, fit=MountFitConfig(max_offset_s=0.0)), logger=_Log())
    _feed(check, pairs, track)
    assert check.status.fits >= 1 and check.status.fit is not None and check.status.fit.ok


# ------------------------------------------------------------------------------------------- the tool on a bag

MOUNT_DEG = np.array([0.87, 1.75, 0.44])        # 2 deg about a tilted axis
MOUNT_M = np.array([0.03, 0.0, 0.0])


@pytest.fixture(scope='module')
def render():
    from dpv_sensor.data.synthetic import render_sequence
    return render_sequence(7, 150, width=320, height=240)


def _bag(tmp_path, seq, poses):
    from dpv_sensor.benchmarks.stream_table_inputs import PosedView
    from dpv_sensor.data import rosbag_io as R
    bag = tmp_path / 'bag'
    R.write_sequence_bag(bag, PosedView(seq, poses), odom_rate=100.0, progress=False)
    return bag


def _tool(bag, out):
    from dpv_sensor.tools import calibrate_mount
    rc = calibrate_mount.main([str(bag), '--json', str(out), '--quiet'])
    return rc, json.loads(out.read_text()) if out.exists() else None


def test_the_tool_finds_a_mount_and_a_time_offset(tmp_path, render, capsys):
    from dpv_sensor.benchmarks.stream_table_inputs import time_shifted_poses
    gt = [np.asarray(render.pose(i), np.float64) for i in range(len(render))]
    X = np.eye(4)
    X[:3, :3] = Rotation.from_rotvec(np.radians(MOUNT_DEG)).as_matrix()
    X[:3, 3] = MOUNT_M
    # the odometry 30 ms ahead of the images (stamped 30 ms early) and through a mount the tool is not told
    odom = [T @ np.linalg.inv(X) for T in time_shifted_poses(render, gt, 0.030)]
    rc, rep = _tool(_bag(tmp_path, render, odom), tmp_path / 'mount.json')
    assert rc == 0
    fit = rep['fit']
    err = np.array(fit['rotvec_deg']) - MOUNT_DEG
    assert float(np.linalg.norm(err)) < 0.5
    assert abs(fit['time_offset_ms'] + 30.0) < 5.0
    assert rep['rotation_off'] and rep['offset_off']
    if all(s is not None for s in fit['sigma_trans_mm']):
        # the shift across the camera's y axis is seen least here: 66 mm off at a σ of 24 mm in a fresh process,
        # 80 mm at 24.5 in a test worker that ran other tests first (the floating-point path of the networks and
        # the flow depends on the process's history): the σ is optimistic by about a third on this axis
        assert np.all(np.abs(np.array(fit['translation_mm']) - 1e3 * MOUNT_M) < 4.0 * np.array(fit['sigma_trans_mm'])
                      + 5.0)
    printed = capsys.readouterr().out
    assert 'T_base_camera:="[' in printed and 'odom_time_offset_ms:=-' in printed
    # the mount it prints, composed back, is the truth within the same tolerance
    q = np.array(rep['mount_estimate'][3:])
    assert math.degrees((Rotation.from_quat(q).inv() * Rotation.from_rotvec(np.radians(MOUNT_DEG))).magnitude()) < 0.5


def test_the_tool_finds_nothing_with_the_exact_mount(tmp_path, render):
    gt = [np.asarray(render.pose(i), np.float64) for i in range(len(render))]
    rc, rep = _tool(_bag(tmp_path, render, gt), tmp_path / 'mount.json')
    assert rc == 0
    assert not rep['rotation_off'] and not rep['translation_off'] and not rep['offset_off']
    assert abs(rep['fit']['time_offset_ms']) < 3.0


def test_the_tool_says_why_a_short_recording_gives_no_estimate(tmp_path, render, capsys):
    short = render.subset(list(range(8)))
    gt = [np.asarray(short.pose(i), np.float64) for i in range(len(short))]
    rc, rep = _tool(_bag(tmp_path, short, gt), tmp_path / 'mount.json')
    assert rc == 1 and rep is None
    assert 'no estimate: too few image pairs' in capsys.readouterr().err


def test_the_node_names_the_mount_to_set():
    """The WARN's last part (ros.worker): with the mount from the parameter, the T_base_camera that the fit says
    (the parameter's pose times the fit's); with the mount from TF, where to correct it."""
    pytest.importorskip('rclpy')
    from dpv_sensor.core.mount_calibration import MountFit
    from dpv_sensor.ros.worker import Worker
    fit = MountFit(True, rotvec_rad=np.radians([0.0, 0.0, 90.0]), translation_m=np.array([0.0, 0.0, 0.0]))
    node = SimpleNamespace(extrinsic_source='auto', T_base_camera=[0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    fake = SimpleNamespace(node=SimpleNamespace(settings=SimpleNamespace(node=node)))
    text = Worker._mount_text(fake, fit)
    assert text.startswith('set T_base_camera:=[0.1, 0, 0, 0, 0, 0.707107, 0.707107]'), text
    node.T_base_camera = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]          # auto with the identity: the mount is TF's
    assert Worker._mount_text(fake, fit).startswith('the mount comes from TF')
