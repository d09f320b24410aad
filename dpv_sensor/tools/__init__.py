"""Console tools (`ros2 run dpv_sensor <tool>`); what they share lives in dpv_sensor.client and dpv_sensor.cli."""
