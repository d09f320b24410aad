"""Studies: one-off measurements behind a figure or a decision in the docs, each a module that prints or writes
what a doc section quotes (e.g. `python -m dpv_sensor.studies.window_graph SEQUENCE`). A study answers a question
asked while the camera was being built (how far the keypoint poses err, which cue tells a right depth from a wrong
one); the benchmarks a user runs to learn how fast or how accurate the camera is live in ``dpv_sensor.benchmarks``.

- ``anchors``: how accurate the metric anchors are and what each way of holding the depth to them does
  (docs/anchors.md).
- ``adaptation_judge``: whether the adapt tool's judges (the anchors', the photometric) tell better held-out depth
  from worse on every folder (docs/adaptation.md, "The anchors' judge").
- ``alignment_depth``: the photometric alignment's rotation against the quality of its reference depth
  (docs/pose_uncertainty.md, "Every sequence: the odometry's covariance and keypoints together").
- ``confidence_features``: which per-pixel cues separate a right depth from a wrong one, and which carry
  (docs/confidence_study.md; its analysis is ``dpv_sensor.evaluation.confidence_study``).
- ``error_breakdown``: where the depth error comes from, by image position, depth, edges, texture and views
  (docs/results.md, "Held-out evaluation"; docs/adaptation.md, "Where the adapted depth gains and loses").
- ``keypoint_accuracy``: how far the refiner's keypoint relative poses err against their covariance
  (docs/pose_uncertainty.md, "How far the keypoint poses err" and "Rotation factors from dense optical flow").
- ``mount_check``: what the mount check finds on every folder with a mount and time offsets put in
  (docs/robot.md, "Check the mount and the clock"; docs/results.md, "The mount check").
- ``plane_anchors``: whether planes through the adapt judge's anchors can judge texture-free depth
  (docs/adaptation.md, "Planes through the anchors, as a judge of texture-free depth").
- ``pose_error_depth``: how the depth answers a chosen share of the odometry's error
  (docs/pose_uncertainty.md, "Where the drift's cost lies").
- ``poses``: the pose-refinement experiments: refinement window, odometry-free mode, the GT poses' consistency
  (docs/results.md, "Speed, memory and pose refinement" and "Held-out evaluation").
- ``selection``: scores weight files on held-out rendered sequences, as the exports were picked
  (docs/training.md, "The shipped weights, stage by stage").
- ``window_decisions``: what each factor set of the refinement window would have done, window by window
  (docs/pose_uncertainty.md, "Per-window decisions").
- ``window_graph``: a picture of the refinement window's factor graph from a real run
  (docs/pose_uncertainty.md, "The factor graph"; docs/window_graph.png).

May import every package except ``dpv_sensor.tools``: the layer on top of ``dpv_sensor.benchmarks``, beside the tools
(a study may use a benchmark's pieces, such as the stream table's pose sources or the held-out loader; no benchmark
imports a study, and no tool does)."""
