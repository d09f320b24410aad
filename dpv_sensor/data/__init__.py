"""Data on disk and made up: sequence folders (``sequence``), the synthetic renderer (``synthetic``), camera
trajectories and odometry noise (``trajectory``), rosbag2 files written and read with ``rosbags``
(``rosbag_io``, which builds messages with ``dpv_sensor.ros.msgs``), which bag topic is the camera image,
camera_info, odometry, by message type (``topic_detection``) and a recorded bag of the node's outputs exported to
files (``bag_export``).

May import: ``dpv_sensor.ros.msgs``, ``dpv_sensor.stream``, ``dpv_sensor.core`` and the ground floor; never
rclpy."""
