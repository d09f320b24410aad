"""Maths on arrays and tensors, with no stream state and no ROS: cameras and SE(3) (``geometry``), DPV
operations (``dpv``), the networks (``nets``: D-Net, K-Net, R-Net, presets, checkpoints), the Bayesian DPV filter
(``filter``), the classical plane-sweep measurement (``classical``), photometric alignment (``photometric``),
parallax (``parallax``), pose uncertainty in depth planes (``pose_uncertainty``), the edge-aware depth filter
(``edge_filter``), degenerate-image checks (``image_quality``) and rectification (``rectify``).

May import: the standard library, numpy, torch, OpenCV, and the ground floor (``dpv_sensor.params``,
``dpv_sensor.common``); no other dpv_sensor package."""
