"""Benchmarks of the layers below, each a module that prints figures (e.g. `python -m dpv_sensor.benchmarks.core`):
what a user runs to learn how fast or how accurate the camera is, the ones the README lists. The one-off studies
behind a doc's figure live in ``dpv_sensor.studies``.

May import every package except ``dpv_sensor.tools`` and ``dpv_sensor.studies``."""
