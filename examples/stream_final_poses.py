"""Stream a drive into the SLAM filter and take each frame's final pose.

With the stalled-track remap (the default) the filter updates frames up to 10 frames
behind the newest one: ``f.world_T_imu`` is the newest frame's pose predicted with the
IMU, ``pop_final_poses()`` hands out the poses the filter is done with.
"""

import numpy as np

import vislam

drive = vislam.simulate_drive(vislam.SimulationOptions(n_frames=60, stall_period=10, velocity_noise_mps=0.5,
                                                       angular_noise_radps=0.05))
seq = drive.sequence
options = vislam.FilterOptions(velocity_noise_mps=0.5, angular_noise_radps=0.05)
f = vislam.SlamFilter(seq.calibration, options)

final = {}
largest_lag = 0
for frame in seq.frames():
    f.step(frame)
    for t, world_T_imu in f.pop_final_poses():
        final[t] = world_T_imu
    largest_lag = max(largest_lag, frame.index - max(final, default=-1))
f.drain()  # the recording ended: the frames still held are final now
final.update(f.pop_final_poses())
landmarks = f.finish()

poses = np.array([final[t] for t in range(seq.n_frames)])
batch = vislam.run(seq, "slam", options)
print(f"{len(poses)} final poses (the filter ran up to {largest_lag} frames behind), {len(landmarks)} landmarks")
print(f"largest difference to vislam.run: {np.abs(poses - batch.world_T_imu).max():.1e}")
assert np.allclose(poses, batch.world_T_imu, atol=1e-9)
