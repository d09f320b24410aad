"""`ros2 run dpv_sensor soak`: a long replay through the node, reporting throughput, latency, drops and memory.

Renders (or takes) a long synthetic sequence, writes it as a rosbag2, starts the node as its own process, and replays
the bag in a loop at 30 Hz (--rate) for --minutes (default 5) with the stamps rebased to the wall clock, so
end-to-end latency = (receipt time of an output) - (its image stamp). Reported at the end (and as JSON with --json):

  throughput   images offered / s, outputs received / s (keyframes only unless publish_between_keyframes)
  latency      median and p95 of output receipt - image stamp (ms), and the node's own receipt -> publish figure
  accounting   images sent = received by the node + lost in transport (lost.*), received = processed + dropped
               (dropped.* by reason) + the one or two in flight at the stop; faults.*
  resets       the estimator's restarts from the node log, by cause; the one for the jump back to the start of the
               trajectory at each loop start of the bag is reported apart as loop_boundary
  memory       VmRSS of the node process (from /proc) after warm-up, at the end, its maximum, the median per
               window, and the medians of the two halves after a 2-minute warm-up (flat memory: they agree)

A tool, not a unit test: it takes minutes. Its `OutputCollector` (client.ros_io) is also used by the node tests.
"""
from __future__ import annotations

import argparse
import bisect
import collections
import json
import os
import pathlib
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from dpv_sensor import params as P
from dpv_sensor.cli import add_setting
from dpv_sensor.client.node_process import ClientNode, node_command
from dpv_sensor.client.replay import mount_params, tf_topics
from dpv_sensor.client.ros_io import OutputCollector

REPO = pathlib.Path(__file__).resolve().parents[2]
NS = 1_000_000_000


# --------------------------------------------------------------------------------------------------------------
# process helpers
# --------------------------------------------------------------------------------------------------------------
def vm_rss_kib(pid: int) -> int | None:
    """Resident memory (kB) of a process from /proc/<pid>/status, or None when it is gone."""
    try:
        with open(f'/proc/{pid}/status') as f:
            for line in f:
                if line.startswith('VmRSS:'):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def start_node_process(params: dict, remaps: dict, env: dict | None = None, log_path=None) -> subprocess.Popen:
    """`python -m dpv_sensor.ros.node --ros-args -p k:=v ... -r a:=b` with its output to `log_path` (or a pipe)."""
    cmd = node_command(params, remaps)
    full_env = dict(os.environ)
    full_env['PYTHONPATH'] = os.pathsep.join([str(REPO)] + [p for p in full_env.get('PYTHONPATH', '').split(os.pathsep)
                                                            if p])
    full_env.setdefault('PYTHONUNBUFFERED', '1')
    full_env.update(env or {})
    out = open(log_path, 'w') if log_path else subprocess.PIPE
    return subprocess.Popen(cmd, cwd=REPO, env=full_env, stdout=out, stderr=subprocess.STDOUT, text=True)


def stop_node_process(proc: subprocess.Popen, timeout: float = 20.0) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()


# --------------------------------------------------------------------------------------------------------------
# the soak run
# --------------------------------------------------------------------------------------------------------------
def _median_rss(samples, t0, t1):
    vals = [r for t, r in samples if t0 <= t <= t1]
    return int(np.median(vals)) if vals else None


def rss_trend(samples, wall_s: float, parts: int = 6, min_window_s: float = 60.0):
    """Median resident memory per consecutive window: `parts` equal windows over the run, none shorter than
    `min_window_s`. [(t0, t1, median kB or None)]. A leak climbs window after window; allocator growth that
    levels off stops climbing."""
    if not samples or not wall_s or wall_s != wall_s:
        return []
    n = max(1, min(parts, int(wall_s // min_window_s)))
    edges = np.linspace(0.0, wall_s, n + 1)
    out = []
    for a, b in zip(edges[:-1], edges[1:]):
        vals = [r for t, r in samples if a <= t < b or (b == edges[-1] and t >= b)]
        out.append((round(float(a), 1), round(float(b), 1), int(np.median(vals)) if vals else None))
    return out


def rss_halves(samples, wall_s: float, warmup_s: float = 120.0):
    """Median resident memory (kB) of [warmup, middle) and [middle, end] with middle halfway from the warm-up to the
    end (a 12-minute run: minutes 2-7 and 7-12), and later / earlier; Nones when a half has no sample."""
    if not samples or not wall_s or wall_s != wall_s or wall_s <= warmup_s:
        return {'windows_s': None, 'earlier_kib': None, 'later_kib': None, 'ratio': None}
    mid = warmup_s + (wall_s - warmup_s) / 2.0
    early = [r for t, r in samples if warmup_s <= t < mid]
    late = [r for t, r in samples if t >= mid]
    a = int(np.median(early)) if early else None
    b = int(np.median(late)) if late else None
    return {'windows_s': [round(warmup_s, 1), round(mid, 1), round(wall_s, 1)], 'earlier_kib': a, 'later_kib': b,
            'ratio': round(b / a, 4) if a and b else None}


# an rclpy console line: [LEVEL] [wall seconds] [logger]: message (the estimator's lines come through the node)
_RESET_LINE = re.compile(r'\[(\d+\.\d+)\] \[[^\]]*\]: (?:\[[\w.]+\] )?estimator reset: (.*)')


def reset_cause(reason: str) -> str:
    """A reset reason without its figures, e.g. 'time gap # s in the camera stream > reset_time_gap # s'."""
    return re.sub(r'-?\d+(?:\.\d+)?', '#', reason.strip())


def classify_resets(log_text: str, loop_starts_ns) -> dict:
    """The estimator's restarts in a node log by cause ({cause: count}). At each loop start of the bag (wall-clock
    ns, as the rebased stamps) the poses jump back to the start of the trajectory: the first restart for a jump
    logged after a loop start (and before the next one) is counted as 'loop_boundary', however late the busy node
    got to it; every other restart is counted by its reason."""
    starts = sorted(int(s) for s in loop_starts_ns)
    causes: collections.Counter = collections.Counter()
    claimed = set()
    for line in log_text.splitlines():
        m = _RESET_LINE.search(line)
        if not m:
            continue
        t_ns = int(round(float(m.group(1)) * NS))
        loop = bisect.bisect_right(starts, t_ns) - 1
        if loop >= 0 and loop not in claimed and 'jumped' in m.group(2):
            claimed.add(loop)
            causes['loop_boundary'] += 1
        else:
            causes[reset_cause(m.group(2))] += 1
    return dict(causes)


def accounting(diag: dict, images_sent: int) -> dict:
    """Where every image sent went, from the node's last /diagnostics: received + lost in transport, and
    processed + dropped of those received; `in_flight` = what is left (the images still queued or in the worker
    at the stop, or lost after the last one received, which no stamp gap shows)."""
    def num(key):
        try:
            return int(diag.get(key, 0))
        except (TypeError, ValueError):
            return 0
    received, lost = num('frames_received'), num('lost.transport')
    processed, dropped = num('frames_processed'), num('dropped_total')
    return {'sent': images_sent, 'received': received, 'lost_transport': lost, 'lost_rmw': num('lost.rmw'),
            'lost_stamp_gaps_only': num('lost.stamp_gaps_only'), 'processed': processed, 'dropped': dropped,
            'unaccounted': images_sent - processed - dropped - lost,
            'received_not_done': received - processed - dropped}


def _percentile(values, q):
    return float(np.percentile(values, q)) if len(values) else float('nan')


def _soak_bag(args, work: pathlib.Path) -> tuple[pathlib.Path, int]:
    """The bag to loop (--bag, or a synthetic sequence rendered into `work` unless it is there already) and its
    number of images."""
    from dpv_sensor.data import rosbag_io as R
    name = f'soak_seed{args.seed}_{args.frames}f_{args.width}x{args.height}'
    bag = pathlib.Path(args.bag) if args.bag else work / name
    if not bag.exists():
        from dpv_sensor.data.synthetic import render_sequence
        print(f'rendering {args.frames} frames ({args.width}x{args.height}, seed {args.seed}) -> {bag}', flush=True)
        seq = render_sequence(args.seed, args.frames, width=args.width, height=args.height, progress=True)
        R.write_sequence_bag(bag, seq, odom_rate=args.odom_rate, progress=True)
    n_images = R.bag_topics(bag)[R.IMAGE_TOPIC][1]
    print(f'bag: {bag} ({n_images} images)', flush=True)
    return bag, n_images


def _soak_params(args) -> dict:
    """The node's parameters: the soak's settings, then --param."""
    params = {'measurement': args.measurement, 'device': 'cpu', 'processing_width': args.processing_width,
              'processing_height': args.processing_height, 'diagnostics_period': 1.0}
    for item in args.param or []:
        k, v = P.split_assignment(item)
        params[k] = v
    return params


@dataclass
class _LoopStarts:
    """The rebased stamp of each loop's first image (the bag's stamps jump back there), from the player's
    on_publish callback."""
    stamps_ns: list = field(default_factory=list)
    last_bag_stamp_ns: int | None = None

    def on_publish(self, topic, _msg, bag_stamp_ns, stamp_ns) -> None:
        from dpv_sensor.data import rosbag_io as R
        if topic == R.IMAGE_TOPIC:
            if self.last_bag_stamp_ns is None or bag_stamp_ns < self.last_bag_stamp_ns:
                self.stamps_ns.append(stamp_ns)
            self.last_bag_stamp_ns = bag_stamp_ns


@dataclass
class _RssRecord:
    """The node's resident memory every 5 s: (seconds since the start of play, kB), and the first sample after
    `warmup_outputs` outputs."""
    t0: float
    next_sample: float
    samples: list = field(default_factory=list)
    start: tuple | None = None
    warmup_outputs: int = 5

    def sample(self, now: float, pid: int, collector: OutputCollector) -> None:
        """Take a sample when one is due; print a progress line every minute."""
        if now < self.next_sample:
            return
        rss = vm_rss_kib(pid)
        if rss is not None:
            self.samples.append((round(now - self.t0, 1), rss))
            if self.start is None and collector.depth_count >= self.warmup_outputs:
                self.start = (round(now - self.t0, 1), rss)
        self.next_sample = now + 5.0
        if len(self.samples) % 12 == 1:
            print(f'  t={now - self.t0:6.0f} s outputs={collector.depth_count} rss={rss} kB '
                  f"dropped={collector.diagnostics.get('dropped_total', '?')}", flush=True)


class _Soak:
    """One soak run: the node as its own process, a client node that plays the bag in a loop and collects the
    outputs; start, play while sampling memory, let the node finish, report, close."""

    def __init__(self, args, bag: pathlib.Path, params: dict, log_path: pathlib.Path):
        from dpv_sensor.client.ros_io import BagPlayer
        from dpv_sensor.data import rosbag_io as R
        self.args = args
        self.log_path = log_path
        remaps = {'image': R.IMAGE_TOPIC, 'camera_info': R.CAMERA_INFO_TOPIC, 'odom': R.ODOM_TOPIC}
        env = {'OMP_NUM_THREADS': str(args.threads)} if args.threads else {}
        self.proc = start_node_process(params, remaps, env=env, log_path=log_path)
        print(f'node pid {self.proc.pid}, log {log_path}', flush=True)
        self.client = ClientNode('dpv_soak')
        self.executor = self.client.executor
        self.collector = OutputCollector(self.client.node, keep_messages=False)
        self.player = BagPlayer(self.client.node, bag, rate=args.rate, rebase_stamps=True, loop=True)
        self.loop_starts = _LoopStarts()
        self.player.on_publish = self.loop_starts.on_publish

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.05)

    def wait_for_node(self) -> None:
        """Until the node subscribed to the inputs (an error when it did not, or exited), then until its first
        output or diagnostics (at most 60 s)."""
        from dpv_sensor.data import rosbag_io as R
        missing = self.player.wait_for_subscribers([R.IMAGE_TOPIC, R.CAMERA_INFO_TOPIC, R.ODOM_TOPIC], timeout=120.0,
                                                   spin=lambda t: self.executor.spin_once(timeout_sec=t))
        if missing or self.proc.poll() is not None:
            raise RuntimeError(f'node did not subscribe to {missing} (exit code {self.proc.poll()}); '
                               f'see {self.log_path}')
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and self.collector.depth_count == 0 \
                and self.collector.diagnostics_count == 0:
            self.executor.spin_once(timeout_sec=0.1)

    def play(self) -> tuple[object, _RssRecord]:
        """Play for --minutes in a thread while spinning and sampling the node's memory; the player's statistics
        (None if it failed) and the memory samples. An error when the node exits meanwhile."""
        stats_box = {}

        def play():
            stats_box['stats'] = self.player.play(duration=self.args.minutes * 60.0)
        thread = threading.Thread(target=play, daemon=True)
        t0 = time.monotonic()
        thread.start()
        rss = _RssRecord(t0=t0, next_sample=t0)
        while thread.is_alive():
            self.executor.spin_once(timeout_sec=0.05)
            rss.sample(time.monotonic(), self.proc.pid, self.collector)
            if self.proc.poll() is not None:
                self.player.stop()
                raise RuntimeError(f'node exited during the soak (code {self.proc.returncode}); see {self.log_path}')
        thread.join()
        return stats_box.get('stats'), rss

    def settle(self, images_offered: int) -> None:
        """Until a diagnostics message shows the node finished what it received (at most 60 s)."""
        settle = time.monotonic() + 60.0
        while time.monotonic() < settle:
            acc = accounting(self.collector.diagnostics, images_offered)
            if acc['received_not_done'] <= 0:
                break
            self.executor.spin_once(timeout_sec=0.1)

    def run(self) -> dict:
        """Wait for the node, play, let the last outputs arrive; the figures of the report."""
        from dpv_sensor.data import rosbag_io as R
        self.wait_for_node()
        stats, rss = self.play()
        self.spin_for(5.0)            # let the last outputs and a fresh diagnostics message arrive
        rss_end = vm_rss_kib(self.proc.pid)
        wall = stats.wall_s if stats else float('nan')
        images_offered = stats.per_topic.get(R.IMAGE_TOPIC, 0) if stats else 0
        self.settle(images_offered)
        return _soak_figures(stats, wall, images_offered, self.collector, rss, rss_end, self.loop_starts.stamps_ns)

    def close(self) -> int:
        """Stop the node and the client; the node's exit code."""
        code = stop_node_process(self.proc)
        self.client.close()
        return code


def _soak_figures(stats, wall: float, images_offered: int, collector: OutputCollector, rss: _RssRecord,
                  rss_end: int | None, loop_starts_ns: list) -> dict:
    """The report's figures from the player's statistics, the collected outputs, the node's last diagnostics and
    the memory samples."""
    lat = collector.latency_ms
    d = collector.diagnostics
    return {
        'wall_s': round(wall, 1),
        'images_offered': images_offered,
        'input_fps': round(images_offered / wall, 2) if wall else None,
        'outputs_received': collector.depth_count,
        'output_fps': round(collector.depth_count / wall, 3) if wall else None,
        'latency_ms_median': round(_percentile(lat, 50), 1),
        'latency_ms_p95': round(_percentile(lat, 95), 1),
        'latency_ms_max': round(float(max(lat)), 1) if lat else None,
        'node_latency_ms_median': d.get('latency_ms_median'),
        'node_processing_ms_median': d.get('processing_ms_median'),
        'node_keyframe_ms_median': d.get('keyframe_ms_median'),
        'node_frames_received': d.get('frames_received'),
        'node_frames_processed': d.get('frames_processed'),
        'node_outputs_published': d.get('outputs_published'),
        'dropped': {k: v for k, v in d.items() if k.startswith('dropped')},
        'lost': {k: v for k, v in d.items() if k.startswith('lost.') or k == 'input_period_ms'},
        'accounting': accounting(d, images_offered),
        'faults': {k: v for k, v in d.items() if k.startswith('faults.')},
        'measurement_model': d.get('measurement_model'),
        'filter_resets': d.get('filter_resets'),
        'output_resets': d.get('output_resets'),
        'loop_starts': len(loop_starts_ns),
        'loop_starts_ns': loop_starts_ns,
        'rss_kib_start': rss.start,
        'rss_kib_end': rss_end,
        'rss_kib_max': max((r for _t, r in rss.samples), default=None),
        # baseline (median) resident memory in the first and the last minute: flat memory means these agree
        'rss_kib_median_first_min': _median_rss(rss.samples, 0.0, 60.0),
        'rss_kib_median_last_min': _median_rss(rss.samples, wall - 60.0, wall + 1.0),
        'rss_kib_median_by_window': rss_trend(rss.samples, wall),
        'rss_halves_after_warmup': rss_halves(rss.samples, wall),
        'rss_samples': rss.samples,
        'player_worst_lateness_ms': round(stats.late_ms_max, 1) if stats else None,
        'loops': stats.loops if stats else None,
    }


def run_soak(args) -> dict:
    """Start the node, replay the bag in a loop for --minutes, stop the node; the report's figures."""
    work = pathlib.Path(args.work_dir or tempfile.mkdtemp(prefix='dpv_soak_'))
    work.mkdir(parents=True, exist_ok=True)
    bag, n_images = _soak_bag(args, work)
    # a bag with the camera mount on /tf_static: the node finds it there (the player plays every topic)
    from dpv_sensor.data import rosbag_io as R
    params = mount_params(_soak_params(args), tf_topics(R.bag_topics(bag)))
    log_path = work / 'node.log'
    soak = _Soak(args, bag, params, log_path)
    result: dict = {'bag': str(bag), 'images_in_bag': n_images, 'minutes': args.minutes, 'rate': args.rate,
                    'params': params, 'threads': args.threads}
    try:
        result.update(soak.run())
    finally:
        result['node_exit_code'] = soak.close()
    try:
        result['resets_by_cause'] = classify_resets(log_path.read_text(errors='replace'), soak.loop_starts.stamps_ns)
    except OSError:
        result['resets_by_cause'] = None
    return result


def _print_report(r: dict) -> None:
    print('\n=== soak report ===')
    print(f"duration      {r.get('wall_s')} s, {r.get('loops')} full loops of {r['images_in_bag']} images at "
          f"{r['rate']:g}x ({r['params']['processing_width']}x{r['params']['processing_height']} processing, "
          f"measurement {r.get('measurement_model')}, OMP threads {r.get('threads') or 'default'})")
    print(f"throughput    in {r.get('input_fps')} images/s, out {r.get('output_fps')} depth/s "
          f"({r.get('outputs_received')} outputs; node processed {r.get('node_frames_processed')} of "
          f"{r.get('node_frames_received')} received)")
    print(f"latency       stamp -> receipt median {r.get('latency_ms_median')} ms, p95 {r.get('latency_ms_p95')} ms, "
          f"max {r.get('latency_ms_max')} ms (node receipt -> publish median {r.get('node_latency_ms_median')} ms; "
          f"estimator {r.get('node_keyframe_ms_median')} ms per keyframe, {r.get('node_processing_ms_median')} ms "
          'per processed frame)')
    acc = r.get('accounting') or {}
    print(f"accounting    sent {acc.get('sent')} = received {acc.get('received')} + lost in transport "
          f"{acc.get('lost_transport')} (rmw {acc.get('lost_rmw')}, stamp gaps only {acc.get('lost_stamp_gaps_only')});"
          f" processed {acc.get('processed')} + dropped {acc.get('dropped')} + lost {acc.get('lost_transport')} = "
          f"sent - {acc.get('unaccounted')} (in flight at the stop)")
    print(f"drops         {r.get('dropped')}")
    print(f"lost          {r.get('lost')}")
    print(f"faults        {r.get('faults') or 'none'}; filter resets {r.get('filter_resets')}, by cause "
          f"{r.get('resets_by_cause')} ({r.get('loop_starts')} loop starts)")
    t_start, rss_start = r.get('rss_kib_start') or (None, None)   # (seconds, kB) at the 5th output
    print(f"memory VmRSS  start {rss_start} kB (at {t_start} s, after 5 outputs), end {r.get('rss_kib_end')} kB, max "
          f"{r.get('rss_kib_max')} kB; median first minute {r.get('rss_kib_median_first_min')} kB, last minute "
          f"{r.get('rss_kib_median_last_min')} kB")
    trend = r.get('rss_kib_median_by_window') or []
    if len(trend) > 1:
        print('memory trend  median per window: ' + ', '.join(
            f'{a / 60:.0f}-{b / 60:.0f} min {m / 1024:.0f} MB' if m is not None else f'{a / 60:.0f}-{b / 60:.0f} min -'
            for a, b, m in trend))
    halves = r.get('rss_halves_after_warmup') or {}
    if halves.get('windows_s'):
        a, m, b = (x / 60 for x in halves['windows_s'])
        print(f"memory halves median {a:.0f}-{m:.0f} min {halves['earlier_kib']} kB, {m:.0f}-{b:.0f} min "
              f"{halves['later_kib']} kB (later / earlier {halves['ratio']})")
    print(f"node exit     {r.get('node_exit_code')}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='soak', description=__doc__.split('\n\n')[0])
    parser.add_argument('--minutes', type=float, default=5.0, help='how long to replay (default 5)')
    parser.add_argument('--rate', type=float, default=1.0, help='playback speed factor (the bag is 30 Hz)')
    parser.add_argument('--bag', help='an existing bag (default: render a synthetic one)')
    parser.add_argument('--frames', type=int, default=300, help='frames of the synthetic sequence (looped)')
    parser.add_argument('--width', type=int, default=320)
    parser.add_argument('--height', type=int, default=240)
    parser.add_argument('--seed', type=int, default=5)
    parser.add_argument('--odom-rate', type=float, default=100.0)
    add_setting(parser, 'measurement')
    add_setting(parser, 'processing_width')
    add_setting(parser, 'processing_height')
    parser.add_argument('--threads', type=int, default=0, help='OMP_NUM_THREADS for the node (0: torch default)')
    parser.add_argument('--param', nargs='+', metavar='NAME:=VALUE', help='more node parameters')
    parser.add_argument('--work-dir', help='where the bag and the node log go (default: a temp dir)')
    parser.add_argument('--json', help='write the report as JSON here')
    args = parser.parse_args(argv)
    result = run_soak(args)
    if args.json:      # first: the figures of a long run survive a problem in the printout
        pathlib.Path(args.json).write_text(json.dumps(result, indent=1))
    _print_report(result)
    return 0 if result.get('node_exit_code') == 0 else 1


if __name__ == '__main__':
    sys.exit(main())
