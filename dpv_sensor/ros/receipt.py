"""What the node decides about an input message on receipt, in the subscription callback, before the newest-wins
mailbox (no rclpy): an image of a second camera on the image topic (another frame_id: dropped, never fused with the
first camera's odometry), images lost in transport or a discontinuity in the stamps (stream_loss, from the stamps
and the publication sequence numbers the callback passes in), an image that cannot be used (unsupported encoding,
size, step and data disagreeing: checked without touching the pixels, so a bad image is counted and logged even
when the worker is busy and the image would have been replaced unseen; a compressed image arrives decoded,
``compressed_image.DecodedImage``, or as one that could not be decoded, or undecoded with the decoder to call), an
image's size, and a change of the odometry's frame_id.

The size: an image smaller than the estimator takes (``stream.frame.image_too_small``) is refused
(dropped.image_too_small, faults.image_too_small), and one of another size than the stream's is a stray until the
new size persists (``stream.continuity.StreamSize``, ``size_change_images`` images in a row): dropped and counted
(dropped.stray_image_size, faults.stray_image_size), so it never reaches the worker and never restarts the filter.
A compressed image's size is read from its header (``compressed_image.compressed_size``): one refused for its size
is never decoded (a 4000x3000 JPEG among 640x480 ones costs no 90 ms decode).

The camera's frame_id: the stream belongs to the first non-empty frame_id that arrives. An image of another frame_id
is a second camera publishing on the same topic: it is dropped and counted (dropped.other_camera,
faults.other_camera) with a warning naming both frames, as long as the stream's own frame keeps coming. When the
stream's frame has not arrived for `FRAME_SWITCH_S` seconds (of receipt time) while another one does, the camera
changed its frame_id for good (a driver restarted with another name, a remapping changed): the stream follows the
new frame from then on (faults.camera_frame_change, one warning). Images with an empty frame_id belong to the stream
(the outputs use the frame_id parameter for them)."""
from __future__ import annotations

from dpv_sensor import params as P
from dpv_sensor.ros import msgs as M
from dpv_sensor.ros.compressed_image import UNDECODABLE_IMAGE, DecodedImage, UndecodableImage, compressed_size
from dpv_sensor.ros.fault_kinds import IMAGE_TOO_SMALL, STRAY_IMAGE_SIZE
from dpv_sensor.ros.node_support import Incoming, merge_incoming
from dpv_sensor.ros.stream_loss import StreamLoss
from dpv_sensor.stream.continuity import StreamSize
from dpv_sensor.stream.frame import image_too_small

NS = 1_000_000_000
UNSUPPORTED_ENCODING = 'unsupported_encoding'
BAD_IMAGE = 'bad_image'
STAMP_JUMP = 'stamp_jump'
ODOM_FRAME_CHANGE = 'odometry_frame_change'
OTHER_CAMERA = 'other_camera'                 # an image of a second frame_id on the image topic (dropped)
CAMERA_FRAME_CHANGE = 'camera_frame_change'   # the stream's frame_id changed for good
SEQUENCE_RESTART = 'image_sequence_restart'   # the image publisher's sequence numbers went back
TWO_PUBLISHERS = 'image_two_publishers'       # ... again and again: two publishers of one frame_id
TWO_PUBLISHERS_RESTARTS = 3     # sequence numbers going back this often within TWO_PUBLISHERS_S: two publishers
TWO_PUBLISHERS_S = 10.0
FRAME_SWITCH_S = 2.0    # the stream follows another frame_id once its own has not arrived for this long


class CameraFrame:
    """The image stream's frame_id and the images of other frame_ids (see the module docs). faults:
    node_support.FaultLog; drop(reason): counts a dropped image."""

    def __init__(self, faults, drop, switch_after_s: float = FRAME_SWITCH_S):
        self.faults = faults
        self.drop = drop
        self.switch_after_s = switch_after_s
        self.frame_id = ''                 # the stream's frame ('' until the first image with one)
        self._last_mono = None             # receipt time of the stream's latest image

    def accept(self, frame_id: str, stamp_ns: int | None, receipt_mono: float) -> bool:
        """True when an image of `frame_id` belongs to the stream; False: dropped, counted and logged here."""
        if not frame_id or frame_id == self.frame_id or not self.frame_id:
            if frame_id and not self.frame_id:
                self.frame_id = frame_id
            self._last_mono = receipt_mono
            return True
        at = f'{stamp_ns / NS:.3f} s' if stamp_ns is not None else 'an unreadable stamp'
        if self._last_mono is not None and receipt_mono - self._last_mono > self.switch_after_s:
            self.faults.report(CAMERA_FRAME_CHANGE, f"image frame_id changed from '{self.frame_id}' to '{frame_id}' "
                               f"at {at}: no '{self.frame_id}' image for {receipt_mono - self._last_mono:.1f} s, the "
                               f"stream follows '{frame_id}' from now on", key=f'{CAMERA_FRAME_CHANGE}:{frame_id}')
            self.frame_id, self._last_mono = frame_id, receipt_mono
            return True
        self.drop(OTHER_CAMERA)
        self.faults.report(OTHER_CAMERA, f"two cameras publish on one image topic: dropping the image of frame_id "
                           f"'{frame_id}' at {at}, the stream is camera '{self.frame_id}' (its images are paired "
                           f"with the odometry; '{frame_id}' would be computed with the wrong pose). Remap one of "
                           "them to its own topic (one node per camera); dropped.other_camera counts them",
                           key=f'{OTHER_CAMERA}:{frame_id}', period_s=30.0)
        return False


class ImageReceipt:
    """The image callback's checks. faults: node_support.FaultLog; drop(reason): counts a dropped image;
    size_change_images: images in a row a new image size must persist for to be taken (``StreamSize``)."""

    def __init__(self, faults, drop, stream_loss: StreamLoss | None = None,
                 size_change_images: int = P.default('size_change_images')):
        self.faults = faults
        self.drop = drop
        self.stream_loss = stream_loss or StreamLoss()
        self.camera = CameraFrame(faults, drop)
        self.size = StreamSize(size_change_images)
        self._carry: Incoming | None = None     # what a rejected image knew about the stream, for the next one
        self._last_stamp_ns: int | None = None  # header stamp of the stream's newest image
        self._restarts_mono: list[float] = []   # receipt times of recent sequence restarts

    def image(self, msg, stamp_ns: int | None, receipt_mono: float, receipt_ns: int,
              seq: int | None = None, source: str = '', decode=None) -> Incoming | None:
        """The Incoming to hand to the worker, or None when the image is rejected (counted and logged here).
        `stamp_ns`: its header stamp (None: unreadable); `seq`: its publication sequence number (None or 0: the
        middleware gives none); `source`: the subscription it came through (each has its own writers' numbers);
        `decode`: for a compressed image still undecoded, `decode(msg) -> DecodedImage`, called once its size (from
        the header) is taken; the Incoming then holds the DecodedImage."""
        loss = self.stream_loss
        if not self.camera.accept(msg.header.frame_id, stamp_ns, receipt_mono):
            loss.on_sample(seq, source)       # another camera's image: its number still shows what was lost
            return None
        last, self._last_stamp_ns = self._last_stamp_ns, stamp_ns
        gap_ns = stamp_ns - last if stamp_ns is not None and last is not None and stamp_ns > last else None
        jumps, changes, restarts = loss.stamp_jumps, loss.rate_changes, loss.sequence.restarts
        # images missing before this one (lost in transport): counted; a gap the middleware reported as lost is
        # judged by the worker (camera_gap_ns), as the report may come after this image
        lost = loss.on_image(stamp_ns, seq, source) if stamp_ns is not None else None
        if loss.sequence.restarts != restarts:
            self._on_sequence_restart(msg.header.frame_id, receipt_mono)
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
        header_size = None
        if decode is not None:      # compressed: judge the size from the header, decode only an image it takes
            header_size = compressed_size(msg.data)
            if header_size is not None and not self._size_taken(item, header_size, stamp_ns):
                return None
            item.msg = msg = decode(msg)
            if msg.error is None and header_size is not None and (msg.width, msg.height) != header_size:
                return self._reject(item, UNDECODABLE_IMAGE, UndecodableImage(
                    f'the header says {header_size[0]}x{header_size[1]} but the payload decodes to '
                    f'{msg.width}x{msg.height}'), stamp_ns)
        if isinstance(msg, DecodedImage) and msg.error is not None:
            return self._reject(item, UNDECODABLE_IMAGE, msg.error, stamp_ns)
        try:
            M.check_colour_image(msg)
        except M.UnsupportedEncoding as exc:
            return self._reject(item, UNSUPPORTED_ENCODING, exc, stamp_ns)
        except M.BadImage as exc:
            return self._reject(item, BAD_IMAGE, exc, stamp_ns)
        if header_size is None and not self._size_taken(item, (int(msg.width), int(msg.height)), stamp_ns):
            return None
        self._carry = None
        return item

    def _size_taken(self, item: Incoming, size: tuple[int, int], stamp_ns: int | None) -> bool:
        """False (rejected, counted and logged) for an image too small for the estimator or a stray of another size
        than the stream's (``StreamSize``); True when the stream takes its size."""
        w, h = size
        small = image_too_small(w, h)
        if small is not None:
            self._reject(item, IMAGE_TOO_SMALL, small, stamp_ns, key=f'{IMAGE_TOO_SMALL}:{w}x{h}', period_s=30.0)
            return False
        verdict = self.size.image(size)
        if not verdict.taken:
            self._reject(item, STRAY_IMAGE_SIZE, f'{verdict.stray} (size_change_images); a stray image does not '
                         'restart the filter', stamp_ns, key=f'{STRAY_IMAGE_SIZE}:{w}x{h}', period_s=30.0)
            return False
        return True

    def _on_sequence_restart(self, frame_id: str, receipt_mono: float) -> None:
        """The image publisher's sequence numbers went back: a restarted driver (info), or, when they go back again
        and again, two publishers of one frame_id on the topic (a warning: their images cannot be told apart)."""
        _source, before, now = self.stream_loss.sequence.last_restart
        recent = [t for t in self._restarts_mono if receipt_mono - t <= TWO_PUBLISHERS_S] + [receipt_mono]
        self._restarts_mono = recent
        if len(recent) >= TWO_PUBLISHERS_RESTARTS:
            self.faults.report(TWO_PUBLISHERS, f"two publishers send images of frame_id '{frame_id}' on one topic: "
                               f'their sequence numbers interleave ({len(recent)} restarts in {TWO_PUBLISHERS_S:g} s) '
                               'and their images are taken as one camera. Remap one of them to its own topic; lost '
                               'images are judged from the stamps', period_s=30.0)
            return
        self.faults.report(SEQUENCE_RESTART, f'image publication sequence numbers went back ({before} -> {now}): '
                           'the camera driver restarted (or a second publisher appeared); lost images are judged '
                           'from the stamps until they run forward again', level='info', period_s=30.0)

    def _reject(self, item: Incoming, kind: str, why, stamp_ns: int | None, key: str | None = None,
                period_s: float | None = None) -> None:
        self._carry = item
        self.drop(kind)
        at = f'{stamp_ns / NS:.3f} s' if stamp_ns is not None else 'an unreadable stamp'
        what = f"compressed image (format '{item.msg.format}')" if hasattr(item.msg, 'format') else 'image'
        self.faults.report(kind, f'dropping {what} at {at}: {why}', key=key, period_s=period_s)
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
