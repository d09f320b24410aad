"""Offline evaluation: depth and confidence metrics (``metrics``), the one offline runner (``runner``: a sequence
through the same ``Pipeline`` the node runs), the records of recorded outputs (``recorded``: a bag or an export),
their scoring (``scoring``) and reports (``report``: files and tables), with ``offline`` the front door of the
``evaluate`` tool (evaluate a sequence, compare configurations, score recorded outputs),
TSDF fusion (``fusion``), the consumer check with Open3D RGB-D odometry (``consumer_odometry``, Open3D loaded
by ``open3d_loader``) and figures (``plots``). No ROS.

May import: ``dpv_sensor.data``, ``dpv_sensor.ros.msgs`` (message decoding, no rclpy), ``dpv_sensor.stream``,
``dpv_sensor.core`` and the ground floor."""
