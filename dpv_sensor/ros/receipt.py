"""What the node decides about an input message on receipt, in the subscription callback, before the newest-wins
mailbox (no rclpy): images lost in transport or a discontinuity in the stamps (stream_loss), an image that cannot be
used (unsupported encoding, size, step and data disagreeing: checked without touching the pixels, so a bad image
is counted and logged even when the worker is busy and the image would have been replaced unseen; a compressed image
arrives decoded, ``compressed_image.DecodedImage``, or as one that could not be decoded), and a change of the
odometry's frame_id."""
from __future__ import annotations

from dpv_sensor.ros import msgs as M
from dpv_sensor.ros.compressed_image import UNDECODABLE_IMAGE, DecodedImage
from dpv_sensor.ros.node_support import Incoming, merge_incoming
from dpv_sensor.ros.stream_loss import StreamLoss

NS = 1_000_000_000
UNSUPPORTED_ENCODING = 'unsupported_encoding'
BAD_IMAGE = 'bad_image'
STAMP_JUMP = 'stamp_jump'
ODOM_FRAME_CHANGE = 'odometry_frame_change'


class ImageReceipt:
    """The image callback's checks. faults: node_support.FaultLog; drop(reason): counts a dropped image."""

    def __init__(self, faults, drop, stream_loss: StreamLoss | None = None):
        self.faults = faults
        self.drop = drop
        self.stream_loss = stream_loss or StreamLoss()
        self._carry: Incoming | None = None     # what a rejected image knew about the stream, for the next one

    def image(self, msg, stamp_ns: int | None, gap_ns: int | None, receipt_mono: float,
              receipt_ns: int) -> Incoming | None:
        """The Incoming to hand to the worker, or None when the image is rejected (counted and logged here)."""
        loss = self.stream_loss
        jumps, changes = loss.stamp_jumps, loss.rate_changes
        # images missing before this one (lost in transport): counted; a gap the middleware reported as lost is
        # judged by the worker (camera_gap_ns), as the report may come after this image
        lost = loss.on_image(stamp_ns) if stamp_ns is not None else None
        if loss.stamp_jumps != jumps:
            self.faults.report(STAMP_JUMP, f'image stamps jumped {loss.last_jump_ns / NS:.3f} s forward at '
                               f'{stamp_ns / NS:.3f} s: a discontinuity (camera stalled, or its clock or /clock '
                               'jumped), not counted as lost images; a gap over reset_time_gap restarts the filter')
        if loss.rate_changes != changes:
            self.faults.report('input_rate_change', f'the camera changed its frame rate: period now '
                               f'{loss.period_ns / 1e6:.1f} ms (input_rate_changes counts them; no image was lost)',
                               level='info', count=False, period_s=60.0)
        item = Incoming(msg, receipt_mono, receipt_ns, None if lost else gap_ns, [lost] if lost else [])
        if self._carry is not None:
            item = merge_incoming(self._carry, item)
        if isinstance(msg, DecodedImage) and msg.error is not None:
            return self._reject(item, UNDECODABLE_IMAGE, msg.error, stamp_ns)
        try:
            M.check_colour_image(msg)
        except M.UnsupportedEncoding as exc:
            return self._reject(item, UNSUPPORTED_ENCODING, exc, stamp_ns)
        except M.BadImage as exc:
            return self._reject(item, BAD_IMAGE, exc, stamp_ns)
        self._carry = None
        return item

    def _reject(self, item: Incoming, kind: str, exc: Exception, stamp_ns: int | None) -> None:
        self._carry = item
        self.drop(kind)
        at = f'{stamp_ns / NS:.3f} s' if stamp_ns is not None else 'an unreadable stamp'
        what = f"compressed image (format '{item.msg.format}')" if isinstance(item.msg, DecodedImage) else 'image'
        self.faults.report(kind, f'dropping {what} at {at}: {exc}')
        return None


class OdomFrameWatch:
    """The odometry's header.frame_id: a change (odom -> map, with or without a jump) is logged and counted."""

    def __init__(self, faults, default: str = 'odom'):
        self.faults = faults
        self.frame = default
        self._seen = False

    def update(self, frame_id: str, stamp_ns: int) -> str:
        """The odometry frame after a message with `frame_id` (an empty one keeps the current frame)."""
        if not frame_id:
            return self.frame
        if self._seen and frame_id != self.frame:
            self.faults.report(ODOM_FRAME_CHANGE, f"odometry frame_id changed from '{self.frame}' to '{frame_id}' at "
                               f'{stamp_ns / NS:.3f} s: poses and the pose output are in the new frame from now on '
                               '(a teleport between the two restarts the filter; two odometry sources on one topic?)',
                               key=f'{ODOM_FRAME_CHANGE}:{self.frame}->{frame_id}')
        self.frame, self._seen = frame_id, True
        return frame_id
