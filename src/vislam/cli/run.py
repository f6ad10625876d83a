"""``vislam run DATA --mode MODE --out DIR``: run one of the report's estimators on a dataset.

Options: defaults of :class:`~vislam.core.options.FilterOptions` < ``--config FILE``
(YAML/TOML) < ``--robust`` < the other flags (:func:`vislam.tools.config.resolve_options`).
The estimator is :func:`vislam.core.estimators.run`; the files are written, all or
nothing, by :func:`vislam.tools.outputs.write_run_outputs`. This module parses, calls
and prints.

Shared with ``vislam compare`` (one definition each): the filter options
(:func:`add_filter_arguments`, :func:`options_from_args`), the noise injected into the
data after loading (``--add-*``, :func:`add_noise_injection_arguments`,
:func:`noise_spec_from_args` -> :class:`~vislam.core.noise.NoiseSpec`, recorded in
summary.json under ``"injected_noise"``) and the evaluation against ground truth in the
same run (``--gt``, :func:`add_ground_truth_arguments`, :func:`ground_truth_from_args`;
metrics in summary.json under ``"evaluation"``, plus ``metrics.json`` and
``error_over_distance.png``).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from vislam.cli.common import (  # noqa: F401 (the shared pieces, importable from here as before)
    FLAG_FIELDS,
    NOISE_FLAGS,
    _component_group,
    _note_option_names,
    _print,
    add_filter_arguments,
    add_ground_truth_arguments,
    add_noise_injection_arguments,
    auto_options,
    finish,
    format_evaluation_line,
    format_summary,
    ground_truth_from_args,
    interrupted_message,
    known_poses_from_args,
    load_data,
    make_progress,
    noise_spec_from_args,
    options_from_args,
    pair_ground_truth,
    reference_poses_from_args,
    tracking_warnings,
)
from vislam.core.options import MODES
from vislam.errors import ConfigError

__all__ = ["register", "run", "format_summary", "format_evaluation_line", "make_progress", "finish",
           "interrupted_message", "FLAG_FIELDS", "NOISE_FLAGS", "add_filter_arguments", "add_noise_injection_arguments",
           "add_ground_truth_arguments", "add_rerun_arguments", "open_rerun_recorder", "options_from_args",
           "noise_spec_from_args", "ground_truth_from_args", "load_data"]

_COMMAND_START = time.time()


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "run", add_help=False,
        help="run IMU localization, landmark mapping, SLAM or the sliding-window smoother on a dataset",
        description="Run one of the report's estimators on a dataset (.npz) and write DIR/trajectory.tum, "
        "DIR/trajectory.kitti, DIR/trajectory.png, DIR/summary.json and, for mapping and SLAM, "
        "DIR/landmarks.ply and DIR/landmarks.npz (with --gt also DIR/metrics.json and "
        "DIR/error_over_distance.png). Outputs appear all together or not at all. Options: "
        "defaults < --config FILE < --robust < the other flags. The --add-* flags add noise to the data (seeded); "
        "the filter's own noise model is set by --velocity-noise etc.",
        epilog="Every filter option (docs/options.md) can be set in the --config file, by its flat name "
        "(velocity_noise_mps: 0.5) or by group (noise: {velocity_mps: 0.5}); the flags above override the file.",
    )
    # what most runs need first; the rest below, grouped by component
    common = parser.add_argument_group("common options")
    common.add_argument("-h", "--help", action="help", help="show this help message and exit")
    parser.add_argument("data", metavar="DATA", help="dataset file (.npz), or an image folder (KITTI raw drive, "
                        "EuRoC, plain; tracked first, the tracks cached as DIR/tracks.npz)")
    common.add_argument("--mode", choices=MODES, default="slam",
                        help="localization (IMU only), mapping (landmarks from known poses), slam (the report's EKF) "
                        "or smoother (fixed-lag smoother on GTSAM over the same measurements) (default: slam)")
    common.add_argument("--out", metavar="DIR", required=True, help="output directory (created if needed)")
    add_filter_arguments(parser, common)
    smoother = _component_group(parser, "smoother")
    smoother.add_argument("--refine", action="store_true", default=None,
                          help="smoother only: a batch Levenberg-Marquardt pass over the whole drive from the "
                          "smoother's result (the trajectory written is the refined one; the smoother's goes to "
                          "smoother.tum)")
    mapping = parser.add_argument_group("mapping")
    mapping.add_argument("--poses", metavar="FILE",
                         help="mapping only: known world_T_imu poses, TUM or KITTI, one per frame (default: the "
                         "localization trajectory)")
    add_ground_truth_arguments(parser, common)
    common.add_argument("--quiet", action="store_true", help="print nothing but errors")
    add_noise_injection_arguments(parser)
    add_rerun_arguments(parser)
    from vislam.cli.common import add_source_arguments

    add_source_arguments(parser)
    _note_option_names(parser)
    parser.set_defaults(func=run)


def add_rerun_arguments(parser) -> None:
    """``--rerun FILE.rrd`` and ``--rerun-spawn``: a 3D view of the run (vislam.tools.rerun_view)."""
    group = parser.add_argument_group(
        "3D viewer", "Record the run frame by frame for the Rerun viewer (needs rerun-sdk: "
        "pip install 'vislam[viewer]'): pose, covariance, camera frustum, landmarks, map, per-frame statistics.")
    group.add_argument("--rerun", metavar="FILE.rrd",
                       help="write a Rerun recording (open it with `rerun FILE.rrd`); written, atomically, after "
                       "the other outputs")
    group.add_argument("--rerun-spawn", action="store_true",
                       help="also stream the recording to a live Rerun viewer (skipped with a warning when no "
                       "viewer or display is available)")


def record_frame(recorder, sequence):
    """The ``on_frame`` callback that records, live, each frame a stepwise filter
    finishes: its pose and covariance, the landmarks in the state now, those frozen in
    the step, the frame's statistics (or None without a recorder)."""
    if recorder is None:
        return None
    timestamps = sequence.timestamps_s
    from vislam.core.lie import se3_inverse

    def on_frame(f, processed) -> None:
        for i, (t, imu_T_world, cov, fs) in enumerate(processed):
            last = i == len(processed) - 1
            stats = fs.to_dict()
            stats.pop("frame", None)
            frozen = f.last_frozen if last else (None, None, None)
            recorder.log_frame(t, float(timestamps[t]), se3_inverse(imu_T_world), cov, f.live_landmark_ids,
                               f.live_p_lm_in_world, *frozen, stats=stats)

    return on_frame


def open_rerun_recorder(args, sequence):
    """The :class:`~vislam.tools.rerun_view.RerunRecorder` of ``--rerun``/``--rerun-spawn``, or
    None. Opened before the run, so a missing rerun-sdk or an unwritable path fails first."""
    if not (getattr(args, "rerun", None) or getattr(args, "rerun_spawn", False)):
        return None
    from vislam.tools.rerun_view import RerunRecorder

    return RerunRecorder(sequence.camera, sequence.cam_T_imu, path=args.rerun or None, spawn=args.rerun_spawn,
                         recording_name=f"{sequence.name} ({args.mode})")


def run(args) -> int:
    from vislam.tools.figure_process import FigureProcess

    with FigureProcess() as figures:  # started once the flags are checked
        return _run(args, figures)


def _check_mode_flags(args) -> None:
    """ConfigError for a flag that the chosen --mode does not use."""
    for flag, given, needs in (("--poses", bool(args.poses), "mapping"), ("--refine", bool(args.refine), "smoother"),
                               ("--imu-bias-sigma", args.imu_bias_sigma is not None, "slam"),
                               ("--imu-bias-time-constant", args.imu_bias_time_constant is not None, "slam")):
        if given and args.mode != needs:
            raise ConfigError(f"{flag} is only used by --mode {needs} (got --mode {args.mode})")


def _dataset_record(args, sequence, tracking) -> dict:
    """summary.json's ``dataset``: the file, its size, cam_T_imu, the tracking and the poses used."""
    dataset = {"name": sequence.name, "path": str(Path(args.data).resolve()), "frames": sequence.n_frames,
               "landmarks": sequence.n_landmarks, "duration_s": sequence.duration_s,
               "cam_T_imu": sequence.cam_T_imu.tolist()}
    if tracking is not None:
        dataset["tracking"] = {k: tracking[k] for k in ("source", "layout", "cache", "cache_reused")}
    if args.mode == "mapping":
        dataset["poses"] = str(Path(args.poses).resolve()) if args.poses else "localization"
    return dataset


def _run(args, figures) -> int:
    _check_mode_flags(args)
    # the figure helper imports matplotlib (~0.6 s) while this process imports, loads and
    # filters: started first, so that a short recording does not wait for it (an input
    # error later ends it unused)
    figures.start()
    from vislam.core.estimators import run as run_estimator
    from vislam.core.results import run_warnings
    from vislam.core.sequence import imu_sample_warnings
    from vislam.tools.comparison import evaluate_run, ground_truth_from_start, injected_noise_record, \
        stage_evaluation
    from vislam.tools.outputs import OutputStage, display_name, method_title, command_start_time, write_run_outputs

    start_time = command_start_time() or _COMMAND_START
    options = options_from_args(args)
    noise = noise_spec_from_args(args)
    sequence, tracking = load_data(args, args.out)
    auto = getattr(args, "auto", False)
    poses, gt, gt_info, recheck = reference_poses_from_args(args, sequence, options, auto)
    dataset = _dataset_record(args, sequence, tracking)
    extra = {}
    if noise is not None:
        from vislam.core.noise import inject_noise
        from vislam.tools.comparison import describe_noise

        sequence, info = inject_noise(sequence, noise)
        # ASCII: the label also goes into the PLY header
        dataset["label"] = f"{sequence.name} + noise ({describe_noise(noise, seed=False, ascii=True)})"
        extra["injected_noise"] = injected_noise_record(noise, info)
    if auto:  # check what the filter will see (with any injected noise)
        options, extra["auto"] = auto_options(args, sequence, args.quiet)
    if options.has_data_corrections:
        from vislam.core.corrections import apply_corrections

        sequence = apply_corrections(sequence, options)  # a no-op if the estimators apply them again
    if recheck:  # against the frame times --auto's corrections give
        pair_ground_truth(gt, sequence, options)
        poses = known_poses_from_args(args, sequence, options)[0]

    stage = OutputStage(args.out)
    close, recorder = (lambda: None), None
    try:
        with stage:
            recorder = open_rerun_recorder(args, sequence)
            progress, close = make_progress(sequence.n_frames, args.mode, args.quiet)
            try:
                result = run_estimator(sequence, args.mode, options, progress=progress, world_T_imu=poses,
                                       on_frame=record_frame(recorder, sequence))
            finally:
                close()
            extra["warnings"] = (tracking_warnings(tracking) + imu_sample_warnings(
                sequence.linear_velocity_in_imu_mps, sequence.angular_velocity_in_imu_radps) + run_warnings(result))
            if "timing" in result.extra:  # smoother: its own timings and those of refine
                extra["timing"] = result.extra["timing"]
            gt_poses = None
            if gt is not None:
                evaluation = evaluate_run(result, gt, sequence)
                gt_poses = ground_truth_from_start(evaluation)  # drawn in the figure, from the estimate's start
                extra["evaluation"] = stage_evaluation(
                    stage.staging, evaluation, f"{display_name(dataset)} — {method_title(result)} vs ground truth",
                    plot=figures.plot_error_over_distance, ground_truth=gt_info)
            summary = write_run_outputs(stage, result, dataset=dataset, duration_s=sequence.duration_s,
                                        start_time=start_time, extra=extra, ground_truth=gt_poses,
                                        plot=figures.plot_trajectory_map)
        if recorder is not None:
            recorder.close()  # the .rrd appears only after the other outputs
    except BaseException as exc:
        if recorder is not None:
            recorder.abort()
        if not isinstance(exc, KeyboardInterrupt):
            raise
        close()
        print(interrupted_message("run", stage), file=sys.stderr)
        return 130
    try:
        return finish(summary, result, stage, args.quiet)
    finally:
        if recorder is not None and recorder.path is not None and not args.quiet:
            _print(f"rerun:         {recorder.path} (open it with: rerun {recorder.path})")


