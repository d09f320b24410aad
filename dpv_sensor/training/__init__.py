"""End-to-end training of D-Net, K-Net and R-Net (paper sec. 3.3) on streamed synthetic scenes.

- :mod:`dpv_sensor.training.dataset`: an ``IterableDataset`` that renders a fresh synthetic scene for
  every sample (seeds >= ``TRAIN_SEED_BASE``; seeds ``VAL_SEEDS`` are held out for validation) and
  cuts it into runs of consecutive keyframes with five-frame windows; optional TartanAir mixing.
- :mod:`dpv_sensor.training.loop`: the unrolled filter loss, the training loop (AdamW, AMP on CUDA,
  clipping, resumable safetensors checkpoints, validation, plots, atomic weight export, DDP).
- :mod:`dpv_sensor.training.stream_validation`: optional validation that streams whole held-out
  sequences through the product's ``Estimator`` (as the node runs the weights).

The console entry point is :mod:`dpv_sensor.tools.train` (``ros2 run dpv_sensor train``).

May import: ``dpv_sensor.evaluation``, ``dpv_sensor.data`` and below; no ROS, neither tools nor benchmarks.
"""
