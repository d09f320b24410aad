"""Records read back from recorded outputs: a rosbag2 of the node's ``depth/image`` (+ ``confidence/image``,
``depth/camera_info``) read with :mod:`dpv_sensor.data.rosbag_io`, or a folder written by
``bag_export.export_depth_bag``; each depth image is matched to the GT sequence frame with the same stamp.
"""
from __future__ import annotations

import pathlib
from typing import Any, Dict, List, Optional, Tuple, Union

import cv2
import numpy as np

from dpv_sensor.evaluation.runner import KeyframeRecord, load_sequence, resize_image, resize_nearest

__all__ = ['first_image_stamp', 'gt_stamp_offset', 'records_from_bag', 'records_from_export']

def _match(stamp: float, gt_stamps: np.ndarray, tolerance: float) -> Optional[int]:
    j = int(np.argmin(np.abs(gt_stamps - stamp)))
    return j if abs(gt_stamps[j] - stamp) <= tolerance else None


def _records_from_arrays(items, gt, *, tolerance: float, stamp_offset: float,
                         keep_images: bool = True) -> Tuple[List[KeyframeRecord], Dict[str, Any]]:
    """items: iterable of (stamp s, depth_hw, confidence_hw | None, K_33 | None)."""
    gt = load_sequence(gt)
    gt_stamps = np.array([gt.stamp(i) for i in range(len(gt))], np.float64)
    records, unmatched = [], 0
    K_gt = np.asarray(gt.K, np.float64)
    for stamp, depth, conf, K in items:
        j = _match(stamp - stamp_offset, gt_stamps, tolerance)
        if j is None:
            unmatched += 1
            continue
        depth = np.asarray(depth, np.float32)
        hw = depth.shape
        if K is None:
            from dpv_sensor.data.sequence import scale_intrinsics_np
            h0, w0 = np.asarray(gt.depth(j)).shape
            K = scale_intrinsics_np(K_gt, hw[1] / w0, hw[0] / h0)
        records.append(KeyframeRecord(
            index=j, stamp=float(stamp), depth_hw=depth, confidence_hw=conf, K_33=np.asarray(K, np.float64),
            gt_depth_hw=resize_nearest(np.asarray(gt.depth(j), np.float32), hw),
            gt_T_world_cam_44=np.asarray(gt.pose(j)),
            image_hw3=resize_image(gt.image(j), hw) if keep_images else None))
    return records, {'matched': len(records), 'unmatched': unmatched, 'stamp_offset_s': stamp_offset}


def first_image_stamp(bag, topic: str) -> float:
    """Header stamp (s) of the first message on `topic` of a rosbag2."""
    from dpv_sensor.ros import msgs as MS
    from dpv_sensor.data import rosbag_io as R
    messages = R.read_messages(bag, [topic])
    try:
        first = next(messages)[3]
    except StopIteration:
        raise R.BagError(f'{bag}: no message on {topic}') from None
    finally:
        messages.close()            # closes the bag reader
    return MS.stamp_to_ns(first.header.stamp) / R.NS


def gt_stamp_offset(first_stamp_s: float, gt_seq, tolerance: float = 1e-3) -> float:
    """The offset (s) to subtract from bag stamps to get GT stamps, from the bag's first camera image: 0 when that
    stamp is one of the GT frames' own stamps (stamps.txt in the bag's clock), else the bag's first image is GT
    frame 0 (a folder without stamps.txt counts from 0 at 30 Hz; a bag written from it may start at any epoch)."""
    stamps = np.array([float(gt_seq.stamp(i)) for i in range(len(gt_seq))])
    if stamps.size and float(np.min(np.abs(stamps - first_stamp_s))) <= tolerance:
        return 0.0
    return first_stamp_s - float(gt_seq.stamp(0))


def records_from_bag(bag, gt, *, depth_topic: Optional[str] = None, confidence_topic: Optional[str] = None,
                     info_topic: Optional[str] = None, image_topic: Optional[str] = None,
                     stamp_offset: Union[float, str] = 'auto',
                     tolerance: float = 1e-3) -> Tuple[List[KeyframeRecord], Dict[str, Any]]:
    """Depth outputs recorded in a bag, matched by header stamp to the frames of the GT sequence ``gt``.

    Topics default to ``/depth/image``, ``/confidence/image``, ``/depth/camera_info`` (or the only topic of
    that type ending the same way, for a namespaced node). ``stamp_offset`` (s) is subtracted from the bag
    stamps before matching; ``'auto'``: when the bag also holds the camera images, the first image stamp is
    taken to be GT frame 0 (a bag written by ``bag`` / ``write_sequence_bag`` from the sequence), else 0. The camera
    image topic is ``image_topic``, or the only sensor_msgs/Image topic besides the node's outputs, else the only
    image_transport compressed CompressedImage topic (``topic_detection.detect_image_topic``; several: BagError listing
    them).
    A depth image matches a GT frame within ``tolerance`` seconds; unmatched ones are counted and skipped.
    Returns (records, info).
    """
    from dpv_sensor.data import rosbag_io as R
    from dpv_sensor.data.topic_detection import detect_image_topic, find_topic
    topics = R.bag_topics(bag)
    d_topic = find_topic(topics, depth_topic or R.DEPTH_TOPIC, 'depth/image', R.IMAGE)
    if d_topic is None:
        raise R.BagError(f'{bag}: no depth topic (topics: {sorted(topics)})')
    c_topic = find_topic(topics, confidence_topic or R.CONFIDENCE_TOPIC, 'confidence/image', R.IMAGE)
    i_topic = find_topic(topics, info_topic or R.DEPTH_INFO_TOPIC, 'depth/camera_info', R.CAMERA_INFO)
    depth = R.read_depth_images(bag, d_topic)
    conf = {s.stamp_ns: s.data for s in R.read_depth_images(bag, c_topic)} if c_topic else {}
    infos = {s.stamp_ns: s.data for s in R.read_camera_infos(bag, i_topic)} if i_topic else {}
    if stamp_offset == 'auto':
        gt_seq = load_sequence(gt)
        img_topic, img_how = detect_image_topic(topics, 'camera image', wanted=image_topic,
                                                  option='--image-topic, or --stamp-offset', exclude=(d_topic, c_topic),
                                                  required=False)
        offset = 0.0
        if img_topic is not None:
            offset = gt_stamp_offset(first_image_stamp(bag, img_topic), gt_seq, tolerance)
        gt = gt_seq
    else:
        offset = float(stamp_offset)
        img_topic, img_how = None, 'not needed (stamp offset given)'
    items = ((s.stamp_ns / R.NS, s.data, conf.get(s.stamp_ns), infos.get(s.stamp_ns)) for s in depth)
    records, info = _records_from_arrays(items, gt, tolerance=tolerance, stamp_offset=offset)
    info.update({'bag': str(bag), 'depth_topic': d_topic, 'confidence_topic': c_topic, 'info_topic': i_topic,
                 'image_topic': img_topic, 'image_topic_chosen_by': img_how, 'stamp_offset': offset,
                 'depth_messages': len(depth)})
    return records, info


def records_from_export(folder, gt, *, stamp_offset: float = 0.0, tolerance: float = 1e-3
                        ) -> Tuple[List[KeyframeRecord], Dict[str, Any]]:
    """A folder written by ``bag_export.export_depth_bag`` (depth/*.png mm, confidence/*.png uint16 scaled by
    65535, stamps_ns.txt or stamps.txt, K.txt) matched by stamp to the GT sequence ``gt``."""
    from dpv_sensor.data.sequence import read_intrinsics
    folder = pathlib.Path(folder)
    files = sorted((folder / 'depth').glob('*.png'))
    if not files:
        raise FileNotFoundError(f'{folder}/depth has no PNG files')
    if (folder / 'stamps_ns.txt').is_file():
        stamps = [int(x) / 1e9 for x in (folder / 'stamps_ns.txt').read_text().split()]
    else:
        stamps = [float(x) for x in (folder / 'stamps.txt').read_text().split()]
    if len(stamps) != len(files):
        raise ValueError(f'{folder}: {len(files)} depth images but {len(stamps)} stamps')
    K = read_intrinsics(folder / 'K.txt') if (folder / 'K.txt').is_file() else None

    def items():
        for f, s in zip(files, stamps):
            raw = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            d = raw.astype(np.float32) / 1000.0
            d[raw == 0] = np.nan
            cf = folder / 'confidence' / f.name
            c = None
            if cf.is_file():
                c = cv2.imread(str(cf), cv2.IMREAD_UNCHANGED).astype(np.float32) / 65535.0
            yield s, d, c, K
    records, info = _records_from_arrays(items(), gt, tolerance=tolerance, stamp_offset=stamp_offset)
    info['folder'] = str(folder)
    return records, info

