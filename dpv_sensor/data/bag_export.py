"""A recorded bag of the node's outputs exported to files, read with ``rosbag_io``.

- `export_depth_bag`: a recorded depth/confidence bag -> a sequence-folder-like directory (depth PNG mm,
  confidence PNG, K.txt, stamps.txt, images and poses when the bag has them; the colour image and odometry topics
  found by ``topic_detection``), with a summary written as export.json.
- `export_topics_line`: which bag topics an export read, in one line for the user.
"""
from __future__ import annotations

import json
import pathlib
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from dpv_sensor import params as P
from dpv_sensor.data.rosbag_io import (CAMERA_INFO, CONFIDENCE_TOPIC, DEPTH_INFO_TOPIC, DEPTH_TOPIC, IMAGE, NS,
                                       ODOMETRY, BagError, Stamped, as_T_base_camera, bag_topics, read_camera_infos,
                                       read_depth_images, read_images, read_odometry, read_poses)
from dpv_sensor.data.topic_detection import detect_image_topic, detect_topic, find_topic
from dpv_sensor.stream.pose_buffer import PoseBuffer


@dataclass
class _ExportTopics:
    """The topics an export reads (None: not in the bag / not wanted) and how the image and odometry topics were
    chosen."""
    depth: str
    confidence: str | None
    camera_info: str | None
    image: str | None
    odom: str | None
    how: dict


@dataclass
class _ExportInputs:
    """What an export reads from the bag: the depth images in order, and by header stamp the confidence images,
    depth camera infos and colour images; poses by stamp (a pose topic) or a PoseBuffer (odometry), or None."""
    depth: list
    confidence: dict
    camera_infos: dict
    images: dict
    poses: dict | PoseBuffer | None


@dataclass
class _ExportFrames:
    """What the frame loop of an export collects for the files written after it."""
    K_33: np.ndarray | None = None
    stamps_ns: list = field(default_factory=list)
    poses: list = field(default_factory=list)


def _export_topics(path, topics: dict, depth_topic: str, confidence_topic: str, info_topic: str,
                   image_topic: str | None, odom_topic: str | None) -> _ExportTopics:
    """The export's topics: the node's outputs by name or namespaced suffix, the colour image and odometry by
    ``detect_topic`` ('auto'), a name, or None."""
    depth_topic_found = find_topic(topics, depth_topic, 'depth/image', IMAGE)
    if depth_topic_found is None:
        raise BagError(f'{path}: no depth topic {depth_topic!r} (topics: {sorted(topics)})')
    conf_topic = find_topic(topics, confidence_topic, 'confidence/image', IMAGE)
    info_t = find_topic(topics, info_topic, 'depth/camera_info', CAMERA_INFO)
    how = {}
    if image_topic is not None:
        image_topic, how['image'] = detect_image_topic(
            topics, 'colour image', wanted=None if image_topic == 'auto' else image_topic,
            option='--image-topic', exclude=(depth_topic_found, conf_topic), required=False)
    if odom_topic is not None:
        odom_topic, how['odom'] = detect_topic(topics, 'odometry', ODOMETRY,
                                               wanted=None if odom_topic == 'auto' else odom_topic,
                                               option='--odom-topic', required=False)
    return _ExportTopics(depth=depth_topic_found, confidence=conf_topic, camera_info=info_t, image=image_topic,
                         odom=odom_topic, how=how)


def _export_pose_source(path, topics: dict, pose_topic: str | None, odom_topic: str | None, T_base_camera,
                        max_odom_gap: float) -> dict | PoseBuffer | None:
    """T_world_cam by stamp from `pose_topic`, else a PoseBuffer of the odometry (NaN poses as gaps), else None."""
    if pose_topic and pose_topic in topics:
        return {s.stamp_ns: s.data for s in read_poses(path, pose_topic)}
    if odom_topic and odom_topic in topics:
        buf = PoseBuffer(max_gap_s=max_odom_gap, history_s=1e9, T_base_camera_44=as_T_base_camera(T_base_camera),
                         backwards_tolerance_s=1e9)
        for s in read_odometry(path, odom_topic):
            buf.add(s.stamp_ns, None if np.isnan(s.data).any() else s.data)
        return buf
    return None


def _export_inputs(path, topics: dict, chosen: _ExportTopics, pose_topic: str | None, T_base_camera,
                   max_odom_gap: float) -> _ExportInputs:
    """Read the export's messages from the bag."""
    depth = read_depth_images(path, chosen.depth)
    conf = {s.stamp_ns: s for s in read_depth_images(path, chosen.confidence)} if chosen.confidence else {}
    infos = {s.stamp_ns: s for s in read_camera_infos(path, chosen.camera_info)} if chosen.camera_info else {}
    images = {}
    if chosen.image and chosen.image in topics:
        images = {s.stamp_ns: s for s in read_images(path, chosen.image)}
    poses = _export_pose_source(path, topics, pose_topic, chosen.odom, T_base_camera, max_odom_gap)
    return _ExportInputs(depth=depth, confidence=conf, camera_infos=infos, images=images, poses=poses)


def _export_frame(out: pathlib.Path, i: int, s: Stamped, inputs: _ExportInputs, frames: _ExportFrames,
                  summary: dict) -> None:
    """Write frame i (depth, and confidence and colour image with its stamp) and collect its K, stamp and pose."""
    import cv2
    from dpv_sensor.data.sequence import depth_to_png_mm
    stem = f'{i:06d}'
    d = s.data
    cv2.imwrite(str(out / 'depth' / f'{stem}.png'), depth_to_png_mm(np.nan_to_num(d, nan=0.0)))
    c = inputs.confidence.get(s.stamp_ns)
    if c is not None:
        cu16 = np.round(np.clip(np.nan_to_num(c.data, nan=0.0), 0, 1) * 65535).astype(np.uint16)
        cv2.imwrite(str(out / 'confidence' / f'{stem}.png'), cu16)
    elif inputs.confidence:
        summary['without_confidence'] += 1
    info = inputs.camera_infos.get(s.stamp_ns)
    if info is not None:
        if frames.K_33 is None:
            frames.K_33 = info.data
        elif not np.allclose(frames.K_33, info.data):
            summary['K_changed'] = True
    im = inputs.images.get(s.stamp_ns)
    if im is not None:
        rgb = im.data
        if rgb.shape[:2] != d.shape:
            rgb = cv2.resize(rgb, (d.shape[1], d.shape[0]), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(out / 'images' / f'{stem}.png'), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    elif inputs.images:
        summary['without_image'] += 1
    if inputs.poses is not None:
        frames.poses.append(_export_pose(inputs.poses, s.stamp_ns, summary))
    frames.stamps_ns.append(s.stamp_ns)
    summary['frames'] += 1


def _export_pose(poses: dict | PoseBuffer, stamp_ns: int, summary: dict) -> np.ndarray:
    """T_world_cam at `stamp_ns` (the pose topic's message with that stamp, or interpolated odometry); NaN (counted
    in the summary) when there is none."""
    T = poses.get(stamp_ns) if isinstance(poses, dict) else poses.pose_at(stamp_ns).T_world_cam_44
    if T is None:
        summary['without_pose'] += 1
        T = np.full((4, 4), np.nan)
    return T


def _write_export_files(out: pathlib.Path, frames: _ExportFrames, summary: dict) -> None:
    """K.txt (the first frame's), stamps.txt, stamps_ns.txt, poses.txt (when every frame has a pose), export.json."""
    from dpv_sensor.data.sequence import write_intrinsics, write_poses
    if frames.K_33 is not None:
        write_intrinsics(out / 'K.txt', frames.K_33)
    with open(out / 'stamps.txt', 'w') as f:
        f.writelines(f'{repr(t / NS)}\n' for t in frames.stamps_ns)
    with open(out / 'stamps_ns.txt', 'w') as f:
        f.writelines(f'{t}\n' for t in frames.stamps_ns)
    if frames.poses and summary['without_pose'] == 0:
        write_poses(out / 'poses.txt', np.stack(frames.poses))
    with open(out / 'export.json', 'w') as f:
        json.dump(summary, f, indent=1)


def export_depth_bag(path, out_dir, *, depth_topic: str = DEPTH_TOPIC, confidence_topic: str = CONFIDENCE_TOPIC,
                     info_topic: str = DEPTH_INFO_TOPIC, image_topic: str | None = 'auto',
                     odom_topic: str | None = 'auto', pose_topic: str | None = None, T_base_camera=None,
                     max_odom_gap: float = P.default('max_odom_gap'), progress: bool = True) -> dict:
    """A recorded bag of the node's outputs -> a sequence-folder-like directory.

    Writes depth/NNNNNN.png (uint16 mm, 0 = none), confidence/NNNNNN.png (uint16, confidence * 65535),
    stamps.txt (s, the depth header stamps), stamps_ns.txt (exact), K.txt (from depth/camera_info; written for the
    first frame, with a warning in the summary when it changes), and, when the bag has them, images/NNNNNN.png (the
    colour image with the same stamp, resized to the depth size) and poses.txt (T_world_cam from `pose_topic`, or
    interpolated from odometry composed with T_base_camera). image_topic / odom_topic: 'auto' (default) = the only
    camera Image / Odometry topic when the bag has one (``detect_topic``; several: BagError listing them), a name,
    or None for none. Returns a summary dict (also written as export.json).
    """
    topics = bag_topics(path)
    chosen = _export_topics(path, topics, depth_topic, confidence_topic, info_topic, image_topic, odom_topic)
    out = pathlib.Path(out_dir)
    (out / 'depth').mkdir(parents=True, exist_ok=True)
    inputs = _export_inputs(path, topics, chosen, pose_topic, T_base_camera, max_odom_gap)
    if inputs.confidence:
        (out / 'confidence').mkdir(exist_ok=True)
    if inputs.images:
        (out / 'images').mkdir(exist_ok=True)
    summary = {'bag': str(path), 'depth_topic': chosen.depth, 'confidence_topic': chosen.confidence,
               'camera_info_topic': chosen.camera_info, 'image_topic': chosen.image, 'odom_topic': chosen.odom,
               'pose_topic': pose_topic if inputs.poses is not None and pose_topic else None, 'chosen_by': chosen.how,
               'frames': 0, 'without_confidence': 0, 'without_image': 0, 'without_pose': 0, 'K_changed': False}
    frames = _ExportFrames()
    iterator: Iterable = inputs.depth
    if progress:
        from tqdm import tqdm
        iterator = tqdm(inputs.depth, desc='exporting', unit='frame', leave=False)
    for i, s in enumerate(iterator):
        _export_frame(out, i, s, inputs, frames, summary)
    _write_export_files(out, frames, summary)
    return summary


def export_topics_line(info) -> str:
    """Which bag topics an export read (and how the camera image topic was chosen), for the user."""
    image = (f"{info['image_topic']} ({info['image_topic_chosen_by']})" if info.get('image_topic')
             else info.get('image_topic_chosen_by'))
    return (f"topics: depth {info['depth_topic']}, confidence {info['confidence_topic']}, camera_info "
            f"{info['info_topic']}, camera image {image}; stamp offset {info['stamp_offset']:.6f} s")


__all__ = ['export_depth_bag', 'export_topics_line']
