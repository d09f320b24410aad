"""The ROS client side, below the tools and benchmarks: start the node as its own process and talk to it
(``node_process``), play and record bags over a live graph and collect outputs (``ros_io``), and replay a bag
through the node in lockstep (``replay``). Tools, benchmarks and the integration tests import these.

May import: ``dpv_sensor.data``, ``dpv_sensor.ros`` and below; neither tools nor benchmarks."""
