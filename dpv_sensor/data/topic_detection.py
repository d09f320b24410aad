"""Which topic of a rosbag2 is which, by message type: the camera image, camera_info and odometry the node reads
(names needed only to choose among several), shared by the demo, `bag`, `fuse` and `evaluate`.

- `detect_input_topics`: the node's input topics of a bag (``rosbag_io.bag_topics`` output or a path), with how
  each was chosen (`describe_choice` says it in one line).
- `detect_topic`: one role's topic by message type (a name the user gave checked; among several, the one next to
  the image; else a BagError listing the candidates and the setting that chooses).
- `detect_image_topic`: the camera image, a sensor_msgs/Image or an image_transport compressed CompressedImage topic
  (raw preferred when a bag holds both: lossless and nothing to decode), replayed to the node with
  ``image_transport: compressed`` (`image_transport_of`, `image_topic_line`, `image_base_topic`).
- `find_topic`: one of the node's output topics by its name or its namespaced ending.
"""
from __future__ import annotations

from typing import Iterable

from dpv_sensor.data.rosbag_io import (CAMERA_INFO, COMPRESSED_IMAGE, COMPRESSED_SUFFIX, IMAGE, ODOMETRY, BagError,
                                       bag_topics, read_messages)

#: The node's inputs: role -> message type.
INPUT_TYPES = {'image': IMAGE, 'camera_info': CAMERA_INFO, 'odom': ODOMETRY}
#: Image topics the node itself publishes (never a camera input; matched as name endings).
OUTPUT_IMAGE_SUFFIXES = ('depth/image', 'confidence/image', 'rgb/image')
#: CompressedImage topics that are never a camera's colour input: depth (compressedDepth) and the node's outputs.
NOT_COLOUR_COMPRESSED_SUFFIXES = ('compressedDepth',) + tuple(f'{s}{COMPRESSED_SUFFIX}' for s in OUTPUT_IMAGE_SUFFIXES)


def _not_an_input(topic: str, msgtype: str) -> bool:
    """A topic of the camera image's types that is no camera input (a node output, compressed depth)."""
    if msgtype == IMAGE:
        return topic.endswith(OUTPUT_IMAGE_SUFFIXES)
    return msgtype == COMPRESSED_IMAGE and topic.endswith(NOT_COLOUR_COMPRESSED_SUFFIXES)


def _namespace(topic: str) -> str:
    return topic.rsplit('/', 1)[0]


def _listing(topics: dict, names) -> str:
    return ', '.join(f'{t} [{topics[t][0]}, {topics[t][1]} messages]' for t in sorted(names)) or 'none'


def detect_topic(topics: dict, role: str, msgtype: str, *, wanted: str | None = None, option: str = '',
                 exclude: Iterable[str] = (), near: str | None = None, required: bool = True
                 ) -> tuple[str | None, str]:
    """Choose the bag topic for one input ``role`` by message type; returns (topic, how it was chosen).

    topics: ``bag_topics()`` output. ``wanted``: a name the user gave - used when the bag has it with type
    ``msgtype``, else BagError. Without one: the only topic of ``msgtype`` (topics in ``exclude`` and node outputs
    ending in ``OUTPUT_IMAGE_SUFFIXES`` left out); among several, the only one in the namespace of ``near`` (a
    camera_info next to its image, as image_transport names them); else BagError listing the candidates and
    naming ``option``, the setting that chooses. None topics: (None, 'absent') when not ``required``, else BagError.
    """
    hint = f'; choose with {option}' if option else ''
    if wanted:
        if wanted not in topics:
            of_type = [t for t, (ty, _n) in topics.items() if ty == msgtype]
            raise BagError(f'no topic {wanted!r} for {role} in the bag; {msgtype} topics: {_listing(topics, of_type)}'
                           f' (all topics: {_listing(topics, topics)})')
        if topics[wanted][0] != msgtype:
            raise BagError(f'{wanted} carries {topics[wanted][0]}, {role} needs {msgtype}')
        return wanted, 'named'
    skip = set(exclude)
    cands = sorted(t for t, (ty, _n) in topics.items() if ty == msgtype and t not in skip and not _not_an_input(t, ty))
    if len(cands) == 1:
        return cands[0], f'the only {msgtype} topic'
    if not cands:
        if not required:
            return None, 'absent'
        raise BagError(f'no {msgtype} topic for {role} in the bag{hint} (topics: {_listing(topics, topics)})')
    if near is not None:
        close = [t for t in cands if _namespace(t) == _namespace(near)]
        if len(close) == 1:
            return close[0], f'the only {msgtype} topic next to {near}'
    raise BagError(f'{len(cands)} {msgtype} topics could be the {role}: {_listing(topics, cands)}{hint}')


def detect_image_topic(topics: dict, role: str = 'image', *, wanted: str | None = None, option: str = '',
                       exclude: Iterable[str] = (), required: bool = True) -> tuple[str | None, str]:
    """The camera image topic (``detect_topic`` for a colour image): a sensor_msgs/Image topic, or an image_transport
    compressed sensor_msgs/CompressedImage one (compressedDepth and the node's outputs left out). ``wanted``: a name
    of either type. Without one, a raw Image topic wins over compressed ones (lossless, nothing to decode; the
    reason says so); a CompressedImage topic is taken when the bag has no raw one."""
    if wanted:
        msgtype = COMPRESSED_IMAGE if topics.get(wanted, ('',))[0] == COMPRESSED_IMAGE else IMAGE
        return detect_topic(topics, role, msgtype, wanted=wanted, option=option)
    skip = set(exclude)
    compressed = [t for t, (ty, _n) in topics.items()
                  if ty == COMPRESSED_IMAGE and t not in skip and not _not_an_input(t, ty)]
    topic, how = detect_topic(topics, role, IMAGE, option=option, exclude=exclude, required=False)
    if topic is not None:
        return topic, how + (f' (preferred to {len(compressed)} {COMPRESSED_IMAGE} topic(s): raw is lossless)'
                             if compressed else '')
    if not compressed and not required:
        return None, 'absent'
    if not compressed:
        hint = f'; choose with {option}' if option else ''
        raise BagError(f'no {IMAGE} or {COMPRESSED_IMAGE} topic for {role} in the bag{hint} '
                       f'(topics: {_listing(topics, topics)})')
    return detect_topic(topics, role, COMPRESSED_IMAGE, option=option, exclude=exclude, required=required)


def image_transport_of(topics: dict, topic: str) -> str:
    """The node's image_transport for a bag's camera image topic: 'compressed' for CompressedImage, else 'raw'."""
    return 'compressed' if topics.get(topic, ('',))[0] == COMPRESSED_IMAGE else 'raw'


def image_topic_line(path, topics: dict, topic: str) -> str:
    """One line for the user: which image topic a tool reads and how the node is fed it, e.g. 'image topic:
    /cam/image_raw/compressed (sensor_msgs/CompressedImage, JPEG 'rgb8; jpeg compressed bgr8') -> node
    image_transport=compressed'."""
    msgtype = topics[topic][0]
    transport = image_transport_of(topics, topic)
    what = msgtype.replace('/msg/', '/')
    if transport == 'compressed':
        messages = read_messages(path, [topic])
        try:
            fmt = str(next(messages)[3].format)
        except StopIteration:
            fmt = ''
        finally:
            messages.close()            # closes the bag reader
        codec = 'PNG' if 'png' in fmt.lower() else 'JPEG' if 'jp' in fmt.lower() else 'unknown codec'
        what += f", {codec} '{fmt}'"
    return f'image topic: {topic} ({what}) -> node image_transport={transport}'


def detect_input_topics(path_or_topics, *, image: str | None = None, camera_info: str | None = None,
                        odom: str | None = None, need: Iterable[str] = ('image', 'camera_info', 'odom'),
                        options: dict | None = None) -> tuple[dict, dict]:
    """The node's input topics in a bag (a path or ``bag_topics()`` output), found by message type.

    image / camera_info / odom: names given by the user (checked; needed only to choose among several topics of
    one type). need: the roles that must be found (others: found when present, else None); options: role -> the
    setting that names it, quoted in errors. Returns ({role: topic or None}, {role: how it was chosen}).
    The camera_info next to the chosen image wins among several.
    """
    topics = path_or_topics if isinstance(path_or_topics, dict) else bag_topics(path_or_topics)
    given = {'image': image, 'camera_info': camera_info, 'odom': odom}
    options = options or {}
    need = set(need)
    chosen: dict = {}
    how: dict = {}
    for role, msgtype in INPUT_TYPES.items():
        try:
            if role == 'image':
                chosen[role], how[role] = detect_image_topic(topics, role, wanted=given[role],
                                                             option=options.get(role, ''), required=role in need)
                continue
            chosen[role], how[role] = detect_topic(
                topics, role, msgtype, wanted=given[role], option=options.get(role, ''),
                near=image_base_topic(topics, chosen.get('image')) if role == 'camera_info' else None,
                required=role in need)
        except BagError:
            if role in need or given[role]:
                raise
            chosen[role], how[role] = None, 'several, none needed'
    return chosen, how


def image_base_topic(topics: dict, topic: str | None) -> str | None:
    """The image topic a transport topic belongs to (``/cam/image_raw/compressed`` -> ``/cam/image_raw``), where its
    camera_info is the sibling; a raw image topic itself."""
    if topic and image_transport_of(topics, topic) == 'compressed' and topic.endswith(COMPRESSED_SUFFIX):
        return topic[:-len(COMPRESSED_SUFFIX)]
    return topic


def describe_choice(chosen: dict, how: dict) -> str:
    """One line: 'image /a (the only sensor_msgs/msg/Image topic), camera_info /b (named), ...'."""
    return ', '.join(f'{role} {t} ({how[role]})' for role, t in chosen.items() if t is not None)


def find_topic(topics: dict, wanted: str, suffix: str, msgtype: str) -> str | None:
    """`wanted` when the bag has it, else the only topic of `msgtype` ending in `suffix` (a namespaced node)."""
    if wanted in topics:
        return wanted
    cands = [t for t, (ty, _n) in topics.items() if ty == msgtype and t.endswith(suffix)]
    return cands[0] if len(cands) == 1 else None


__all__ = ['detect_input_topics', 'detect_topic', 'detect_image_topic', 'image_transport_of', 'image_topic_line',
           'image_base_topic', 'describe_choice', 'find_topic', 'INPUT_TYPES', 'OUTPUT_IMAGE_SUFFIXES',
           'NOT_COLOUR_COMPRESSED_SUFFIXES']
