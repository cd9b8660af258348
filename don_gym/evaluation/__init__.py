"""Stage "evaluation": the last stage, which may use every other one.

Modules: ``splits`` (which seeds are held out), ``datasets`` (the evaluation datasets' recipe), ``frames``
(dataset plumbing shared by tracking and pose), ``tracking_metrics`` (the tracking protocol's pure core),
``tracking`` (its runner over datasets), ``report`` (its tables and figures), ``pose_metrics`` (BOP's pose
errors and recalls), ``pose_evaluation`` (6D pose over datasets), ``episodes`` (the episode pool of the robot
benchmarks), ``grasp_benchmark`` and ``bin_benchmark``.
"""
