"""The stream table: every sequence of a data folder and held-out rendered seeds through the node process.

    python -m dpv_sensor.benchmarks.stream_table --data DATA_FOLDER --seeds 50-52 --out out/stream_table \\
        [--noise-seeds 0-2] [--params window_mode=centered ...] [--sequences tum_fr1_rpy ...] [--frames 60]

Each run is one (sequence, pose source, node parameters) replay exactly as ``make demo`` replays
(dpv_sensor.client.replay): the sequence is written as a rosbag2 (image + camera_info at the sequence's stamps,
odometry at 100 Hz), the node is started as its own process at its defaults plus the demo's transport settings
(reliable input, deep queue, diagnostics every 0.1 s) plus ``--params``, the bag is played in lockstep (no image
dropped) while the outputs are recorded, and the recorded bag is scored with ``evaluate bag``'s code
(dpv_sensor.evaluation.offline.records_from_bag / evaluate_records).

``--offline`` runs the same sequences, pose sources and parameters through the node's pipeline in this process
(``evaluation.runner.run_sequence``: no bag, DDS or node process; the honest source's covariance handed to the frames
as the bag would carry it) and scores them the same way, without consumer odometry: a quick ablation that gives the
node's depth (cached and tabled apart, ``offline=True`` in the names). The table of record is the node's.

Pose sources: ``gt`` (the sequence's poses as odometry), ``offset<t>ms`` (``--offset-ms``, default 10: the GT pose
t ms after each image's stamp, before it when negative, a camera-odometry time offset), ``mount<k>``
(``--mount-seeds``: the GT poses through a mount the node is not told, 1-3 deg about a tilted axis and 2-5 cm,
seeded), ``noisy<k>`` for each noise seed k (odometry-like drift: 2 % of each step's translation in a random
direction and a 0.1 deg rotation about a random axis per frame,
chained: dpv_sensor.data.trajectory.corrupt_trajectory) and ``noisy<k>cov`` (``--covariance``: the same poses with the
noise model's own accumulated variance in ``pose.covariance``, as an honest odometry publishes it:
dpv_sensor.data.trajectory.corruption_variance) and ``noisy<k>twist`` (``--twist-covariance``: the same poses with a
constant ``pose.covariance`` and the noise model's motion noise in ``twist.covariance``, as a diff-drive controller
publishes it: dpv_sensor.data.trajectory.corruption_twist_variance). Depth is always scored against the GT depth,
and consumer odometry against the GT poses.

Columns (frame means over the recorded keyframe outputs unless said otherwise):

- abs_rel, d1: metric depth; ms abs_rel: per-frame median-scaled abs_rel; coverage: scored / valid GT pixels.
- scale q25, scale q75: quartiles over the images of each image's scale (the median of depth / GT over its scored
  pixels); scaled abs_rel: abs_rel once each image is divided by its own scale (what a perfect per-image scale
  correction would leave: dpv_sensor.evaluation.metrics.image_scale_summary). anchors/kf: metric anchors per
  checked keyframe (``depth_anchors``; /diagnostics ``anchors_per_keyframe``).
- mount°, mount σ°, offset ms, offset σ: the node's mount check at the end of the run (/diagnostics
  ``mount_estimate``: the camera's angle from the mount in use and the largest of its axis sigmas;
  ``time_offset_estimate``: + = the odometry stamped late); the truth of a ``mount<k>`` or ``offset<t>ms`` source is
  in the run's JSON (``noise``).
- ECE, mean conf, d1 pooled, kept@.9, d1@.9, d1@.7: calibration of the published confidence as the probability of
  the delta1 event (dpv_sensor.evaluation.metrics.calibration_summary, pixels pooled over the run); a reliability
  diagram per run in ``OUT/plots/<run>_reliability.png``.
- conf½: confident-half ratio, abs_rel of the most confident half of a frame's scored pixels / abs_rel of all of
  them (dpv_sensor.evaluation.metrics.confident_half_ratio), mean over frames (the pooled figure is in the JSON).
- resets: published outputs whose filter restarted, whichever layer restarted it (the estimator's stream rules,
  an odometry teleport in the pose buffer, lost visual tracking; the filter's own rules are off), the stream's
  first output not counted: the node's ``output_resets`` diagnostics counter; the reasons are in the JSON.
- kf ms: median time of the node's estimator on a keyframe image (from the ``keyframe_ms_last`` values of the
  recorded /diagnostics: one per keyframe, since lockstep waits for the node to report each image).
- const abs_rel, const d1: a constant depth equal to the median GT depth of the whole sequence (an oracle
  constant), scored on the same keyframes and the same pixels as the prediction.
- odo t×, odo r×: consumer odometry (dpv_sensor.evaluation.consumer_odometry): Open3D RGB-D odometry between
  consecutive outputs on the predicted depth vs on the GT depth of the same frames; the ratio of the median
  translation / rotation RPE (hybrid Jacobian, Open3D's default). col t×, col r×: the same with the photometric-only
  Jacobian (the depth only warps), which stays accurate on GT depth where the hybrid one drifts.

Rows ``noisy`` (and ``noisy+cov``) are the mean over the noise seeds (with the spread of abs_rel); each seed's
numbers are in the JSON.

Resumable: every run is cached as ``OUT/runs/<sequence>__<pose>__<params>.json`` and skipped when present (delete a
file to redo that run); rendered seeds are cached under ``OUT/sequences``. Bags live under ``OUT/work/<run>`` while
a run is in progress and are deleted after it (``--keep-bags`` keeps them). The table is rebuilt from every cached
run of the requested set: ``OUT/stream_table.md`` and ``OUT/stream_table.json`` (``stream_table_<params>.*`` with
``--params``); ``--table-only`` only rebuilds it.
SIGINT or SIGTERM (``kill PID``, also for a run started with nohup) stops the run in progress and its node process;
finished runs stay cached. Exit code 0 when every requested run is in the table, 1 when a run failed (the others
still ran), 2 for bad arguments.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import re
import sys
import time
import traceback
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Tuple

from dpv_sensor.benchmarks.stream_table_inputs import (RENDER_FRAMES, RENDER_SIZE, TIME_OFFSET_MS, params_tag,
                                                       rendered_sequence, run_key, sequence_folders)
from dpv_sensor.benchmarks.stream_table_markdown import write_table
from dpv_sensor.benchmarks.stream_table_runs import RUN_VERSION, run_one, run_one_offline


# --------------------------------------------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='stream_table', description=__doc__.split('\n\n')[0],
                                epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--data', default=None, help='folder of sequence folders (every one is replayed)')
    p.add_argument('--sequences', nargs='*', default=None, help='only these sequence folders of --data')
    p.add_argument('--seeds', default='50-52', help="held-out rendered seeds, e.g. '50-52' or '50,53' ('' for none)")
    p.add_argument('--frames', type=int, default=RENDER_FRAMES, help=f'frames per rendered seed ({RENDER_FRAMES})')
    p.add_argument('--render-size', default=f'{RENDER_SIZE[0]}x{RENDER_SIZE[1]}', metavar='WxH',
                   help=f'size of the rendered seeds ({RENDER_SIZE[0]}x{RENDER_SIZE[1]})')
    p.add_argument('--noise-seeds', default='0-2', help="odometry noise seeds ('' for GT poses only)")
    p.add_argument('--covariance', action='store_true',
                   help='add the honest-odometry pose sources noisy<k>cov: the noisy poses of every noise seed with '
                        "the noise model's accumulated variance in pose.covariance")
    p.add_argument('--twist-covariance', action='store_true',
                   help='add the diff-drive pose sources noisy<k>twist: the noisy poses of every noise seed with a '
                        "constant pose.covariance and the noise model's motion noise in twist.covariance")
    p.add_argument('--no-gt', action='store_true', help='only the noisy (and time-offset) pose sources')
    p.add_argument('--offset-ms', type=float, nargs='*', default=[TIME_OFFSET_MS],
                   help=f'add a time-offset pose source per value: GT poses taken this many ms after each image stamp '
                        f'(negative: before; default {TIME_OFFSET_MS:g}; 0 or none given = none)')
    p.add_argument('--mount-seeds', default='',
                   help="add the mount-error pose sources mount<k> for these seeds, e.g. '1' or '1-2' (GT poses "
                        'seen through a mount 1-3 deg and 2-5 cm off that the node is not told)')
    p.add_argument('--params', nargs='*', default=[], metavar='KEY=VALUE', help='node parameters over the defaults')
    p.add_argument('--out', default='out/stream_table', help='output folder (cache of runs, tables)')
    p.add_argument('--min-depth', type=float, default=None, help='smallest GT depth scored (default: all valid)')
    p.add_argument('--max-depth', type=float, default=None, help='largest GT depth scored (default: all valid)')
    p.add_argument('--domain-id', type=int, default=None,
                   help='ROS_DOMAIN_ID of the node and the player (default: $ROS_DOMAIN_ID, else a random one)')
    p.add_argument('--keep-bags', action='store_true', help='keep the input / output bags of every run')
    p.add_argument('--no-consumer-odometry', action='store_true',
                   help='skip the consumer check (Open3D RGB-D odometry on predicted vs GT depth: the odo/col '
                        'columns), most of the scoring time on long sequences')
    p.add_argument('--table-only', action='store_true', help='run nothing, rebuild the table from the cache')
    p.add_argument('--offline', action='store_true',
                   help="the node's pipeline in this process (no bag, DDS or node; no consumer odometry): quick "
                        "ablations, cached and tabled apart (offline=True in the names)")
    p.add_argument('--quiet', action='store_true', help='no progress bars')
    return p


@dataclass
class _Options:
    """The command line's values that need parsing: node parameters, rendered and noise seeds, render size."""
    params: Dict[str, Any]
    seeds: List[int]
    noise_seeds: List[int]
    render_size: Tuple[int, int]


@dataclass
class _Table:
    """What one invocation covers: the sequences (name -> folder; None: a rendered seed, rendered when its first run
    starts), the pose sources, the node parameters, and where the runs are cached and the table is written."""
    out: pathlib.Path
    params: Dict[str, Any]
    folders: Dict[str, Optional[pathlib.Path]]
    noise_seeds: List[int]
    single_sources: Tuple[str, ...]      # pose sources with one run per sequence (gt, offset<t>ms)
    command: str
    covariance: bool = False             # also the noisy<k>cov sources (the noise model's variance published)
    twist: bool = False                  # also the noisy<k>twist sources (constant pose, motion noise in the twist)
    offline: bool = False                # the pipeline in this process instead of the node (run_one_offline)

    @property
    def tag_params(self) -> Dict[str, Any]:
        """The parameters as run files and table names carry them (offline runs are told apart)."""
        return dict(self.params, offline=True) if self.offline else self.params

    @property
    def sequences(self) -> List[str]:
        return list(self.folders)

    @property
    def sources(self) -> List[str]:
        suffixes = ('',) + (('cov',) if self.covariance else ()) + (('twist',) if self.twist else ())
        return list(self.single_sources) + [f'noisy{k}{x}' for x in suffixes for k in self.noise_seeds]

    def run_file(self, seq_name: str, pose_source: str) -> pathlib.Path:
        return self.out / 'runs' / f'{run_key(seq_name, pose_source, self.tag_params)}.json'

    def cached_runs(self) -> List[Dict[str, Any]]:
        """The cached runs of this table (of the current RUN_VERSION), sequence by sequence."""
        runs = []
        for s in self.sequences:
            for src in self.sources:
                f = self.run_file(s, src)
                if f.is_file():
                    r = json.loads(f.read_text())
                    if r.get('version') == RUN_VERSION:
                        r['key'] = f.stem      # the file's name is the key (offline runs once kept the node's)
                        runs.append(r)
        return runs

    def write(self, failures: Dict[str, str]) -> str:
        """Write the table of the cached runs; its text."""
        text, _ = write_table(self.out, self.cached_runs(), self.sequences, self.noise_seeds, self.tag_params,
                              self.command, failures, self.single_sources, self.covariance, self.twist)
        return text


def _parse_options(ap: argparse.ArgumentParser, a) -> _Options:
    """Parse --params, --seeds, --noise-seeds and --render-size (a usage error names a bad one)."""
    from dpv_sensor.client.replay import parse_params
    from dpv_sensor.training.dataset import check_heldout_seeds, parse_seeds
    try:
        params = parse_params(a.params)
        seeds = check_heldout_seeds(parse_seeds(a.seeds))
        noise_seeds = list(parse_seeds(a.noise_seeds))
        m = re.fullmatch(r'(\d+)x(\d+)', a.render_size)
        if not m:
            raise ValueError(f'--render-size expects WxH, got {a.render_size!r}')
        render_size = (int(m.group(1)), int(m.group(2)))
    except ValueError as exc:
        ap.error(str(exc))
    return _Options(params=params, seeds=seeds, noise_seeds=noise_seeds, render_size=render_size)


def _sequences(ap: argparse.ArgumentParser, a, seeds: List[int]) -> Dict[str, Optional[pathlib.Path]]:
    """The folders of --data (only --sequences when given), then the rendered seeds (None: not rendered yet)."""
    folders: Dict[str, Optional[pathlib.Path]] = {}
    if a.data:
        data = pathlib.Path(a.data)
        if not data.is_dir():
            ap.error(f'--data {data}: no such folder')
        found = {f.name: f.resolve() for f in sequence_folders(data)}
        names = a.sequences if a.sequences is not None else sorted(found)
        missing = [n for n in names if n not in found]
        if missing:
            ap.error(f'no sequence folder {missing} in {data} (found: {sorted(found)})')
        folders.update({n: found[n] for n in names})
    for s in seeds:
        folders[f'synthetic_seed{s}'] = None
    if not folders:
        ap.error('nothing to run: give --data and/or --seeds')
    return folders


def _prepare_to_run(out: pathlib.Path, domain_id: Optional[int]) -> None:
    """SIGINT and SIGTERM stop the current run cleanly (its node process included), also when the benchmark was
    started in the background, where the shell leaves SIGINT ignored; finished runs stay cached. The runs get a
    private ROS environment under `out` (``domain_id``, else $ROS_DOMAIN_ID, else a random domain)."""
    import signal
    from dpv_sensor.client.ros_io import private_ros_env

    def _stop(signum, frame):
        raise KeyboardInterrupt
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _stop)
    if domain_id is None and os.environ.get('ROS_DOMAIN_ID', '').isdigit():
        domain_id = int(os.environ['ROS_DOMAIN_ID'])
    private_ros_env(out, domain_id)


def _run_missing(table: _Table, a, render_size: Tuple[int, int], failures: Dict[str, str]) -> bool:
    """Run what is not cached yet (every sequence with GT poses first), caching each run and rewriting the table
    after it; a failed run is noted in `failures`. False when interrupted."""
    progress = not a.quiet
    todo = [(s, src) for src in table.sources for s in table.sequences if not table.run_file(s, src).is_file()]
    print(f'stream table: {len(table.sequences) * len(table.sources) - len(todo)} runs cached, {len(todo)} to run '
          f'(parameters: {params_tag(table.params)}) -> {table.out}', flush=True)
    for n, (s, src) in enumerate(todo, 1):
        key = run_key(s, src, table.tag_params)
        print(f'\n=== run {n}/{len(todo)}: {s}, poses {src}, {params_tag(table.params)} '
              f'({time.strftime("%H:%M:%S")}) ===', flush=True)
        try:
            if table.folders[s] is None:
                table.folders[s] = rendered_sequence(table.out, int(s[len('synthetic_seed'):]), a.frames, progress,
                                                     render_size)
            if table.offline:
                res = run_one_offline(s, table.folders[s], src, table.params, table.out, min_depth=a.min_depth,
                                      max_depth=a.max_depth, progress=progress)
            else:
                res = run_one(s, table.folders[s], src, table.params, table.out, min_depth=a.min_depth,
                              max_depth=a.max_depth, keep_bags=a.keep_bags, progress=progress,
                              consumer_odometry=not a.no_consumer_odometry)
        except KeyboardInterrupt:
            print('\ninterrupted; finished runs are cached, run the same command again to go on', flush=True)
            return False
        except Exception as exc:
            failures[key] = f'{type(exc).__name__}: {exc}'
            (table.out / 'runs' / f'{key}.error.txt').write_text(traceback.format_exc())
            print(f'run {key} FAILED: {failures[key]}', flush=True)
            continue
        _cache_run(table.run_file(s, src), res)
        print(f"run {key}: abs_rel {res['abs_rel']:.4f}, d1 {res['delta1']:.3f}, {res['keyframes_scored']} "
              f"keyframes, resets {res['output_resets']}, kf {res['keyframe_ms_median'] or float('nan'):.0f} ms, "
              f"{res['timing']['total_s']:.0f} s", flush=True)
        table.write(failures)
    return True


def _cache_run(path: pathlib.Path, res: Dict[str, Any]) -> None:
    """Write a run's result to the cache (through a temporary file: an interrupted write leaves no run)."""
    tmp = path.with_name(path.name + '.tmp')
    tmp.write_text(json.dumps(res, indent=1))
    tmp.replace(path)


def main(argv: Optional[List[str]] = None) -> int:
    from dpv_sensor.cli import tool_argv
    argv = tool_argv(argv)
    ap = build_parser()
    a = ap.parse_args(argv)
    opts = _parse_options(ap, a)
    out = pathlib.Path(a.out).resolve()
    (out / 'runs').mkdir(parents=True, exist_ok=True)
    folders = _sequences(ap, a, opts.seeds)
    from dpv_sensor.training.dataset import parse_seeds
    single = tuple(([] if a.no_gt else ['gt']) + [f'offset{v:g}ms' for v in a.offset_ms if v != 0]
                   + [f'mount{k}' for k in parse_seeds(a.mount_seeds)])
    table = _Table(out=out, params=opts.params, folders=folders, noise_seeds=opts.noise_seeds, single_sources=single,
                   command='python -m dpv_sensor.benchmarks.stream_table ' +
                   ' '.join(x for x in argv if x != '--table-only'), covariance=a.covariance, twist=a.twist_covariance,
                   offline=a.offline)
    failures: Dict[str, str] = {}
    if not a.table_only:
        _prepare_to_run(out, a.domain_id)
        if not _run_missing(table, a, opts.render_size, failures):
            return 1
    text = table.write(failures)
    print('\n' + text)
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())
