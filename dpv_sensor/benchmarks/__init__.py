"""Micro-benchmarks of the dpv_sensor core (run as modules, e.g. `python -m dpv_sensor.benchmarks.core`)."""
