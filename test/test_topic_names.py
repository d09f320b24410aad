"""A remapped image topic takes its camera_info (and an output's compressedDepth) with it, as image_transport names
them, unless those are remapped themselves; the README's node one-liner, run as written against a camera on
/camera/color/{image_raw,camera_info}, produces depth."""
import pathlib
import shlex

import pytest

from ros_helpers import start_node, stop_process, wait_for
from stream_driver import FAST_PARAMS, StreamDriver
from dpv_sensor.ros.topic_names import camera_info_of, topic_name

REPO = pathlib.Path(__file__).resolve().parents[1]


def _resolver(remaps: dict, ns: str = '/cam'):
    def resolve(name: str, only_expand: bool) -> str:
        if not only_expand and name in remaps:
            name = remaps[name]
        return name if name.startswith('/') else f'{ns}/{name}'
    return resolve


def test_camera_info_is_the_image_topics_sibling():
    assert camera_info_of('/camera/color/image_raw') == '/camera/color/camera_info'
    assert camera_info_of('/image') == '/camera_info'
    assert camera_info_of('image') == 'camera_info'


@pytest.mark.parametrize('remaps,name,expected', [
    ({}, 'camera_info', 'camera_info'),                                           # nothing remapped: as it is
    ({'image': '/camera/color/image_raw'}, 'camera_info', '/camera/color/camera_info'),
    ({}, 'image/compressed', 'image/compressed'),                                # image_transport: compressed
    ({'image': '/camera/color/image_raw'}, 'image/compressed', '/camera/color/image_raw/compressed'),
    ({'image': '/a/image', 'image/compressed': '/b/jpeg'}, 'image/compressed', 'image/compressed'),
    ({'image': '/a/image', 'camera_info': '/b/info'}, 'camera_info', 'camera_info'),   # remapped itself: its rule
    ({'depth/image': '/dpv/depth'}, 'depth/camera_info', '/dpv/camera_info'),
    ({'depth/image': '/dpv/depth'}, 'depth/image/compressedDepth', '/dpv/depth/compressedDepth'),
    ({'rgb/image': '/dpv/rgb'}, 'rgb/camera_info', '/dpv/camera_info'),
    ({'depth/image': '/dpv/depth'}, 'confidence/camera_info', 'confidence/camera_info'),
    ({'depth/image': '/dpv/depth'}, 'depth/points', 'depth/points'),
])
def test_followers_follow_their_remapped_image(remaps, name, expected):
    assert topic_name(name, _resolver(remaps)) == expected


def _readme_node_line() -> list[str]:
    for line in (REPO / 'README.md').read_text().splitlines():
        if line.startswith('python -m dpv_sensor.ros.node') and ' -r image:=' in line:
            return shlex.split(line.split('#')[0])[3:]
    raise AssertionError('the README has no `python -m dpv_sensor.ros.node ... -r image:=` line')


def test_readme_one_liner_subscribes_the_sibling_camera_info_and_produces_depth():
    args = _readme_node_line()
    assert args[:1] == ['--ros-args'] and 'image:=/camera/color/image_raw' in args, args
    assert not any(a.startswith('camera_info:=') for a in args), args
    drv = StreamDriver(args + ['-p', 'measurement:=classical', '-p', 'processing_width:=160',
                               '-p', 'processing_height:=128', '-p', 'diagnostics_period:=0.25',
                               '-p', 'extrinsic_source:=parameter'],
                       topics={'image': '/camera/color/image_raw', 'camera_info': '/camera/color/camera_info',
                               'odom': '/odom'}, frames=12, name='readme_camera')
    try:
        drv.wait_ready()
        for i in range(12):
            drv.send(i, drv.stamp_ns(i))
            assert drv.wait_accounted(i + 1), drv.outputs.diagnostics
        assert wait_for(lambda: drv.outputs.depth_count > 0, timeout=30.0, spin=drv.spin), drv.outputs.diagnostics
        diag = drv.wait_diagnostics()
    finally:
        log = drv.stop()
    assert drv.code == 0, log
    assert "camera_info='/camera/color/camera_info'" in log, log
    assert int(diag.get('dropped.no_camera_info', 0)) == 0, diag


def test_a_remapped_output_image_takes_its_camera_info_and_compressed_depth(observer):
    node, executor = observer
    params = {**FAST_PARAMS, 'publish_compressed_depth': True}
    args = ['--ros-args'] + [a for k, v in params.items() for a in ('-p', f'{k}:={v}')] + \
        ['-r', 'depth/image:=/dpv/depth', '-r', 'rgb/camera_info:=/mine/rgb_info']
    proc = start_node(args)
    want = {'/dpv/depth', '/dpv/camera_info', '/dpv/depth/compressedDepth', '/mine/rgb_info', '/rgb/image',
            '/confidence/camera_info', '/depth/points'}

    def published() -> set:
        return {name for name, _types in node.get_topic_names_and_types()
                if node.get_publishers_info_by_topic(name)}
    try:
        ok = wait_for(lambda: want <= published(), timeout=60.0, spin=lambda t: executor.spin_once(timeout_sec=t))
        topics = published()
    finally:
        code, out = stop_process(proc)
    assert ok, (sorted(topics), out)
    assert code == 0, out
    assert not {'/depth/camera_info', '/depth/image/compressedDepth', '/rgb/camera_info'} & topics, sorted(topics)
