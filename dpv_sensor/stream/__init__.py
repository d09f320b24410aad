"""The virtual camera without ROS: what goes in and out (``frame``), odometry lookup at an image stamp
(``pose_buffer``), keyframe selection and the window (``keyframes``), the streaming estimator (``estimator``,
its configuration ``estimator_config`` and output composition ``depth_output``), the gtsam window refiner and
visual odometry (``poses``), the stream-continuity rules (``continuity``) and the pipeline the node and the
offline tools both run (``pipeline``).

May import: ``dpv_sensor.core`` and the ground floor (``params``, ``common``); never ROS."""
