"""Console tools (`ros2 run dpv_sensor <tool>`), the top layer; what they share lives in dpv_sensor.client and
dpv_sensor.cli, and a tool does not import another (the demo's call of evaluate and fuse is the one exception).

May import every package."""
