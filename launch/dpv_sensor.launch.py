"""Start the dpv_sensor node: `ros2 launch dpv_sensor dpv_sensor.launch.py [argument:=value ...]`.

Arguments
  namespace     namespace of the node and of its relative topics (default: none), e.g. namespace:=cam gives
                /cam/depth/image; the shipped params file is keyed `/**` so it applies in any namespace
  params_file   parameters file (default: the installed config/dpv_sensor.yaml)
  driver        input topics (and, for zed, T_base_camera) of a camera driver started with its own defaults:
                none (default), realsense (realsense2_camera rs_launch.py: /camera/camera/color/...) or zed
                (zed_wrapper zed_camera.launch.py, wrapper 5.x: /zed/zed_node/rgb/color/rect/... and /zed/zed_node/odom)
  image, camera_info, odom
                input topics; each one given overrides the driver's. camera_info follows image (its sibling, as
                image_transport names it) unless given
  preset, window_mode, T_base_camera, extrinsic_source, measurement, device, publish_tf, base_frame
                node parameters (empty: the params file's value), e.g. preset:=paper T_base_camera:='[0,0,0,0,0,0,1]'
  params        any further node parameters, space separated `name:=value` pairs, e.g. params:='damping:=0.5'
  remaps        further remappings, space separated `from:=to` pairs, e.g. remaps:='depth/image:=/dpv/depth' (a
                remapped image takes its camera_info and compressedDepth with it)
  log_level     debug, info (default), warn, error

Precedence of parameters: the params file, then the driver's, then the arguments above.

Examples
  ros2 launch dpv_sensor dpv_sensor.launch.py driver:=realsense odom:=/odometry/filtered T_base_camera:='[...]'
  ros2 launch dpv_sensor dpv_sensor.launch.py namespace:=cam driver:=zed preset:=paper window_mode:=causal

The argument logic is the plain function `node_configuration()`, importable without the launch packages;
`ros_args()` gives the command line it amounts to.
"""
from __future__ import annotations

import os

PACKAGE = 'dpv_sensor'
EXECUTABLE = 'node'                 # console_scripts entry point of setup.py (lib/dpv_sensor/node)
PARAMS_FILE = os.path.join('config', 'dpv_sensor.yaml')   # relative to the package share directory
INPUTS = ('image', 'camera_info', 'odom')
PARAMETERS = ('preset', 'window_mode', 'T_base_camera', 'extrinsic_source', 'measurement', 'device', 'publish_tf',
              'base_frame')
ZED_OPTICAL_IN_CAMERA_LINK = [0.0, 0.06, 0.0, -0.5, 0.5, -0.5, 0.5]

# Input topics (and parameters) of camera drivers started with their own launch files and defaults.
DRIVERS: dict[str, dict] = {
    'none': {'topics': {}, 'parameters': {}},
    # realsense2_camera 4.5x rs_launch.py: camera_namespace 'camera' and camera_name 'camera'. D4xx cameras have
    # no odometry: remap odom to your odometry source; the camera mount comes from TF (extrinsic_source auto: the
    # driver publishes camera_link -> camera_color_optical_frame on /tf_static, the robot's URDF base_link ->
    # camera_link), or set T_base_camera to the colour optical frame's pose in the odometry's child frame.
    'realsense': {'topics': {'image': '/camera/camera/color/image_raw',
                             'camera_info': '/camera/camera/color/camera_info'},
                  'parameters': {}},
    # zed_wrapper 5.x zed_camera.launch.py: camera_name 'zed', node_name 'zed_node' (4.x wrappers named the image
    # rgb/image_rect_color and its info rgb/camera_info: pass image:= and camera_info:=). Its odometry tracks
    # zed_camera_link (x forward, y left, z up, between the lenses); the rgb image is the left camera's, whose optical
    # frame sits half the 12 cm baseline to the left (ZED 2, 2i, X; ZED Mini: pass T_base_camera with y 0.0315).
    'zed': {'topics': {'image': '/zed/zed_node/rgb/color/rect/image',
                       'camera_info': '/zed/zed_node/rgb/color/rect/camera_info',
                       'odom': '/zed/zed_node/odom'},
            'parameters': {'T_base_camera': ZED_OPTICAL_IN_CAMERA_LINK}},
}


def parse_pairs(text: str, what: str = 'remap') -> list[tuple[str, str]]:
    """'a:=b c:=d' -> [('a', 'b'), ('c', 'd')]; ValueError naming a malformed pair."""
    pairs = []
    for item in text.split():
        src, sep, dst = item.partition(':=')
        if not sep or not src or not dst or ':=' in dst:
            raise ValueError(f'{what} {item!r} is not of the form from:=to')
        pairs.append((src, dst))
    return pairs


def remappings(driver: str = 'none', image: str = '', camera_info: str = '', odom: str = '',
               remaps: str = '') -> list[tuple[str, str]]:
    """The node's remappings: the driver's input topics, each overridden by an explicit one, then `remaps`. An
    image given without its camera_info takes its own sibling (the node's rule), not the driver's."""
    if driver not in DRIVERS:
        raise ValueError(f'driver {driver!r} is not one of {sorted(DRIVERS)}')
    topics = dict(DRIVERS[driver]['topics'])
    if image and not camera_info:
        topics.pop('camera_info', None)
    for name, value in zip(INPUTS, (image, camera_info, odom)):
        if value:
            topics[name] = value
    return [(name, topics[name]) for name in INPUTS if name in topics] + parse_pairs(remaps)


def parameters(driver: str = 'none', params: str = '', **values: str) -> dict:
    """Typed node parameters from launch arguments (strings; empty = not given): the driver's, then `values` (names
    of PARAMETERS), then `params` ('name:=value ...'), each checked against the node's parameter table."""
    from dpv_sensor import params as P
    if driver not in DRIVERS:
        raise ValueError(f'driver {driver!r} is not one of {sorted(DRIVERS)}')
    unknown = set(values) - set(PARAMETERS)
    if unknown:
        raise ValueError(f'not a launch parameter argument: {sorted(unknown)}')
    out = {k: (list(v) if isinstance(v, list) else v) for k, v in DRIVERS[driver]['parameters'].items()}
    given = [(k, v) for k, v in values.items() if v != ''] + parse_pairs(params, 'parameter')
    names = {s.name for s in P.SPECS}
    for name, text in given:
        if name not in names:
            raise ValueError(f'unknown parameter {name!r}')
        spec = P.spec(name)
        try:
            value = P.parse_value(text, spec.default)
        except ValueError as exc:
            raise ValueError(f"parameter '{name}': {exc}") from None
        out[name] = P.check_value(spec, value)
    P.check_relations(out)
    return out


def node_configuration(args: dict) -> dict:
    """What the Node action gets from the launch arguments `args` (name -> string, missing = default):
    namespace, parameters ([params file, dict]), remappings and ros_arguments."""
    def arg(name, default=''):
        return args.get(name, default) or default
    driver = arg('driver', 'none')
    params_file = arg('params_file')
    if not params_file:
        from ament_index_python.packages import get_package_share_directory
        params_file = os.path.join(get_package_share_directory(PACKAGE), PARAMS_FILE)
    values = parameters(driver, arg('params'), **{k: arg(k) for k in PARAMETERS})
    return {'namespace': arg('namespace'),
            'parameters': [params_file] + ([values] if values else []),
            'remappings': remappings(driver, arg('image'), arg('camera_info'), arg('odom'), arg('remaps')),
            'ros_arguments': ['--log-level', arg('log_level', 'info')]}


def ros_args(config: dict) -> list[str]:
    """The node's command line for `config` (as launch_ros builds it, with the parameters dict inline)."""
    def text(value):
        if isinstance(value, bool):
            return 'true' if value else 'false'
        if isinstance(value, list):
            return '[' + ','.join(repr(float(v)) for v in value) + ']'
        return str(value)
    out = ['--ros-args', '-r', f'__node:={PACKAGE}']
    if config['namespace']:
        out += ['-r', f"__ns:=/{config['namespace'].strip('/')}"]
    for entry in config['parameters']:
        if isinstance(entry, dict):
            out += [a for k, v in entry.items() for a in ('-p', f'{k}:={text(v)}')]
        else:
            out += ['--params-file', str(entry)]
    out += [a for src, dst in config['remappings'] for a in ('-r', f'{src}:={dst}')]
    return out + list(config['ros_arguments'])


def _node_actions(context):
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    names = ('namespace', 'params_file', 'driver', *INPUTS, *PARAMETERS, 'params', 'remaps', 'log_level')
    config = node_configuration({n: LaunchConfiguration(n).perform(context) for n in names})
    return [Node(package=PACKAGE, executable=EXECUTABLE, name=PACKAGE, namespace=config['namespace'],
                 parameters=config['parameters'], remappings=config['remappings'],
                 ros_arguments=config['ros_arguments'], output='screen', emulate_tty=True)]


def generate_launch_description():
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, OpaqueFunction

    args = [
        DeclareLaunchArgument('namespace', default_value='', description='namespace of the node and its topics'),
        DeclareLaunchArgument('params_file', default_value='',
                              description='parameters file (empty: the installed config/dpv_sensor.yaml)'),
        DeclareLaunchArgument('driver', default_value='none', choices=sorted(DRIVERS),
                              description='input topics of a camera driver started with its defaults'),
        DeclareLaunchArgument('image', default_value='', description='image topic (overrides the driver)'),
        DeclareLaunchArgument('camera_info', default_value='',
                              description="camera_info topic (default: the image topic's sibling)"),
        DeclareLaunchArgument('odom', default_value='', description='odometry topic (overrides the driver)'),
    ] + [DeclareLaunchArgument(name, default_value='', description=f'node parameter {name} (empty: the params '
                               "file's)") for name in PARAMETERS] + [
        DeclareLaunchArgument('params', default_value='', description="further parameters: 'name:=value ...'"),
        DeclareLaunchArgument('remaps', default_value='', description="further remappings: 'from:=to from:=to'"),
        DeclareLaunchArgument('log_level', default_value='info', description='debug, info, warn or error'),
    ]
    return LaunchDescription(args + [OpaqueFunction(function=_node_actions)])
