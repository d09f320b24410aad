"""The kinds of fault the node counts (their names are the counters faults.* and dropped.* in /diagnostics; each
has its own log message where it happens). No ROS. The receipt's kinds are in ``receipt`` (unsupported_encoding,
bad_image) and ``compressed_image`` (undecodable_image), the pipeline's in ``dpv_sensor.stream.pipeline``
(degenerate_image, visual_odometry_lost)."""

SIZE_CHANGE = 'image_size_change'
NO_CAMERA_INFO = 'no_camera_info'
BAD_CAMERA_INFO = 'bad_camera_info'
CAMERA_INFO_MISMATCH = 'camera_info_size_mismatch'
NAN_ODOMETRY = 'nan_odometry'
ODOM_JUMP = 'odometry_jump'
ODOM_GAP = 'odometry_gap'
ODOM_TIMEOUT = 'odometry_timeout'
ODOM_LATE = 'odometry_late'                    # an image replaced in the mailbox while the worker waited for odometry
ODOM_TOO_OLD = 'odometry_too_old'
ODOM_INVALID = 'odometry_invalid_bracket'
ODOM_COVARIANCE_NAN = 'odometry_covariance_nan'    # NaN or infinity in the pose covariance (it is ignored)
ODOM_ZERO_STAMP = 'odometry_zero_stamp'        # odometry with header.stamp 0 (an unstamped driver; ignored)
ODOM_CONFLICT = 'odometry_conflict'            # two messages at one stamp with different poses (the first is kept)
EMPTY_FRAME_ID = 'empty_frame_id'              # an image without header.frame_id (the frame_id parameter is used)
TIME_BACKWARDS = 'time_backwards'
DUPLICATE_STAMP = 'duplicate_stamp'
ESTIMATOR_EXCEPTION = 'estimator_exception'
PUBLISH_ERROR = 'publish_error'
UNKNOWN_OUTPUT = 'unknown_output_stamp'
INTERNAL_ERROR = 'internal_error'
BUSY = 'busy'
UNSUPPORTED_DISTORTION = 'unsupported_distortion'
RECTIFY_SIZE = 'rectify_size_mismatch'
MISSING_RGB = 'missing_output_colour'
INCOMPATIBLE_QOS = 'incompatible_qos'
OUTPUT_K_MISMATCH = 'output_K_mismatch'
NO_EXTRINSIC = 'no_extrinsic'                  # no camera mount (extrinsic_source tf) for an image yet: dropped
BAD_TRANSFORM = 'bad_transform'                # a transform on /tf_static or /tf with NaN or a non-unit quaternion
