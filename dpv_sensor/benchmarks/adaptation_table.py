"""The adaptation table: shipped against adapted weights, each recording adapted by the ``adapt`` tool exactly as a
user runs it and scored through the stream table on frames it never saw.

    python -m dpv_sensor.benchmarks.adaptation_table --data DATA --out out/adaptation_table \
        [--pairs sun3d_3dmatch_frag1:sun3d_3dmatch_frag2 ...] [--seeds 60] [--noise-seeds 0] [--offline] \
        [--recording-odometry 0] [--tool-args "--steps 150"]

Evaluations:

- every sequence folder of ``--data`` (``--sequences`` picks some): adapted on its first half (images, poses, K and
  stamps written to a folder without ``depth/``), scored on its second half;
- every ``--pairs A:B`` (both directions): adapted on the whole of A (no depth), scored on the whole of B;
- every held-out rendered seed of ``--seeds``: the same halves as a folder (the control).

The recordings carry the dataset's poses, or with ``--recording-odometry SEED`` the stream table's odometry-like
drift of that seed, as a robot's recording carries its odometry (written as ``<name>_odom<seed>``).

The tool runs as its own process (``python -m dpv_sensor.tools.adapt REC --out W --quiet`` plus ``--tool-args``).
Exit 0: its weights are scored; exit 1 (the held-out score refused them): the user keeps the shipped weights, so
the adapted column is the shipped one, marked refused. Scoring is the stream table (dpv_sensor.benchmarks.
stream_table) of each scored folder at the node's defaults, with ``weights:=`` the adapted file for the adapted
column: GT poses, and per noise seed the noisy odometry with and without its covariance; ``--offline`` runs the
node's pipeline in this process instead of the node. Tool runs and stream-table runs are cached under ``--out``.

Written: ``OUT/adaptation_table.md`` (per evaluation and pose source: abs_rel, delta<1.25, ECE, share of pixels at
confidence >= 0.9 and their delta<1.25, shipped -> adapted; the tool's steps, minutes and decision; the summary the
acceptance reads: mean relative abs_rel change and delta1 change over the real evaluations, the worst abs_rel and
ECE changes, the renders apart) and ``OUT/adaptation_table.json``.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import shlex
import subprocess
import sys
from dataclasses import dataclass
from typing import Any, Dict, List, Optional

import numpy as np

from dpv_sensor.benchmarks.stream_table_inputs import odometry_poses, rendered_sequence, sequence_folders

# the pose-source rows of the stream table that the adaptation table reports (stream_table_markdown.table_rows)
POSES = ('gt', 'noisy', 'noisy+cov')
# (column, stream-table row key)
METRICS = (('abs_rel', 'abs_rel'), ('d1', 'd1'), ('ECE', 'ECE'), ('kept@.9', 'kept@.9'), ('d1@.9', 'd1@.9'))


@dataclass
class Evaluation:
    """One line of the table: the recording the tool adapts on (no depth) and the folder scored."""
    name: str
    recording: pathlib.Path
    scored: pathlib.Path
    kind: str           # 'halves' | 'pair' | 'render'


def _write_part(src: pathlib.Path, dst: pathlib.Path, frames: range, depth: bool,
                odometry_seed: Optional[int] = None) -> pathlib.Path:
    """Frames of a sequence folder as a folder of their own (PNG images: no second JPEG loss), once. A folder
    written anew (other frames, or a source that changed: a seed rendered with another frame count) takes the
    cached results made from its old content with it: the tool's run on it, the stream-table runs of its name.
    ``odometry_seed``: its poses are the stream table's odometry-like corruption of the dataset's (that seed), as a
    robot's recording carries them."""
    import shutil
    from dpv_sensor.data.sequence import Sequence, write_sequence
    done = dst / '.complete'
    src_done = src / '.complete'
    tag = (f'{src.resolve()} {frames.start}-{frames.stop} depth={depth} odometry={odometry_seed} '
           f'{src_done.read_text().strip() if src_done.is_file() else ""}')
    if done.is_file() and done.read_text() == tag:
        return dst
    seq = Sequence(src, depth=depth)
    if len(frames) < 2 or frames.stop > len(seq):
        raise ValueError(f'{src.name}: frames {frames.start}-{frames.stop} of {len(seq)}')
    out = dst.parent.parent
    shutil.rmtree(dst, ignore_errors=True)
    shutil.rmtree(out / 'weights' / dst.name, ignore_errors=True)
    for stale in (out / 'stream' / 'runs').glob(f'{dst.name}__*'):
        stale.unlink()
    part = seq.subset(list(frames))
    if odometry_seed is not None:
        part = part.with_poses(odometry_poses(part, f'noisy{odometry_seed}'))
    write_sequence(dst, part, lossless=True, write_depth=depth, write_extras=False)
    done.write_text(tag)
    return dst


def evaluations(data: Optional[pathlib.Path], names: Optional[List[str]], pairs: List[str], seeds: List[int],
                out: pathlib.Path, frames: int, odometry_seed: Optional[int] = None) -> List[Evaluation]:
    """The evaluations' folders, written under OUT/recordings and OUT/scored (``odometry_seed``: the recordings
    carry odometry-like poses of that noise seed, named ``..._odom<seed>``)."""
    odom = '' if odometry_seed is None else f'_odom{odometry_seed}'
    from dpv_sensor.data.sequence import Sequence
    evals: List[Evaluation] = []
    folders = {p.name: p for p in sequence_folders(data)} if data else {}
    for name in names if names is not None else list(folders):
        if name not in folders:
            raise ValueError(f'no sequence folder {name!r} in {data}')
    halves = [(n, folders[n]) for n in (names if names is not None else folders)]
    halves += [(f'synthetic_seed{s}', rendered_sequence(out, s, frames, progress=True)) for s in seeds]
    for name, src in halves:
        n = len(Sequence(src, depth=False))
        evals.append(Evaluation(
            name=f'{name} (2nd half)',
            recording=_write_part(src, out / 'recordings' / f'{name}_first{odom}', range(0, n // 2), depth=False,
                                  odometry_seed=odometry_seed),
            scored=_write_part(src, out / 'scored' / f'{name}_second', range(n // 2, n), depth=True),
            kind='render' if name.startswith('synthetic_seed') else 'halves'))
    for pair in pairs:
        a, _, b = pair.partition(':')
        if a not in folders or b not in folders:
            raise ValueError(f'--pairs {pair!r}: both must be sequence folders of {data}')
        for x, y in ((a, b), (b, a)):
            nx, ny = len(Sequence(folders[x], depth=False)), len(Sequence(folders[y], depth=False))
            evals.append(Evaluation(
                name=f'{y} (adapted on {x})',
                recording=_write_part(folders[x], out / 'recordings' / f'{x}_all{odom}', range(0, nx), depth=False,
                                      odometry_seed=odometry_seed),
                scored=_write_part(folders[y], out / 'scored' / f'{y}_all', range(0, ny), depth=True),
                kind='pair'))
    return evals


def adapt(ev: Evaluation, out: pathlib.Path, tool_args: List[str]) -> Dict[str, Any]:
    """Run the adapt tool on the evaluation's recording (cached by recording and arguments): its decision. Exit 0:
    weights written; 1: refused by the held-out score; 2: the recording refused (e.g. too short; its message kept)."""
    wdir = out / 'weights' / ev.recording.name
    cmd = [sys.executable, '-m', 'dpv_sensor.tools.adapt', str(ev.recording), '--out', str(wdir), '--quiet',
           *tool_args]
    stamp = wdir / 'command.json'
    done = json.loads(stamp.read_text()) if stamp.is_file() else {}
    if done.get('command') != shlex.join(cmd):
        wdir.mkdir(parents=True, exist_ok=True)
        print(f'adapt: {shlex.join(cmd)}', flush=True)
        proc = subprocess.run(cmd, stderr=subprocess.PIPE, text=True)
        sys.stderr.write(proc.stderr)
        if proc.returncode not in (0, 1, 2):
            raise RuntimeError(f'the adapt tool exited {proc.returncode} on {ev.recording}')
        done = {'command': shlex.join(cmd), 'rc': proc.returncode, 'stderr': proc.stderr.strip()[-500:]}
        stamp.write_text(json.dumps(done))
    weights = wdir / 'weights.safetensors'
    rep = json.loads((wdir / 'report.json').read_text()) if done['rc'] != 2 else {}
    decision = {0: 'written', 1: 'refused', 2: 'not run'}[done['rc']]
    return {'weights': str(weights) if done['rc'] == 0 else None, 'decision': decision, 'steps': rep.get('steps'),
            'minutes': rep.get('minutes'), 'held_out': rep.get('held_out'),
            'why': rep.get('refused') if done['rc'] == 1 else (done['stderr'] if done['rc'] == 2 else None),
            'stop_reason': rep.get('stop_reason'), 'command': done['command']}


def score(scored: List[pathlib.Path], out: pathlib.Path, weights: Optional[str], noise_seeds: str,
          offline: bool) -> Dict[str, Dict[str, Dict[str, Any]]]:
    """Stream-table rows of the scored folders: {folder name: {pose row: row}} (weights None: the shipped)."""
    from dpv_sensor.benchmarks import stream_table
    from dpv_sensor.benchmarks.stream_table_markdown import table_stem
    data = scored[0].parent
    params = {} if weights is None else {'weights': weights}
    argv = ['--data', str(data), '--sequences', *[p.name for p in scored], '--seeds', '', '--noise-seeds',
            noise_seeds, '--covariance', '--offset-ms', '0', '--no-consumer-odometry', '--quiet',
            '--out', str(out / 'stream')] + (['--offline'] if offline else [])
    if weights is not None:
        argv += ['--params', f'weights={weights}']
    if stream_table.main(argv) != 0:
        raise RuntimeError(f'stream table failed: {argv}')
    stem = table_stem(dict(params, offline=True) if offline else params)
    table = json.loads((out / 'stream' / f'{stem}.json').read_text())
    rows: Dict[str, Dict[str, Dict[str, Any]]] = {}
    for r in table['rows']:
        rows.setdefault(r['sequence'], {})[r['poses'].split(' ×')[0]] = r
    return rows


def _delta(a, b):
    return None if a is None or b is None else b - a


def summary(lines: List[Dict[str, Any]]) -> Dict[str, Any]:
    """What the acceptance reads, per pose row: over the real evaluations the mean relative abs_rel change, the
    mean delta1 change, the worst abs_rel and ECE changes; the renders' worst abs_rel change."""
    out: Dict[str, Any] = {}
    for pose in POSES:
        real = [ln for ln in lines if ln['kind'] != 'render' and pose in ln['shipped'] and pose in ln['adapted']]
        renders = [ln for ln in lines if ln['kind'] == 'render' and pose in ln['shipped'] and pose in ln['adapted']]
        if not real and not renders:
            continue

        def d(ln, k):
            return _delta(ln['shipped'][pose].get(k), ln['adapted'][pose].get(k))
        rel = [d(ln, 'abs_rel') / ln['shipped'][pose]['abs_rel'] for ln in real]
        out[pose] = {
            'evaluations': len(real),
            'mean_abs_rel_change_pct': 100 * float(np.mean(rel)) if rel else None,
            'mean_abs_rel': [float(np.mean([ln[w][pose]['abs_rel'] for ln in real])) for w in ('shipped', 'adapted')]
            if real else None,
            'mean_d1_change_points': 100 * float(np.mean([d(ln, 'd1') for ln in real])) if real else None,
            'worst_abs_rel_change': max((d(ln, 'abs_rel') for ln in real), default=None),
            'worst_ece_change': max((d(ln, 'ECE') for ln in real), default=None),
            'renders_worst_abs_rel_change': max((d(ln, 'abs_rel') for ln in renders), default=None)}
    return out


def _fmt(v, f='{:.3f}'):
    return '–' if v is None else f.format(v)


def markdown(lines: List[Dict[str, Any]], summ: Dict[str, Any], command: str) -> str:
    head = ['evaluation', 'poses', *[f'{c} shipped → adapted' for c, _ in METRICS], 'tool']
    text = [f'Command: `{command}`', '', '| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for ln in lines:
        tool = ln['tool']
        what = tool['decision'] + ('' if tool['steps'] is None else
                                   f", {tool['steps']} steps, {_fmt(tool['minutes'], '{:.1f}')} min")
        for pose in POSES:
            if pose not in ln['shipped']:
                continue
            s, a = ln['shipped'][pose], ln['adapted'].get(pose, {})
            cells = [f'{_fmt(s.get(k))} → {_fmt(a.get(k))}' for _c, k in METRICS]
            text.append(f"| {ln['name']} | {pose} | " + ' | '.join(cells) + f' | {what} |')
    text += ['', '| poses | real evaluations | mean abs_rel shipped → adapted | mean abs_rel change | mean d1 change |'
             ' worst abs_rel change | worst ECE change | renders: worst abs_rel change |', '|---' * 8 + '|']
    for pose, s in summ.items():
        m = s['mean_abs_rel']
        text.append(f"| {pose} | {s['evaluations']} | {_fmt(m and m[0], '{:.4f}')} → {_fmt(m and m[1], '{:.4f}')} | "
                    f"{_fmt(s['mean_abs_rel_change_pct'], '{:+.1f} %')} | "
                    f"{_fmt(s['mean_d1_change_points'], '{:+.1f} points')} | "
                    f"{_fmt(s['worst_abs_rel_change'], '{:+.4f}')} | {_fmt(s['worst_ece_change'], '{:+.4f}')} | "
                    f"{_fmt(s['renders_worst_abs_rel_change'], '{:+.4f}')} |")
    text += ['', 'Refused: the held-out score refused the adapted weights (the tool exits 1 and writes none), so the '
             'user keeps the shipped ones and the adapted figures are the shipped figures; not run: the tool '
             'refused the recording (exit 2, e.g. too few keyframes to hold out), the same. Scored frames are never '
             'adapted on; the recordings adapted on have no depth/.']
    text += [f"- {ln['name']}: {ln['tool']['decision']}: {ln['tool']['why']}" for ln in lines if ln['tool']['why']]
    return '\n'.join(text) + '\n'


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog='adaptation_table', description=__doc__.split('\n\n')[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--data', type=pathlib.Path, help='folder of sequence folders (each: halves)')
    ap.add_argument('--sequences', nargs='*', help='only these sequence folders of --data')
    ap.add_argument('--pairs', nargs='*', default=[], help='A:B: adapt on A, score B, and the other way round')
    ap.add_argument('--seeds', default='', help="held-out rendered seeds, e.g. '60' or '60-61' (controls)")
    ap.add_argument('--frames', type=int, default=60, help='frames per rendered seed (60)')
    ap.add_argument('--noise-seeds', default='0', help="odometry noise seeds ('' for GT poses only)")
    ap.add_argument('--recording-odometry', type=int, default=None, metavar='SEED',
                    help="the recordings adapted on carry odometry-like poses (the stream table's noise, this seed) "
                         "instead of the dataset's, as a robot's recording does; scoring is unchanged")
    ap.add_argument('--tool-args', default='', help='arguments added to the adapt command, e.g. "--steps 150"')
    ap.add_argument('--offline', action='store_true', help='score with the pipeline in this process, not the node')
    ap.add_argument('--out', type=pathlib.Path, default=pathlib.Path('out/adaptation_table'))
    return ap


def main(argv: Optional[List[str]] = None) -> int:
    from dpv_sensor.cli import tool_argv
    from dpv_sensor.training.dataset import check_heldout_seeds, parse_seeds
    argv = tool_argv(argv)
    ap = build_parser()
    a = ap.parse_args(argv)
    if a.data is not None and not a.data.is_dir():
        ap.error(f'--data {a.data}: not a folder')
    try:
        seeds = check_heldout_seeds(parse_seeds(a.seeds))
        evals = evaluations(a.data, a.sequences, a.pairs, seeds, a.out.resolve(), a.frames, a.recording_odometry)
    except ValueError as exc:
        ap.error(str(exc))
    if not evals:
        ap.error('nothing to evaluate: give --data and/or --seeds')
    out = a.out.resolve()
    tools = {}
    for ev in evals:
        if ev.recording.name not in tools:
            tools[ev.recording.name] = adapt(ev, out, shlex.split(a.tool_args))
    scored = list({ev.scored.name: ev.scored for ev in evals}.values())
    shipped = score(scored, out, None, a.noise_seeds, a.offline)
    lines = []
    for ev in evals:
        tool = tools[ev.recording.name]
        adapted = shipped[ev.scored.name] if tool['weights'] is None else \
            score([ev.scored], out, tool['weights'], a.noise_seeds, a.offline)[ev.scored.name]
        pick = {pose: {k: row.get(k) for _c, k in METRICS} for pose, row in shipped[ev.scored.name].items()}
        lines.append({'name': ev.name, 'kind': ev.kind, 'recording': str(ev.recording), 'scored': str(ev.scored),
                      'tool': tool, 'shipped': pick,
                      'adapted': {pose: {k: row.get(k) for _c, k in METRICS} for pose, row in adapted.items()}})
    write_tables(out, 'adaptation_table', 'python -m dpv_sensor.benchmarks.adaptation_table ' + shlex.join(argv),
                 lines, summary, markdown)
    return 0


def write_tables(out: pathlib.Path, stem: str, command: str, lines: List[Dict[str, Any]], summarise, render) -> None:
    """``OUT/<stem>.md`` (``render(lines, summary, command)``, also printed) and ``OUT/<stem>.json`` (the command,
    the lines and ``summarise(lines)``)."""
    summ = summarise(lines)
    text = render(lines, summ, command)
    (out / f'{stem}.md').write_text(text)
    (out / f'{stem}.json').write_text(json.dumps({'command': command, 'lines': lines, 'summary': summ}, indent=1))
    print('\n' + text)


if __name__ == '__main__':
    sys.exit(main())
