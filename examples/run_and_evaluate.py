"""Localization and SLAM on a simulated drive with a noisy IMU, graded against the truth."""

import vislam

drive = vislam.simulate_drive(vislam.SimulationOptions(n_frames=80, velocity_noise_mps=0.5,
                                                       angular_noise_radps=0.05))
options = vislam.FilterOptions(velocity_noise_mps=0.5, angular_noise_radps=0.05)
for mode in ("localization", "slam"):
    result = vislam.run(drive.sequence, mode, options)
    ev = vislam.evaluate(result.world_T_imu, drive.world_T_imu)
    print(f"{mode:13s} ATE {ev.ape.rmse:6.3f} m over {ev.path_length_m:.0f} m, "
          f"filter {result.stats.filter_seconds:.2f} s")
