"""ATE of one run with given FilterOptions, data corrections applied first.

The measurements behind the notes on `vislam check`'s suggestions in benchmarks/README.md
(``vislam run`` does not apply the data corrections yet: the lead wires
``apply_corrections`` into the run). Usage::

    PYTHONPATH=src python benchmarks/corrections_ate.py DATA MODE GT '{"gyro_bias_radps": [0, 0.005, 0]}'

DATA a dataset file, MODE localization|mapping|slam, GT the KITTI ground truth of the
left camera (converted to the IMU with the dataset's cam_T_imu), then the options as JSON.
Prints the APE (SE(3)-aligned) RMSE and the run time.
"""

from __future__ import annotations

import json
import sys
import time

from vislam.core import estimators
from vislam.core.corrections import apply_corrections
from vislam.core.options import FilterOptions
from vislam.tools.dataset_io import load_sequence
from vislam.tools.evaluation import evaluate, load_ground_truth


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    data, mode, gt_path = argv[:3]
    options = FilterOptions.from_dict(json.loads(argv[3]) if len(argv) > 3 else {})
    sequence = load_sequence(data)
    gt = load_ground_truth(gt_path, frame="cam", cam_T_imu=sequence.cam_T_imu).world_T_body
    t0 = time.perf_counter()
    result = estimators.run(apply_corrections(sequence, options), mode, options)
    n = min(len(gt), len(result.world_T_imu))
    ev = evaluate(result.world_T_imu[:n], gt[:n])
    print(f"{data} {mode} {argv[3] if len(argv) > 3 else '{}'}: ATE {ev.ape.rmse:.3f} m "
          f"({time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
