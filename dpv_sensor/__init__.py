"""dpv_sensor: a virtual RGB-D camera from monocular video and odometry.

The subpackages are the layers; imports point down the list only, and nothing below ``ros`` imports ROS:

- ``core``: maths on arrays and tensors (geometry, DPV operations, the networks, the Bayesian filter,
  photometric alignment, parallax, pose uncertainty, image checks); no stream state, no ROS.
- ``stream``: the virtual camera without ROS: frames, keyframes, the estimator, the pose source and the
  stream-continuity rules. ``Pipeline.push(frame)`` is what the node and every offline tool run.
- ``ros``: the rclpy adapter (messages, parameters, QoS and transport, inputs, outputs, TF, diagnostics).
- ``data``: sequence folders, the renderer and rosbag2 files.
- ``evaluation``: metrics, the offline runner, fusion, the consumer check and plots.
- ``client`` (the ROS client side for tools and tests) and ``training``; then ``benchmarks`` (what a user runs
  to learn how fast or how accurate the camera is), then ``studies`` (the one-off measurements behind the docs'
  figures) and ``tools``.

``params`` (the settings tables), ``cli`` (the command-line groups built from them) and ``common`` (the JSON
sanitiser, the code version) are on the ground floor: every layer may import them, they import no layer.
"""
__version__ = '0.1.0'
