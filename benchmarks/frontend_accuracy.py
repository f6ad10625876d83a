#!/usr/bin/env python
"""The stereo tracker against known truth: rendered drives and the EuRoC frames (issue 21).

Usage::

    # once per seed (about 1-2 s per frame on 2 shared cores):
    vislam simulate --images --frames 500 --seed S --velocity-noise 0.5 --angular-noise 0.05 --out DIR/seedS
    PYTHONPATH=src python benchmarks/frontend_accuracy.py DIR/seed0 DIR/seed1 ... [--euroc FOLDER]
                                                          [--out benchmarks/results/frontend_accuracy.json]
                                                          [--tracker-config FILE.yaml]

For each rendered date folder (``vislam simulate --images``):

* ``vislam track DIR/sim_drive_*_sync --out DIR/tracks.npz``; every tracked observation is
  graded against the true geometry (``scene_planes.npz``, true poses from
  ``groundtruth.tum``; :func:`vislam.core.render.track_reprojection_errors`): median error,
  share beyond 3 px, tracked landmarks per frame, median track length (frames in which one
  id is observed; checked to be consecutive: no track has a gap) and how the tracks ended;
* ``vislam run DIR/sim_drive_*_sync --mode slam --gt DIR/groundtruth.kitti`` (the folder
  itself, as a user runs it) and ``vislam run DIR/sequence.npz --mode slam --gt ...``
  (the simulator's own observations of the same drive): ATE of each and their ratio;
  dead reckoning (``--mode localization``) for scale; both SLAMs again told the drive's
  IMU noise (``--told MPS RADPS``, default 0.5 0.05: with its defaults the filter trusts
  the noisy velocities and ends near dead reckoning).

With ``--tracker-config FILE`` the tracker runs with those options (``vislam track --config``,
``vislam run --tracker-config``) and its tracks and SLAM runs go to ``DIR/variant_<FILE's stem>/``;
the simulator's runs stay in DIR and are shared by every variant.

With ``--euroc`` (default ``../shared/data/images/euroc_v1_01_first95`` when present):
stereo row difference, depths, the drift of the full-length tracks from the common image
motion (a homography from frame 0) and the raw displacement.

Targets (issue 21): median <= 0.3 px, <= 1 % beyond 3 px, >= 100 landmarks per frame,
median track length >= 10, SLAM ATE on the tracks <= 1.3x that on the simulator's
observations; EuRoC: row difference median <= 0.5 px, drift median <= 0.3 px, depths 0.5-15 m.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _vislam(*args) -> None:
    subprocess.run([sys.executable, "-m", "vislam", *map(str, args)], check=True)


def _ate(run_dir: Path) -> float:
    return json.loads((run_dir / "summary.json").read_text())["evaluation"]["ape_rmse_m"]


def _consecutive(obs) -> bool:
    """Whether every track's length (frames observed) equals its span (last - first + 1 frames):
    then the median track length counts consecutive frames of one id."""
    ids, frames = obs.landmark_ids, obs.frame_index
    first = np.full(obs.n_landmarks, np.iinfo(np.int64).max)
    last = np.full(obs.n_landmarks, -1)
    np.minimum.at(first, ids, frames)
    np.maximum.at(last, ids, frames)
    return bool(np.array_equal(last - first + 1, obs.track_lengths()))


def rendered(folder: Path, noise: tuple[float, float] | None, tracker_config: Path | None = None) -> dict:
    from vislam.core.render import camera_poses, track_reprojection_errors
    from vislam.tools.dataset_io import load_sequence
    from vislam.tools.trajectory_io import read_tum

    drive = next(folder.glob("sim_drive_*_sync"))
    work = folder / f"variant_{tracker_config.stem}" if tracker_config else folder
    work.mkdir(exist_ok=True)
    config = ["--config", tracker_config] if tracker_config else []
    tracks = work / "tracks.npz"
    if not tracks.is_file():
        _vislam("track", drive, "--out", tracks, "--quiet", *config)
    seq = load_sequence(tracks)
    _, world_T_imu = read_tum(folder / "groundtruth.tum")
    scene = SimpleNamespace(**dict(np.load(folder / "scene_planes.npz")))
    err = track_reprojection_errors(seq.observations, camera_poses(world_T_imu, seq.cam_T_imu), seq.camera.K,
                                    seq.camera.baseline_m, scene)
    finite = err[np.isfinite(err)]
    out = {"folder": str(folder), "tracker_config": str(tracker_config) if tracker_config else None,
           "frames": seq.n_frames, "tracks": seq.n_landmarks,
           "observations": seq.observations.n_observations, "ungraded_share": float(1 - finite.size / err.size),
           "error_median_px": float(np.median(finite)), "error_p90_px": float(np.percentile(finite, 90)),
           "beyond_3px_share": float(np.mean(finite > 3)),
           "landmarks_per_frame_mean": float(seq.observations.counts_per_frame().mean()),
           "track_length_median": float(np.median(seq.observations.track_lengths())),
           "track_length_is_consecutive": _consecutive(seq.observations),
           "statistics": json.loads((work / "tracks.tracking.json").read_text())["rejections"],
           "track_ends": json.loads((work / "tracks.tracking.json").read_text()).get("track_ends")}
    gt = folder / "groundtruth.kitti"
    # the filter with its defaults (the command as written) and told the drive's IMU noise (--told)
    told = ["--velocity-noise", str(noise[0]), "--angular-noise", str(noise[1])] if noise else []
    for name, data, mode, extra in (("slam_tracked", drive, "slam", []),
                                    ("slam_simulator", folder / "sequence.npz", "slam", []),
                                    ("slam_tracked_told", drive, "slam", told),
                                    ("slam_simulator_told", folder / "sequence.npz", "slam", told),
                                    ("dead_reckoning", folder / "sequence.npz", "localization", [])):
        if extra == [] and name.endswith("_told"):
            continue
        on_drive = data == drive
        run = (work if on_drive else folder) / f"run_{name}"
        if not (run / "summary.json").is_file():
            tracker = ["--tracker-config", tracker_config] if on_drive and tracker_config else []
            _vislam("run", data, "--mode", mode, "--gt", gt, "--out", run, "--quiet", *extra, *tracker)
        out[f"ate_{name}_m"] = _ate(run)
    out["ate_ratio_tracked_over_simulator"] = out["ate_slam_tracked_m"] / out["ate_slam_simulator_m"]
    if "ate_slam_tracked_told_m" in out:
        out["ate_ratio_told"] = out["ate_slam_tracked_told_m"] / out["ate_slam_simulator_told_m"]
    return out


def euroc(folder: Path) -> dict:
    import cv2

    from vislam.tools.frontend_io import open_stereo_source, track_source

    source = open_stereo_source(folder)
    seq, stats = track_source(source)
    obs = seq.observations
    px = obs.pixels
    depth = source.K[0, 0] * source.baseline_m / (px[:, 0] - px[:, 2])
    full = np.flatnonzero(obs.track_lengths() == seq.n_frames)
    first, last = obs.frame(0), obs.frame(seq.n_frames - 1)
    p0 = first[1][np.searchsorted(first[0], full), :2]
    p1 = last[1][np.searchsorted(last[0], full), :2]
    H, _ = cv2.findHomography(p0, p1, 0)
    pred = cv2.perspectiveTransform(p0.reshape(-1, 1, 2), H).reshape(-1, 2)
    return {"folder": str(folder), "frames": seq.n_frames, "tracks_per_frame_mean": float(obs.counts_per_frame().mean()),
            "row_difference_median_px": float(np.median(np.abs(px[:, 1] - px[:, 3]))),
            "depth_min_m": float(depth.min()), "depth_max_m": float(depth.max()),
            "full_length_tracks": int(full.size),
            "raw_displacement_median_px": float(np.median(np.linalg.norm(p1 - p0, axis=1))),
            "drift_from_common_motion_median_px": float(np.median(np.linalg.norm(p1 - pred, axis=1))),
            "baseline_m": source.baseline_m}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="*", type=Path, help="date folders written by vislam simulate --images")
    parser.add_argument("--euroc", type=Path, default=REPO.parent / "shared" / "data" / "images" / "euroc_v1_01_first95")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "frontend_accuracy.json")
    parser.add_argument("--told", type=float, nargs=2, metavar=("MPS", "RADPS"), default=(0.5, 0.05),
                        help="also run both SLAMs told this IMU noise (the drives' --velocity-noise/--angular-noise)")
    parser.add_argument("--tracker-config", type=Path, metavar="FILE",
                        help="tracker options (YAML/TOML); tracks and SLAM runs in DIR/variant_<stem>/")
    args = parser.parse_args()
    result = {"rendered": [], "euroc": None}
    for folder in args.folders:
        r = rendered(folder, args.told, args.tracker_config)
        result["rendered"].append(r)
        print(f"{folder}: {r['frames']} frames, error median {r['error_median_px']:.3f} px, "
              f"{100 * r['beyond_3px_share']:.2f} % > 3 px, {r['landmarks_per_frame_mean']:.0f} landmarks/frame, "
              f"track length median {r['track_length_median']:g}; ATE SLAM tracked {r['ate_slam_tracked_m']:.3f} m, "
              f"simulator's {r['ate_slam_simulator_m']:.3f} m (ratio {r['ate_ratio_tracked_over_simulator']:.2f}), "
              f"dead reckoning {r['ate_dead_reckoning_m']:.3f} m; told the IMU noise: tracked "
              f"{r.get('ate_slam_tracked_told_m', float('nan')):.3f} m, simulator's "
              f"{r.get('ate_slam_simulator_told_m', float('nan')):.3f} m (ratio {r.get('ate_ratio_told', float('nan')):.2f})",
              flush=True)
    if args.euroc and (args.euroc / "mav0").is_dir():
        e = euroc(args.euroc)
        result["euroc"] = e
        print(f"EuRoC: row difference median {e['row_difference_median_px']:.3f} px, depths "
              f"{e['depth_min_m']:.2f}-{e['depth_max_m']:.2f} m, drift from the common motion median "
              f"{e['drift_from_common_motion_median_px']:.3f} px (raw displacement "
              f"{e['raw_displacement_median_px']:.2f} px), {e['tracks_per_frame_mean']:.0f} tracks/frame")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
