"""The kinds of fault the node counts (their names are the counters faults.* and dropped.* in /diagnostics; each
has its own log message where it happens). No ROS. The receipt's kinds are in ``receipt`` (unsupported_encoding,
bad_image) and ``compressed_image`` (undecodable_image), the pipeline's in ``dpv_sensor.stream.pipeline``
(degenerate_image, visual_odometry_lost)."""

SIZE_CHANGE = 'image_size_change'
IMAGE_TOO_SMALL = 'image_too_small'           # an image below the estimator's smallest size (refused on receipt)
STRAY_IMAGE_SIZE = 'stray_image_size'         # an image of another size than the stream's that did not persist
FUTURE_STAMP = 'future_stamp'                  # an image stamped ahead of the node's clock and the odometry
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
ODOM_COVARIANCE_NAN = 'odometry_covariance_nan'    # NaN or infinity in the pose or twist covariance (it is ignored)
# an odometry pose or twist covariance that is not one (core.odometry_covariance.check_covariance; it is ignored)
ODOM_COVARIANCE_NEGATIVE = 'odometry_covariance_negative_diagonal'
ODOM_COVARIANCE_ASYMMETRIC = 'odometry_covariance_asymmetric'
ODOM_COVARIANCE_NOT_PSD = 'odometry_covariance_not_psd'
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
TF_LOOP = 'tf_loop'                            # a loop in TF through the camera mount's path (once per appearance)
TF_CONFLICTING_PARENTS = 'tf_conflicting_parents'  # messages giving a frame of the mount's path a second parent
TF_MOUNT_FLIP = 'tf_mount_flip'                # /tf_static messages on the mount's path that disagree (publishers)
