"""Height error of SLAM on a simulated drive with a roll/pitch gyro bias, default vs --auto.

The drive: SimulationOptions(seed=0) (600 frames) with a clean IMU and a gyro bias of
0.01 rad/s on roll and pitch. "--auto" here is what ``vislam run --auto`` does: the
suggestions of ``check_sequence`` as the options, the data corrections applied first.
Prints the largest |z_est − z_true| over the drive, also as a share of the distance.

    PYTHONPATH=src python benchmarks/auto_height.py
"""

from __future__ import annotations

import numpy as np

from vislam.core import estimators
from vislam.core.check import check_sequence
from vislam.core.corrections import apply_corrections
from vislam.core.options import FilterOptions
from vislam.core.simulate import SimulationOptions, simulate_drive


def main() -> None:
    drive = simulate_drive(SimulationOptions(seed=0, gyro_bias_radps=(0.01, 0.01, 0.0)))
    distance = drive.distance_m()
    check = check_sequence(drive.sequence)
    print("suggested:", check.suggested)
    for name, options in (("default", FilterOptions()), ("auto", check.suggested_options())):
        result = estimators.run(apply_corrections(drive.sequence, options), "slam", options)
        dz = np.abs(result.world_T_imu[:, 2, 3] - drive.world_T_imu[:, 2, 3])
        print(f"{name}: distance {distance:.0f} m, height error max {dz.max():.2f} m "
              f"({100 * dz.max() / distance:.2f} % of the distance)")


if __name__ == "__main__":
    main()
