"""dpv_sensor: a virtual RGB-D camera from monocular video and odometry.

Layers (dependencies point down only; see DESIGN.md):
geometry -> dpv -> nets -> filter -> poses -> estimator  (torch/numpy only, never rclpy)
node + msgs (the rclpy adapter), data (sequences, renderer, rosbag2 I/O), tools (console scripts).
"""
__version__ = '0.1.0'
