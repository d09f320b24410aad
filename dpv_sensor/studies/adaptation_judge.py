"""Whether the adaptation's judges tell better depth from worse: the ``adapt`` tool run as a user runs it on the
first half of every folder (and of held-out renders), with the recording's poses exact or drifting like odometry,
its held-out keyframes scored by both judges and by the ground truth. Backs docs/adaptation.md.

    python -m dpv_sensor.studies.adaptation_judge --data DATA_FOLDER [--sequences ...] [--seeds 60] \
        [--poses gt noisy0 noisy1] [--tool-args "--steps 120 --threads 2"] [--out out/adaptation_judge]

Each run: the first half of the folder as a recording (images, poses, K and stamps; no depth), the tool at its
defaults plus ``--tool-args``, made to keep its adapted weights in memory whatever the judges say (``--judge
photometric --significance 1``: the photometric judge decides at the mean, the anchors' score is computed beside it)
and ``--gt`` (the same frames with depth and the dataset's poses: abs_rel of the held-out frames through the
node's pipeline, base and adapted). From the report's per-run scores, both judges' verdicts at the default
significance are made again here exactly as the tool makes them: the anchors' judge (with the photometric veto and
its refusal where too few runs have anchors) and the photometric judge alone. The table says per run the true
change of the held-out abs_rel, each judge's mean change and decision, and whether the anchors' mean change agrees
in sign with the true change; the summary: the agreement over the runs the anchors judge, and the true change of
the weights each judge would have written (mean, worst). Writes ``OUT/adaptation_judge.md`` and ``.json``; tool
runs are cached under ``OUT/runs``.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import shlex
import subprocess
import sys
from typing import Any, Dict, List, Optional

import numpy as np

SIGNIFICANCE = 0.05


def _parts(src: pathlib.Path, out: pathlib.Path, name: str, pose_source: str):
    """(recording without depth, the same frames with depth and the dataset's poses): the first half of ``src``."""
    from dpv_sensor.benchmarks.adaptation_table import _write_part
    from dpv_sensor.data.sequence import Sequence
    n = len(Sequence(src, depth=False)) // 2
    seed = None if pose_source == 'gt' else int(pose_source[len('noisy'):])
    rec = _write_part(src, out / 'folders' / f'{name}__{pose_source}', range(0, n), False, seed)
    gt = _write_part(src, out / 'folders' / f'{name}__truth', range(0, n), True, None)
    return rec, gt


def run_tool(rec: pathlib.Path, gt: pathlib.Path, out: pathlib.Path, tool_args: List[str], cached_only: bool = False
             ) -> Optional[Dict[str, Any]]:
    """The tool's report on ``rec`` (cached under ``out`` with its command; ``cached_only``: None where the run
    is not cached)."""
    cmd = [sys.executable, '-m', 'dpv_sensor.tools.adapt', str(rec), '--out', str(out), '--quiet', '--gt', str(gt),
           '--judge', 'photometric', '--significance', '1', *tool_args]
    stamp = out / '.command'
    report = out / 'report.json'
    if not (report.is_file() and stamp.is_file() and stamp.read_text() == shlex.join(cmd)):
        if cached_only:
            return None
        out.mkdir(parents=True, exist_ok=True)
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode not in (0, 1):
            raise RuntimeError(f'adapt failed ({proc.returncode}): {proc.stderr[-2000:]}')
        stamp.write_text(shlex.join(cmd))
    return json.loads(report.read_text())


def verdicts(report: Dict[str, Any], significance: float = SIGNIFICANCE) -> Dict[str, Any]:
    """Both judges' decisions at ``significance`` from a report's per-run scores, as the tool makes them."""
    from dpv_sensor.training.heldout_decision import judge, runs_needed, veto
    held = report['held_out']
    photo = {'base_runs': held['runs']['base'], 'adapted_runs': held['runs']['adapted']}
    anchors = held['beside'].get('anchors')
    p = judge(photo['base_runs'], photo['adapted_runs'], significance, 'photometric')
    out: Dict[str, Any] = {'photometric': {'change_pct': 100 * p.mean_change, 'p': p.p_value, 'writes': p.better}}
    if anchors is None:
        return out
    judged = int(np.sum(np.isfinite(np.asarray(anchors['base_runs'], np.float64))))
    a = judge(anchors['base_runs'], anchors['adapted_runs'], significance, 'anchors')
    vetoed = veto(photo['base_runs'], photo['adapted_runs'], significance, 'photometric') is not None
    refused = judged < runs_needed(significance)
    out['anchors'] = {'change_pct': None if refused else 100 * a.mean_change, 'p': a.p_value, 'runs_judged': judged,
                      'refused': refused, 'vetoed': a.better and vetoed,
                      'writes': (not refused) and a.better and not vetoed}
    return out


def line(name: str, pose_source: str, report: Dict[str, Any]) -> Dict[str, Any]:
    gt = report.get('ground_truth') or {}
    b, a = (gt.get('base') or {}).get('abs_rel'), (gt.get('adapted') or {}).get('abs_rel')
    v = verdicts(report)
    anchors = v.get('anchors') or {}
    true = None if b is None or a is None else a - b
    agree = None
    if anchors.get('change_pct') is not None and true is not None and true != 0:
        agree = bool(np.sign(anchors['change_pct']) == np.sign(true))
    return {'sequence': name, 'poses': pose_source, 'steps': report['steps'], 'abs_rel': [b, a], 'true_change': true,
            'verdicts': v, 'anchors_agree': agree}


def summary(lines: List[Dict[str, Any]]) -> Dict[str, Any]:
    judged = [ln for ln in lines if ln['anchors_agree'] is not None]
    out: Dict[str, Any] = {'runs': len(lines), 'anchors_judged': len(judged),
                           'anchors_sign_agreement': (sum(ln['anchors_agree'] for ln in judged) / len(judged)
                                                      if judged else None)}
    for j in ('anchors', 'photometric'):
        written = [ln['true_change'] for ln in lines if (ln['verdicts'].get(j) or {}).get('writes')
                   and ln['true_change'] is not None]
        rel = [ln['true_change'] / ln['abs_rel'][0] for ln in lines if (ln['verdicts'].get(j) or {}).get('writes')
               and ln['true_change'] is not None]
        out[j] = {'written': len(written), 'worst_abs_rel_change': max(written) if written else None,
                  'mean_abs_rel_change_pct': 100 * float(np.mean(rel)) if rel else None}
    return out


def _f(x, fmt='{:+.4f}'):
    return '–' if x is None else fmt.format(x)


def markdown(lines: List[Dict[str, Any]], summ: Dict[str, Any], command: str) -> str:
    rows = ['| run | steps | held-out abs_rel (GT) | photometric change, p | photometric judge | anchors change, p, '
            'runs judged | anchors judge | agrees |', '|---|---|---|---|---|---|---|---|']
    for ln in lines:
        v = ln['verdicts']
        ph, an = v['photometric'], v.get('anchors') or {}
        if not an:
            judge_a = '–'
        elif an['refused']:
            judge_a = 'refuses (too few anchors)'
        else:
            judge_a = 'writes' if an['writes'] else ('vetoed' if an['vetoed'] else 'refuses')
        b, a = ln['abs_rel']
        agrees = '–' if ln['anchors_agree'] is None else ('yes' if ln['anchors_agree'] else 'no')
        rows.append(f"| {ln['sequence']}, {ln['poses']} | {ln['steps']} | {_f(b, '{:.4f}')} → {_f(a, '{:.4f}')} "
                    f"({_f(ln['true_change'])}) | {ph['change_pct']:+.2f} %, {ph['p']:.3f} | "
                    f"{'writes' if ph['writes'] else 'refuses'} | "
                    f"{_f(an.get('change_pct'), '{:+.2f} %')}, {_f(an.get('p'), '{:.3f}')}, "
                    f"{an.get('runs_judged', '–')} | {judge_a} | {agrees} |")
    s = summ
    agree = s['anchors_sign_agreement']
    text = [f'```\n{command}\n```', '', *rows, '',
            f"The anchors' mean change agrees in sign with the true change on "
            f"{'–' if agree is None else f'{100 * agree:.0f} %'} of the {s['anchors_judged']} runs it judges "
            f"({s['runs']} runs)."]
    for j in ('anchors', 'photometric'):
        w = s[j]
        text.append(f"- {j} judge: writes {w['written']} of {s['runs']}; their held-out abs_rel change: mean "
                    f"{_f(w['mean_abs_rel_change_pct'], '{:+.1f} %')}, worst {_f(w['worst_abs_rel_change'])}")
    return '\n'.join(text) + '\n'


def main(argv: Optional[List[str]] = None) -> int:
    from tqdm import tqdm

    from dpv_sensor.benchmarks.adaptation_table import write_tables
    from dpv_sensor.benchmarks.stream_table_inputs import rendered_sequence, sequence_folders
    from dpv_sensor.cli import tool_argv
    from dpv_sensor.training.dataset import check_heldout_seeds, parse_seeds
    argv = tool_argv(argv)
    ap = argparse.ArgumentParser(prog='adaptation_judge', description=__doc__.split('\n\n')[0])
    ap.add_argument('--data', type=pathlib.Path, default=None, help='folder of sequence folders')
    ap.add_argument('--sequences', nargs='*', default=None, help='only these sequence folders of --data')
    ap.add_argument('--seeds', default='60', help="held-out rendered seeds ('' for none)")
    ap.add_argument('--frames', type=int, default=300, help='frames per rendered seed')
    ap.add_argument('--poses', nargs='+', default=['gt', 'noisy0', 'noisy1'],
                    help="the recordings' poses: gt, or noisy<seed> (the stream table's odometry-like drift)")
    ap.add_argument('--tool-args', default='--steps 120 --threads 2', help='added to the adapt command')
    ap.add_argument('--out', type=pathlib.Path, default=pathlib.Path('out/adaptation_judge'))
    ap.add_argument('--table-only', action='store_true', help='run nothing: the table of the cached runs')
    a = ap.parse_args(argv)
    out = a.out.resolve()
    sources = {}
    if a.data is not None:
        for f in sequence_folders(a.data):
            if a.sequences is None or f.name in a.sequences:
                sources[f.name] = f
    for seed in check_heldout_seeds(parse_seeds(a.seeds)):
        sources[f'synthetic_seed{seed}'] = rendered_sequence(out, seed, a.frames, progress=True)
    jobs = [(name, src, p) for name, src in sources.items() for p in a.poses]
    lines = []
    for name, src, pose_source in tqdm(jobs, desc='adapt runs', unit='run'):
        try:
            rec, gt = _parts(src, out, name, pose_source)
            report = run_tool(rec, gt, out / 'runs' / f'{name}__{pose_source}', shlex.split(a.tool_args),
                              a.table_only)
        except (RuntimeError, ValueError) as exc:
            print(f'{name}, {pose_source}: {exc}', file=sys.stderr)
            continue
        if report is None:
            continue
        if report.get('refused') and report['steps'] == 0:
            print(f"{name}, {pose_source}: {report['refused']}", file=sys.stderr)
            continue
        lines.append(line(name, pose_source, report))
    write_tables(out, 'adaptation_judge', 'python -m dpv_sensor.studies.adaptation_judge ' + shlex.join(argv), lines,
                 summary, markdown)
    return 0


if __name__ == '__main__':
    sys.exit(main())
