"""Benchmarks of the layers below, each a module that prints figures (e.g. `python -m dpv_sensor.benchmarks.core`).

May import every package except ``dpv_sensor.tools``."""
