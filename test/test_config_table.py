"""One table per configuration: every setting is defined once (dpv_sensor.params), and the node, the estimator and
`evaluate` refuse a bad value with the same message; the offline pipeline takes its pose source from the table."""
import ast
import dataclasses
import pathlib

import numpy as np
import pytest

from dpv_sensor.evaluation import offline as E
from dpv_sensor import params as P
from dpv_sensor.stream.estimator import EstimatorConfig

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / 'dpv_sensor'
SETTINGS = {s.name for s in P.SPECS + P.LIBRARY_SPECS}

# Same name, another setting: the fusion's own confidence mask, the trainer's table (TrainConfig), the frame of a
# frame or message (the node's frame_id setting is only the fallback for images without one), the pose study's
# measurement (classical or a network preset), a checkpoint path a benchmark reads, the preset of a training step.
OTHER_MEANING = {('evaluation/fusion.py', 'min_confidence'), ('tools/fuse.py', 'min_confidence'),
                 ('training/config.py', 'device'), ('training/checkpoints.py', 'device'),
                 ('stream/frame.py', 'frame_id'), ('stream/keyframes.py', 'frame_id'), ('client/ros_io.py', 'frame_id'),
                 # the odometry child frame a written bag carries, not the node's TF parent
                 ('data/rosbag_io.py', 'base_frame'), ('tools/bag.py', 'base_frame'),
                 ('studies/poses.py', 'measurement'), ('studies/error_breakdown.py', 'weights'),
                 ('benchmarks/train_step.py', 'preset')}
# the network presets are the tables of the nets themselves (planes and range of each preset)
OWN_VALUES = ('core/nets/',)


def _literal_defaults(tree):
    """(line, name, value) of every literal default (None aside: 'not given') of a function argument, a dataclass
    field or an argparse ``--name`` option whose name is a setting."""
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            args = node.args
            pos = args.posonlyargs + args.args
            for arg, default in list(zip(pos[len(pos) - len(args.defaults):], args.defaults)) + \
                    [(a, d) for a, d in zip(args.kwonlyargs, args.kw_defaults) if d is not None]:
                if arg.arg in SETTINGS and isinstance(default, ast.Constant) and default.value is not None:
                    yield node.lineno, arg.arg, default.value
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and \
                node.target.id in SETTINGS and isinstance(node.value, ast.Constant) and node.value.value is not None:
            yield node.lineno, node.target.id, node.value.value
        elif isinstance(node, ast.Call) and getattr(node.func, 'attr', '') == 'add_argument' and node.args and \
                isinstance(node.args[0], ast.Constant) and str(node.args[0].value).startswith('--'):
            name = str(node.args[0].value)[2:].replace('-', '_')
            for kw in node.keywords:
                if name in SETTINGS and kw.arg in ('default', 'choices') and \
                        isinstance(kw.value, (ast.Constant, ast.Tuple, ast.List)) and \
                        not (isinstance(kw.value, ast.Constant) and kw.value.value is None):
                    yield node.lineno, name, ast.unparse(kw.value)


def test_each_setting_has_exactly_one_definition():
    found = []
    for path in sorted(PACKAGE.rglob('*.py')):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel == 'params.py' or rel.startswith(OWN_VALUES):
            continue
        for line, name, value in _literal_defaults(ast.parse(path.read_text())):
            if (rel, name) not in OTHER_MEANING:
                found.append(f'{rel}:{line}: {name} = {value!r}')
    assert not found, 'a second default / choice list of a setting (take it from dpv_sensor.params):\n' + \
        '\n'.join(found)


def test_the_scan_finds_a_planted_second_default():
    tree = ast.parse("def f(damping: float = 0.8):\n    pass\n\n"
                     "p.add_argument('--window-mode', default='causal', choices=('causal', 'centered'))\n")
    assert {(name, str(value)) for _line, name, value in _literal_defaults(tree)} == {
        ('damping', '0.8'), ('window_mode', "'causal'"), ('window_mode', "('causal', 'centered')")}


def test_config_classes_are_the_table():
    fields = {f.name: f for f in dataclasses.fields(EstimatorConfig)}
    assert list(fields) == [s.name for s in P.ESTIMATOR_SPECS]
    cfg = EstimatorConfig()
    for s in P.ESTIMATOR_SPECS:
        assert getattr(cfg, s.name) == s.default, s.name
    node = P.NodeConfig()
    assert [f.name for f in dataclasses.fields(node)] == [s.name for s in P.NODE_SPECS]
    assert set(fields) | {s.name for s in P.NODE_SPECS} == SETTINGS       # every setting lands in one class
    assert not set(fields) & {s.name for s in P.NODE_SPECS}
    assert P.NodeConfig.from_params(P.defaults()).depth_encoding == P.default('depth_encoding')


BAD = [('damping', 3.0, "parameter 'damping' = 3.0 is above its maximum 1.0"),
       ('filter_mode', 'kalman', "parameter 'filter_mode' = 'kalman' is not one of"),
       ('processing_width', 16, "parameter 'processing_width' = 16 is below its minimum 32")]


@pytest.mark.parametrize('name,value,message', BAD, ids=[b[0] for b in BAD])
def test_estimator_and_evaluate_refuse_a_bad_value_with_the_same_message(name, value, message, tmp_path, capsys):
    from dpv_sensor.tools import evaluate as tool
    with pytest.raises(ValueError) as from_estimator:
        EstimatorConfig(**{name: value}).validate()
    with pytest.raises(ValueError) as from_params:
        P.validate(dict(P.defaults(), **{name: value}))
    with pytest.raises(ValueError) as from_evaluate:
        E.build_config({name: value})
    texts = {str(e.value) for e in (from_estimator, from_params, from_evaluate)}
    assert len(texts) == 1 and message in texts.pop()
    rc = tool.main(['sequence', 'synthetic:0:4', '--config', f'{name}={value}', '--out', str(tmp_path / 'x')])
    assert rc == 2 and message in capsys.readouterr().err


def test_node_refuses_a_bad_value_with_the_same_message():
    from ros_helpers import forked_node_starts
    name, value, message = BAD[0]
    ((code, out),) = forked_node_starts([('module', ['--ros-args', '-p', f'{name}:={value}'])])
    assert code == 2, out
    assert message in out and 'Traceback' not in out


# ---------------------------------------------------------------------------------------------
# the pose source offline
# ---------------------------------------------------------------------------------------------

TINY = {'measurement': 'classical', 'processing_width': 40, 'processing_height': 32, 'num_planes': 8,
        'keyframe_max_interval': 1, 'd_min': 1.0, 'd_max': 8.0, 'filter_mode': 'global'}


def _sequence(n=6):
    from test_evaluation import _gt_sequence
    return _gt_sequence(n)


def test_evaluate_passes_the_refiner_sigmas_from_the_config(monkeypatch):
    import torch
    from dpv_sensor.stream import window_refiner as poses
    torch.set_num_threads(1)
    built = []
    real = poses.WindowPoseRefiner

    class Recording(real):
        def __init__(self, config=None):
            built.append(config)
            super().__init__(config)

    monkeypatch.setattr(poses, 'WindowPoseRefiner', Recording)
    overrides = E.parse_overrides(['pose_refinement=window', 'odom_sigma_rot_deg=0.1', 'odom_sigma_trans_m=0.004'])
    config, _ = E.build_config(dict(TINY, **overrides))
    records, status = E.run_sequence(_sequence(), config, E.EvalOptions(progress=False))
    assert len(built) == 1
    assert built[0].odom_sigma_rot_deg == 0.1 and built[0].odom_sigma_trans_m == 0.004
    assert built[0].odom_sigma_trans_rel == P.default('odom_sigma_trans_rel')
    assert status.pose_refiner is True and records


def test_evaluate_runs_the_odometry_free_mode_offline():
    """odometry=none offline: visual odometry gives the poses (the sequence's are not used)."""
    import torch
    from dpv_sensor.data.synthetic import render_sequence
    torch.set_num_threads(1)
    seq = render_sequence(3, 10, width=160, height=120)
    config, _ = E.build_config(dict(TINY, odometry='none', processing_width=80, processing_height=64))
    records, status = E.run_sequence(seq, config, E.EvalOptions(progress=False))
    assert len(records) >= 3, status
    est = [r.T_world_cam_44 for r in records]
    gt = [np.asarray(seq.pose(r.index)) for r in records]
    assert all(np.all(np.isfinite(T)) for T in est)
    # visual odometry starts at the identity, the sequence's first pose is not: the poses are VO's
    assert not np.allclose(np.asarray(seq.pose(0)), np.eye(4))
    assert all(not np.allclose(a, b, atol=1e-6) for a, b in zip(est, gt))
