"""Topic names that follow their image topic, as image_transport names them (no ROS import).

image_transport's convention: an image topic's camera_info is its sibling (``/cam/color/image_raw`` ->
``/cam/color/camera_info``) and a transport's topic is its child (``depth/image`` -> ``depth/image/compressedDepth``,
``image`` -> ``image/compressed``).
So a remapped image topic takes its camera_info and transports with it, unless those are remapped themselves:
``-r image:=/camera/color/image_raw`` alone subscribes ``/camera/color/camera_info`` (and, with
``image_transport: compressed``, ``/camera/color/image_raw/compressed``), and ``-r depth/image:=/dpv/depth``
publishes ``/dpv/camera_info`` and ``/dpv/depth/compressedDepth``.
"""
from __future__ import annotations

from typing import Callable

# follower topic -> (image topic it follows, how: 'sibling' camera_info or 'child' transport suffix)
FOLLOWERS: dict[str, tuple[str, str]] = {
    'camera_info': ('image', 'sibling'),
    'image/compressed': ('image', 'child'),          # the input with image_transport: compressed
    'depth/camera_info': ('depth/image', 'sibling'),
    'rgb/camera_info': ('rgb/image', 'sibling'),
    'confidence/camera_info': ('confidence/image', 'sibling'),
    'depth/image/compressedDepth': ('depth/image', 'child'),
}


def camera_info_of(image_topic: str) -> str:
    """image_transport's camera_info topic of an image topic: its sibling named camera_info."""
    parent = image_topic.rstrip('/').rpartition('/')[0]
    return f'{parent}/camera_info' if parent or image_topic.startswith('/') else 'camera_info'


def topic_name(name: str, resolve: Callable[[str, bool], str]) -> str:
    """The name to create the publisher or subscription of `name` with.

    resolve(topic, only_expand) -> fully qualified name (rclpy's ``Node.resolve_topic_name``; with only_expand the
    remap rules are not applied). A follower (``FOLLOWERS``) that is not remapped itself follows its image topic's
    resolved (remapped) name; every other name is returned as it is, for the node's remap rules to apply."""
    if name not in FOLLOWERS or resolve(name, False) != resolve(name, True):
        return name
    image, how = FOLLOWERS[name]
    image_topic = resolve(image, False)
    if image_topic == resolve(image, True):        # the image is not remapped either: the plain relative name
        return name
    if how == 'sibling':
        return camera_info_of(image_topic)
    return f"{image_topic}/{name.rpartition('/')[2]}"
