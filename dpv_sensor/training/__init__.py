"""End-to-end training of D-Net, K-Net and R-Net (paper sec. 3.3) on streamed synthetic scenes.

- :mod:`dpv_sensor.training.dataset`: an ``IterableDataset`` that renders a fresh synthetic scene for
  every sample (seeds >= ``TRAIN_SEED_BASE``; seeds ``VAL_SEEDS`` are held out for validation) and
  cuts it into runs of consecutive keyframes with five-frame windows; optional TartanAir mixing.
- :mod:`dpv_sensor.training.config`: the trainer's settings (``TrainConfig``) and the export-selection score.
- :mod:`dpv_sensor.training.unrolled`: the unrolled filter loss of one batch (D-Net, DPV filter, R-Net).
- :mod:`dpv_sensor.training.validation`: the window validation on held-out seeds (and the classical baseline).
- :mod:`dpv_sensor.training.checkpoints`: resumable safetensors checkpoints and the atomic weight export.
- :mod:`dpv_sensor.training.plots`: the loss curves and the validation montage.
- :mod:`dpv_sensor.training.loop`: the training loop (AdamW, AMP, clipping, validation schedule, DDP).
- :mod:`dpv_sensor.training.stream_validation`: optional validation that streams whole held-out
  sequences through the product's ``Estimator`` (as the node runs the weights).

The console entry point is :mod:`dpv_sensor.tools.train` (``ros2 run dpv_sensor train``).

May import: ``dpv_sensor.evaluation``, ``dpv_sensor.data`` and below; no ROS, neither tools nor benchmarks.
"""
