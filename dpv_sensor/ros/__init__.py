"""The rclpy adapter of the virtual camera: the entry point (``entry``), the node (``node``), its parameters
(``node_params``), message <-> numpy conversion (``msgs``), the DDS transport profile (``transport``), what is
decided about an input on receipt (``receipt``, ``stream_loss``, ``topic_names``), TF (``tf_publisher``) and
small plumbing (``node_support``, ``process_memory``). It owns no algorithm.

May import: ``dpv_sensor.stream``, ``dpv_sensor.core`` and the ground floor. Only the modules that talk to a
ROS graph import rclpy; ``msgs``, ``entry`` and the receipt rules stay importable without it."""
