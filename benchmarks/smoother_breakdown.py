"""Where a smoother frame's time goes: the steps of SmootherFilter timed one by one (CPU time).

Usage (from the repository root)::

    PYTHONPATH=src python benchmarks/smoother_breakdown.py ../shared/data/dense/0034.npz [--repeat 3]

Each step of :class:`vislam.core.smoother.SmootherFilter` is wrapped in a timer
(``time.process_time``: CPU time of the process, so that other work on a shared machine
adds little) and the drive is run ``--repeat`` times with the smoother's defaults; the
best run's per-frame mean of every step is printed with its share of the run (nested
steps are included in their parents). "levelled odometry factor" is the Python code
GTSAM calls back from inside the iSAM2 update to linearize the levelled motion model
(``level_odometry_error``; the number of calls per frame is printed too). Dense files
are run with the filter told their IMU noise (0.5 m/s, 0.05 rad/s), as benchmarks do.
The steps timed are those the tree under ``PYTHONPATH`` has (a step it lacks is
printed as "-"), so the script also runs on older trees.
"""

from __future__ import annotations

from frame_breakdown import breakdown  # the timers, the runs and the table (this folder)

from vislam.core import smoother

#: (label, owner, attribute or attributes): the steps timed, in the order printed (indented: inside the one above)
STEPS = [
    ("frame (step)", smoother.SmootherFilter, "step"),
    ("  pose and motion factor", smoother.SmootherFilter, "_predict_pose"),
    ("  select (repeats, stall counts)", smoother.SmootherFilter, "_select"),
    ("  stereo factors of known landmarks", smoother.SmootherFilter, "_add_observations"),
    ("  new landmarks", smoother.SmootherFilter, "_initialize_new"),
    ("  marginalize (final values, covariances)", smoother.SmootherFilter, "_marginalize"),
    ("  iSAM2 update (window)", smoother.SmootherFilter, "_update_window"),
    ("    levelled odometry factor (callbacks)", smoother, ("_level_odometry", "level_odometry_error")),
    ("  outlier check", smoother.SmootherFilter, "_check_outliers"),
    ("    drift test", smoother.SmootherFilter, "_drift_test"),
    ("  history record", smoother.SmootherFilter, "_record"),
]


def main() -> int:
    return breakdown(STEPS, "smoother", "smoother", __doc__.splitlines()[0], counted=("callbacks",))


if __name__ == "__main__":
    raise SystemExit(main())
