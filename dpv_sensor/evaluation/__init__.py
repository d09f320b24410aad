"""Offline evaluation: depth and confidence metrics (``metrics``), the offline runner and its reports
(``offline``: a sequence through the same ``Pipeline`` the node runs, or a recorded bag, scored against GT),
TSDF fusion (``fusion``), the consumer check with Open3D RGB-D odometry (``consumer_odometry``, Open3D loaded
by ``open3d_loader``) and figures (``plots``). No ROS.

May import: ``dpv_sensor.data``, ``dpv_sensor.ros.msgs`` (message decoding, no rclpy), ``dpv_sensor.stream``,
``dpv_sensor.core`` and the ground floor."""
