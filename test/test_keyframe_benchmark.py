"""benchmarks.keyframe on a recorded sequence folder (--sequence): the frames pushed are the folder's, at its own
size, its depth never read, and the stage table says which sequence it timed."""
from __future__ import annotations

import numpy as np

from dpv_sensor.benchmarks import keyframe as KB
from dpv_sensor.data.sequence import Sequence, write_sequence
from dpv_sensor.data.synthetic import render_sequence


def test_a_sequence_folder_is_timed_at_its_own_size_without_its_depth(tmp_path):
    folder = tmp_path / 'room'
    write_sequence(folder, render_sequence(seed=5, num_frames=40, width=320, height=240), write_depth=False)
    seq = Sequence(folder, depth=False)
    frames = list(KB._frames((640, 480), 3, 5, str(folder)))
    assert len(frames) == 5 and frames[0].image.shape[:2] == (240, 320)
    np.testing.assert_array_equal(frames[2].T_world_cam_44, seq.pose(2))
    result = KB.run({'f32': {'cpu_precision': 'float32'}}, keyframes=1, warmup=0, threads=1, sequence=str(folder))
    assert result['sequence'] == 'room' and 'input' not in result
    v = result['variants']['f32']
    assert v['keyframes_timed'] == 1 and v['stages_ms']['push']['median'] > 0
    assert 'sequence room' in KB.markdown(result)
