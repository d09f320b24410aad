"""The pose modules under their former name: the window refiner is :mod:`dpv_sensor.stream.window_refiner`,
visual odometry :mod:`dpv_sensor.stream.visual_odometry`. Import from those; this module only re-exports them."""
from dpv_sensor.stream.visual_odometry import VisualOdometry, VisualOdometryConfig, VOResult  # noqa: F401
from dpv_sensor.stream.window_refiner import (PoseRefinerConfig, RefinementResult, WindowKeyframe,  # noqa: F401
                                              WindowPoseRefiner, odometry_between_sigmas, relative_pose_errors)
