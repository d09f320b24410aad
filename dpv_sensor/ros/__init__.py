"""The rclpy adapter of the virtual camera: the console script (``entry``) and the start-up steps before the heavy
imports (``startup``), the node (``node``) and its parts: typed parameters (``node_params``), inputs (``inputs``:
subscriptions and what arrives), the worker that runs the pipeline (``worker``), outputs (``outputs``: publishers),
``diagnostics``, QoS (``qos``) and the fault kinds (``fault_kinds``); message <-> numpy conversion (``msgs``,
``cloud_msgs``, ``compressed_depth``), the DDS transport profile (``transport``), what is decided about an input on
receipt (``receipt``, ``stream_loss``, ``topic_names``), TF (``tf_publisher``) and small plumbing (``node_support``,
``process_memory``). It owns no algorithm.

May import: ``dpv_sensor.stream``, ``dpv_sensor.core`` and the ground floor. Only the modules that talk to a
ROS graph import rclpy; the message conversions, ``entry``, ``startup`` and the receipt rules stay importable
without it."""
