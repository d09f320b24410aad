"""Start the dpv_sensor node: `ros2 launch dpv_sensor dpv_sensor.launch.py [argument:=value ...]`.

Arguments
  namespace     namespace of the node and of its relative topics (default: none), e.g. namespace:=cam gives
                /cam/depth/image; the shipped params file is keyed `/**` so it applies in any namespace
  params_file   parameters file (default: the installed config/dpv_sensor.yaml)
  preset        input topic names of a camera driver started with its own defaults: none (default),
                realsense (realsense2_camera rs_launch.py: /camera/camera/color/...) or zed (zed_wrapper
                zed_camera.launch.py, wrapper 5.x: /zed/zed_node/rgb/color/rect/... and /zed/zed_node/odom)
  image, camera_info, odom
                input topics; each one given overrides the preset's
  remaps        further remappings, space separated `from:=to` pairs, e.g. remaps:='depth/image:=/dpv/depth'
  log_level     debug, info (default), warn, error

Examples
  ros2 launch dpv_sensor dpv_sensor.launch.py preset:=realsense odom:=/odometry/filtered
  ros2 launch dpv_sensor dpv_sensor.launch.py namespace:=cam preset:=zed params_file:=/path/my_params.yaml

The topic logic is the plain function `remappings()`, importable without the launch packages.
"""
from __future__ import annotations

import os

PACKAGE = 'dpv_sensor'
EXECUTABLE = 'node'                 # console_scripts entry point of setup.py (lib/dpv_sensor/node)
PARAMS_FILE = os.path.join('config', 'dpv_sensor.yaml')   # relative to the package share directory
INPUTS = ('image', 'camera_info', 'odom')

# Input topics of camera drivers started with their own launch files and defaults.
PRESETS: dict[str, dict[str, str]] = {
    'none': {},
    # realsense2_camera 4.5x rs_launch.py: camera_namespace 'camera' and camera_name 'camera'. D4xx cameras have
    # no odometry: remap odom to your odometry source.
    'realsense': {'image': '/camera/camera/color/image_raw',
                  'camera_info': '/camera/camera/color/camera_info'},
    # zed_wrapper 5.x zed_camera.launch.py: camera_name 'zed', node_name 'zed_node' (4.x wrappers named the image
    # rgb/image_rect_color and its info rgb/camera_info: pass image:= and camera_info:=). Its odometry tracks
    # zed_camera_link, so set T_base_camera to the left optical frame's pose in it.
    'zed': {'image': '/zed/zed_node/rgb/color/rect/image',
            'camera_info': '/zed/zed_node/rgb/color/rect/camera_info',
            'odom': '/zed/zed_node/odom'},
}


def parse_remaps(text: str) -> list[tuple[str, str]]:
    """'a:=b c:=d' -> [('a', 'b'), ('c', 'd')]; ValueError naming a malformed pair."""
    pairs = []
    for item in text.split():
        src, sep, dst = item.partition(':=')
        if not sep or not src or not dst or ':=' in dst:
            raise ValueError(f'remap {item!r} is not of the form from:=to')
        pairs.append((src, dst))
    return pairs


def remappings(preset: str = 'none', image: str = '', camera_info: str = '', odom: str = '',
               remaps: str = '') -> list[tuple[str, str]]:
    """The node's remappings: the preset's input topics, each overridden by an explicit one, then `remaps`."""
    if preset not in PRESETS:
        raise ValueError(f'preset {preset!r} is not one of {sorted(PRESETS)}')
    topics = dict(PRESETS[preset])
    for name, value in zip(INPUTS, (image, camera_info, odom)):
        if value:
            topics[name] = value
    return [(name, topics[name]) for name in INPUTS if name in topics] + parse_remaps(remaps)


def _node_actions(context):
    from ament_index_python.packages import get_package_share_directory
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    def arg(name):
        return LaunchConfiguration(name).perform(context)

    params_file = arg('params_file') or os.path.join(get_package_share_directory(PACKAGE), PARAMS_FILE)
    return [Node(package=PACKAGE, executable=EXECUTABLE, name=PACKAGE, namespace=arg('namespace'),
                 parameters=[params_file],
                 remappings=remappings(arg('preset'), arg('image'), arg('camera_info'), arg('odom'), arg('remaps')),
                 arguments=['--ros-args', '--log-level', arg('log_level')], output='screen', emulate_tty=True)]


def generate_launch_description():
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, OpaqueFunction

    args = [
        DeclareLaunchArgument('namespace', default_value='', description='namespace of the node and its topics'),
        DeclareLaunchArgument('params_file', default_value='',
                              description='parameters file (empty: the installed config/dpv_sensor.yaml)'),
        DeclareLaunchArgument('preset', default_value='none', choices=sorted(PRESETS),
                              description='input topic names of a camera driver'),
        DeclareLaunchArgument('image', default_value='', description='image topic (overrides the preset)'),
        DeclareLaunchArgument('camera_info', default_value='', description='camera_info topic (overrides the preset)'),
        DeclareLaunchArgument('odom', default_value='', description='odometry topic (overrides the preset)'),
        DeclareLaunchArgument('remaps', default_value='', description="further remappings: 'from:=to from:=to'"),
        DeclareLaunchArgument('log_level', default_value='info', description='debug, info, warn or error'),
    ]
    return LaunchDescription(args + [OpaqueFunction(function=_node_actions)])
