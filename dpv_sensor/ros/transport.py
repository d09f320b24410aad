"""The node's own DDS transport settings, applied before rclpy starts (no rclpy import here).

With the Fast DDS defaults (shared memory with a 512 KiB segment + UDPv4 with the system's 208 KiB socket buffers)
a 640x480 rgb8 image (921 KB) does not fit the shared-memory segment and arrives over UDP as ~15 fragments that
overflow the receive buffer: a best-effort reader loses most images and the small messages sent next to them
(camera_info, odometry), a reliable one gets them late. The node therefore runs on UDPv4 alone with 4 MiB socket
buffers (``config/fastdds.xml``); a camera driver with default settings then sends to it over UDP, and everything
arrives (figures and the experiment: ``python -m dpv_sensor.benchmarks.transport``; docs/transport.md).

:func:`configure` points ``FASTRTPS_DEFAULT_PROFILES_FILE`` at that profile in the process environment, unless the
user chose a transport (a profiles file or ``FASTDDS_BUILTIN_TRANSPORTS``) or another RMW. With the localhost
discovery range (``ROS_LOCALHOST_ONLY=1`` or ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) rmw_fastrtps adds its own
default transports to any profile, so the node instead uses ``config/fastdds_localhost.xml`` (the same transport,
discovery by unicast on 127.0.0.1 only) and clears that range in its own environment.
"""
from __future__ import annotations

import os
import pathlib
import sys
from typing import MutableMapping

PACKAGE = 'dpv_sensor'
PROFILE = 'fastdds.xml'
PROFILE_LOCALHOST = 'fastdds_localhost.xml'
PROFILE_VAR = 'FASTRTPS_DEFAULT_PROFILES_FILE'
# any of these set by the user: their transport choice stands
USER_VARS = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE', 'FASTDDS_BUILTIN_TRANSPORTS')


def config_dirs() -> list[pathlib.Path]:
    """Where the profiles may be: the source tree's config/, then the installed share/dpv_sensor/config."""
    dirs = [pathlib.Path(__file__).resolve().parents[2] / 'config']
    try:
        from ament_index_python.packages import get_package_share_directory
        dirs.append(pathlib.Path(get_package_share_directory(PACKAGE)) / 'config')
    except Exception:   # not installed with colcon, or ament_index_python absent
        pass
    dirs.append(pathlib.Path(sys.prefix) / 'share' / PACKAGE / 'config')
    return dirs


def find_profile(name: str) -> pathlib.Path | None:
    for d in config_dirs():
        if (d / name).is_file():
            return d / name
    return None


def localhost_range(env: MutableMapping[str, str]) -> bool:
    """True when rcl will use the localhost discovery range (ROS_LOCALHOST_ONLY=1 wins over the range variable)."""
    return env.get('ROS_LOCALHOST_ONLY', '') == '1' or env.get('ROS_AUTOMATIC_DISCOVERY_RANGE', '') == 'LOCALHOST'


def configure(environ: MutableMapping[str, str] | None = None) -> str:
    """Apply the node's transport settings to `environ` (default: this process's environment, before rclpy is
    initialised); returns one line for the log saying what was done and why."""
    env = os.environ if environ is None else environ
    rmw = env.get('RMW_IMPLEMENTATION', '')
    if rmw and not rmw.startswith('rmw_fastrtps'):
        return f'transport: {rmw} with its own settings (the Fast DDS profile applies to rmw_fastrtps only)'
    chosen = [f'{v}={env[v]}' for v in USER_VARS if env.get(v)]
    if chosen:
        return f"transport: the user's settings ({', '.join(chosen)})"
    localhost = localhost_range(env)
    path = find_profile(PROFILE_LOCALHOST if localhost else PROFILE)
    if path is None:
        return f'transport: Fast DDS defaults (config/{PROFILE} not found; large images may be lost)'
    env[PROFILE_VAR] = str(path)
    note = f'transport: UDPv4 with 4 MiB socket buffers ({path})'
    if localhost:
        env.pop('ROS_LOCALHOST_ONLY', None)
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SUBNET'   # the profile restricts discovery to 127.0.0.1 itself
        note += ', discovery on 127.0.0.1 only'
    return note


def choose_reliability(setting: str, offered: list[str]) -> str:
    """Reliability of an input subscription: `setting` ('best_effort' / 'reliable') as it is, or for 'auto' from
    the reliabilities the topic's publishers offer: 'reliable' when there is at least one publisher and every one
    offers reliable (lost samples are then repaired), else 'best_effort', which matches best-effort and reliable
    publishers alike (a reliable subscription never matches a best-effort publisher)."""
    if setting != 'auto':
        return setting
    return 'reliable' if offered and all(o == 'reliable' for o in offered) else 'best_effort'
