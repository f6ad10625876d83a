"""Landmark mapping (the report's III-B) with the true poses: how close is the map?"""

import numpy as np

import vislam

drive = vislam.simulate_drive(vislam.SimulationOptions(n_frames=80, pixel_noise_px=0.5))
seq = drive.sequence
f = vislam.MappingFilter(seq.calibration, vislam.FilterOptions(pixel_noise_px=0.5))
for frame in seq.frames():
    f.step(frame, world_T_imu=drive.world_T_imu[frame.index])
landmark_map = f.finish()

ok = landmark_map.status == 0
error_m = np.linalg.norm(landmark_map.p_lm_in_world[ok] - drive.p_lm_in_world[landmark_map.ids[ok]], axis=1)
print(f"{ok.sum()} landmarks mapped, median error {np.median(error_m):.3f} m")
