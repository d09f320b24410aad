"""Data on disk and made up: sequence folders (``sequence``), the synthetic renderer (``synthetic``), camera
trajectories and odometry noise (``trajectory``) and rosbag2 files written and read with ``rosbags``
(``rosbag_io``, which builds messages with ``dpv_sensor.ros.msgs``).

May import: ``dpv_sensor.ros.msgs``, ``dpv_sensor.stream``, ``dpv_sensor.core`` and the ground floor; never
rclpy."""
