"""A picture of the pose-refinement window's factor graph, from a real run.

    .venv/bin/python -m dpv_sensor.studies.window_graph SEQUENCE [--poses noisy0cov] [--frames 60]
        [--params pose_refinement=window refine_odom_covariance=odometry refine_keypoints=true] [--out PNG]

It runs the first --frames frames of a sequence folder through the node's pipeline in this process with the pose
source of the stream table (``gt``, ``noisy<seed>``, ``noisy<seed>cov``) and the refinement settings of --params,
then draws the last window the refiner solved (``RefinementResult.factors``: the gauge prior, odometry between
neighbours, photometric alignments, keypoint poses) and prints, per window, how many factors of each kind it held.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
from typing import List, Optional

DEFAULT_PARAMS = ('pose_refinement=window', 'refine_odom_covariance=odometry', 'refine_keypoints=true')


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0], epilog=__doc__.split('\n\n', 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('sequence', help='a sequence folder')
    p.add_argument('--poses', default='noisy0cov', help='pose source (stream table names; default noisy0cov)')
    p.add_argument('--frames', type=int, default=60)
    p.add_argument('--params', nargs='*', default=list(DEFAULT_PARAMS), help='KEY=VALUE node parameters')
    p.add_argument('--out', default='out/window_graph.png')
    p.add_argument('--threads', type=int, default=2)
    a = p.parse_args(argv)
    import torch
    torch.set_num_threads(a.threads)
    from dpv_sensor.benchmarks import stream_table_inputs as ST
    from dpv_sensor.data.sequence import Sequence
    from dpv_sensor.evaluation import runner as RN
    from dpv_sensor.evaluation.plots import window_graph_plot
    from dpv_sensor.stream.window_refiner import PoseRefinerConfig, WindowPoseRefiner
    seq = Sequence(pathlib.Path(a.sequence))
    config, _ = RN.build_config(RN.parse_overrides(a.params))
    if config.pose_refinement != 'window':
        p.error('--params must set pose_refinement=window')
    refiner = WindowPoseRefiner(PoseRefinerConfig.from_params(config.as_dict()))
    solved = []
    refine = refiner.refine

    def keep(ref, sources, *args, **kw):
        res = refine(ref, sources, *args, **kw)
        if res.factors:
            solved.append((ref.key, sorted(res.T_world_cam), res.factors))
            print(f'window at {ref.key:.3f}: ' + ', '.join(f'{k} {len(v)}' for k, v in res.factors.items()))
        return res
    refiner.refine = keep
    n = min(a.frames, len(seq))
    poses = ST.odometry_poses(seq, a.poses)[:n]
    var = ST.odometry_variance(seq, a.poses)
    RN.run_sequence(seq, config, RN.EvalOptions(max_frames=n, progress=False), keep_images=False, poses=poses,
                    pose_variance=None if var is None else var[:n], pose_refiner=refiner)
    if not solved:
        print('the refiner solved no window', file=sys.stderr)
        return 1
    ref, window, factors = solved[-1]
    out = window_graph_plot(window, factors, a.out, reference=ref,
                            title=f'{pathlib.Path(a.sequence).name}: one window '
                                  f'({a.poses}; {" ".join(a.params)})')
    print(f'written: {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
