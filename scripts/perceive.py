#!/usr/bin/env python
"""Estimate a UAV's pose from its fixed camera and IMU (visual-inertial odometry) on a saved run.

    python scripts/simulate.py configs/uav_vio_flight.yaml --out runs/vio_flight
    python scripts/perceive.py runs/vio_flight --out runs/vio_flight/perception

Reads RUN_DIR (``trajectory.csv`` and ``config.yaml`` of scripts/simulate.py), renders the
camera's images at ``--camera-rate`` Hz and ``--size`` pixels,
simulates the UAV's IMU (paper Table IMU_simulator), runs VIO and IMU-only dead reckoning
(mysim_jax/perception/vio_run_folder.py, running vio.py and imu_preintegration.py; the initial
state is the true one at the first image) and writes into OUT: ``trajectory_vio.tum``, ``trajectory_dead_reckoning.tum``,
``trajectory_true.tum`` (t x y z qx qy qz qw), ``metrics.json`` (ATE with and without SE(3)
alignment, RPE, distance flown, from evo; and a Gauss-Markov fit of the unaligned position and
velocity errors, ``error_model``), ``velocity_vio.csv``, ``vio_frames.csv`` (features, inliers,
keyframes per image), plots (``estimation_paths.png``, ``estimation_error.png``,
``vio_features.png``), a few images with their features, ``features.mp4`` and
``replay.html`` (the run in 3D with a time slider, as scripts/simulate.py writes it).
The images are the full renderer's (mysim_jax/perception/render.py): the textured ground
and every other UAV, the net, the tethers and the target in view.

``--camera`` picks a fixed camera (default: the first one, on ``--body`` if given);
``--t-end S`` estimates the run up to S seconds (e.g. before its UAV tumbles). Bad input (a
missing folder or column, an unknown body or camera, a zero image size, a camera that sees
no ground, an unusable OUT) is a one-line error and exit code 2 before any long work;
outputs are written to a temporary folder and moved into OUT only when complete.

Target tracking (``--track CONFIG``, mysim_jax/perception/track.py and localize.py)::

    python scripts/perceive.py --track configs/capture_falling_gimbals.yaml --out runs/track_falling

simulates CONFIG (a scene with a target and a gimbal camera on its UAVs) with every gimbal
steered, frame by frame, from its own rendered images (``--camera-rate`` Hz, ``--size``
pixels, the ground-truth oracle detector with ``--det-noise`` px and ``--miss-rate``, or
the learned one with ``--detector``), localises the target from all cameras each frame
and writes into OUT: ``metrics.json`` (fraction of frames with the target in view, pixel
error of its centre from the image centre, localisation error mean/p95 per fusion method,
the size-range fits of the paper's and the pinhole relation), ``tracking.npz`` (per frame
and camera: poses, gimbal angles and commands, detections, true boxes), ``trajectory.csv``
and ``config.yaml`` (the run, one row per frame), ``localisation.csv`` and the plots
``pointing.png``, ``localisation_error.png``, ``localisation_paths.png``, ``size_range.png``.
"""

from __future__ import annotations

import argparse
import re
import sys
import time


def _size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"'{text}' is not WIDTHxHEIGHT in pixels (e.g. 640x360)")
    return int(m.group(1)), int(m.group(2))


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", nargs="?", help="run folder written by scripts/simulate.py (VIO mode)")
    parser.add_argument("--track", metavar="CONFIG", help="gimbal tracking + target localisation: simulate "
                        "CONFIG closed loop (instead of VIO on RUN_DIR)")
    parser.add_argument("--t-end", type=float, metavar="S", help="--track: simulated time (default: the config's); VIO: "
                        "estimate the run up to this time (default: to its end), e.g. before its UAV crashes")
    parser.add_argument("--detector", choices=("oracle", "learned"), default="oracle",
                        help="--track: the ground-truth box with noise (oracle, default) or the learned detector "
                        "(mysim_jax.perception.detect)")
    parser.add_argument("--weights", metavar="MSGPACK", help="--track, learned: detector weights written by "
                        "scripts/train_detector.py (default: the committed docs/detector/detector.msgpack)")
    parser.add_argument("--full-frame", action="store_true", help="--track, learned: search the whole image "
                        "every frame (default: around where the tracker expects the target, the whole image when "
                        "it has lost it)")
    parser.add_argument("--no-teammates", action="store_true", help="--track, learned: do not tell the region "
                        "detector where the team's own UAVs are expected in each image (default: it is told, from "
                        "their positions with VIO-like errors, and drops detections a teammate explains)")
    parser.add_argument("--det-noise", type=float, default=1.0, metavar="PX", help="--track, oracle: box edge noise "
                        "(px, default 1)")
    parser.add_argument("--miss-rate", type=float, default=0.0, help="--track, oracle: probability of a missed "
                        "detection (default 0)")
    parser.add_argument("--range-sigma", type=float, metavar="REL", help="--track: relative range noise the "
                        "fusion assumes for ranges from box sizes (default by the target: 0.05 for a sphere, 0.3 for "
                        "a drone, whose box depends on its attitude)")
    parser.add_argument("--no-cue", action="store_true", help="--track: no start cue; the cameras search")
    parser.add_argument("--pose-noise", type=float, nargs=2, metavar=("M", "RAD"), help="--track: also localise "
                        "with camera poses perturbed by these position and rotation standard deviations")
    parser.add_argument("--pose-seeds", type=int, default=0, metavar="N", help="--track, with --pose-noise: also "
                        "localise with N draws of the pose noise (seeds 0..N-1), from the detections and from the true "
                        "boxes (what the pose errors alone cost; default 0: the one draw of --seed)")
    parser.add_argument("--pose-seed-start", type=int, default=0, metavar="K", help="--track, with --pose-seeds: "
                        "the first draw's seed (default 0: draws K..K+N-1)")
    parser.add_argument("--team-ranging", type=float, nargs=2, metavar=("M", "BIAS_M"), help="--track, with "
                        "--pose-seeds: the UAVs also measure their distances to each other every frame (UWB-like: "
                        "white noise of M and a constant bias per pair drawn with spread BIAS_M) and the "
                        "self-calibration of the pose biases uses them (reported beside the one without)")
    parser.add_argument("--pose-noise-time", type=float, default=0.0, metavar="S", help="--track: correlation "
                        "time of the pose noise (Gauss-Markov over the frames, as VIO errors; default 0: white)")
    parser.add_argument("--out", required=True, help="output folder (created if missing)")
    parser.add_argument("--camera", help="fixed camera to use (default: the first fixed camera)")
    parser.add_argument("--body", help="UAV body to estimate (default: the camera's)")
    parser.add_argument("--size", type=_size, default=(640, 360), metavar="WxH", help="image size (default 640x360)")
    parser.add_argument("--camera-rate", type=float, default=20.0, metavar="HZ", help="image rate (default 20 Hz)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the IMU noise, the ground texture and the "
                        "image noise (default 0)")
    parser.add_argument("--no-video", action="store_true", help="do not write features.mp4")
    parser.add_argument("--no-replay", action="store_true", help="do not write replay.html (the run in 3D)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.track is not None and args.run_dir is not None:
        parser.error("give either RUN_DIR (VIO) or --track CONFIG (tracking), not both")
    if args.track is None and args.run_dir is None:
        parser.error("RUN_DIR is required (or --track CONFIG)")
    from mysim_jax.core.extras import MissingExtra, available, require

    try:
        require("scripts/perceive.py", "gtsam", "evo", "allantools")
    except MissingExtra as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.track is not None:
        return _track(args)
    if not args.no_replay and not available("plotly"):
        print("note: replay.html skipped: the HTML replay needs plotly (pip install -e '.[plots]')", file=sys.stderr)
        args.no_replay = True

    from mysim_jax.io.output import OutputError, check_output_dir
    from mysim_jax.perception.camera import PerceptionError
    from mysim_jax.perception.vio_run_folder import prepare_perception, run_perception, vio_summary_lines

    try:
        out = check_output_dir(args.out)
        job = prepare_perception(args.run_dir, camera=args.camera, body=args.body, size=args.size,
                                 camera_rate=args.camera_rate, seed=args.seed, t_end=args.t_end)
    except (OutputError, PerceptionError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    from mysim_jax.io.output import staged_output

    t0 = time.perf_counter()
    with staged_output(out) as tmp:
        metrics = run_perception(job, tmp, progress=not args.no_progress, video=not args.no_video)
        if not args.no_replay:
            from mysim_jax.io.replay import write_replay_html

            write_replay_html(job.columns, job.config, tmp / "replay.html",
                              title=f"{job.config.name} (perceived: {job.body} from {job.camera})")
    wall = time.perf_counter() - t0
    print("\n".join(vio_summary_lines(metrics, wall, out)))
    return 0


def _track(args) -> int:
    """--track mode: closed-loop gimbal tracking and target localisation (see the module doc)."""
    from mysim_jax.config.scene import ConfigError, dump_config, load_config
    from mysim_jax.io.output import OutputError, check_output_dir
    from mysim_jax.perception.camera import PerceptionError, intrinsics

    try:
        config = load_config(args.track)
        out = check_output_dir(args.out)
        from mysim_jax.perception.track import check_tracking_scene, make_detector, make_pose_noise

        check_tracking_scene(config)
        if config.sim.precision == "float64":
            raise PerceptionError(f"{args.track}: tracking runs the scene in float32; set sim.precision: float32")
        if args.t_end is not None and not args.t_end > 0:
            raise PerceptionError(f"--t-end must be positive, got {args.t_end}")
        if args.range_sigma is None:
            from mysim_jax.perception.localize import RANGE_SIGMA
            from mysim_jax.perception.render_models import auto_target_style

            args.range_sigma = RANGE_SIGMA[auto_target_style(config)]
        if not args.range_sigma > 0:
            raise PerceptionError(f"--range-sigma must be positive, got {args.range_sigma}")
        if args.pose_seeds < 0 or (args.pose_seeds and args.pose_noise is None):
            raise PerceptionError(f"--pose-seeds {args.pose_seeds}: a count >= 0, and only with --pose-noise")
        if args.pose_seed_start < 0 or (args.pose_seed_start and not args.pose_seeds):
            raise PerceptionError(f"--pose-seed-start {args.pose_seed_start}: a seed >= 0, and only with --pose-seeds")
        ranging = None
        if args.team_ranging is not None:
            if not args.pose_seeds:
                raise PerceptionError("--team-ranging needs --pose-seeds (the draws it is reported over)")
            from mysim_jax.perception.pose_bias import TeamRanging

            ranging = TeamRanging(sigma_m=args.team_ranging[0], bias_m=args.team_ranging[1])
        if not args.camera_rate > 0:
            raise PerceptionError(f"--camera-rate must be positive, got {args.camera_rate}")
        intr = intrinsics(width=args.size[0], height=args.size[1])
        detector = make_detector(args.detector, args.weights, args.det_noise, args.miss_rate, args.seed,
                                 region=not args.full_frame)
        pose_noise = None
        if args.pose_noise is not None:
            pose_noise = make_pose_noise(args.pose_noise[0], args.pose_noise[1], args.pose_noise_time, args.seed)
    except (ConfigError, OutputError, PerceptionError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    from mysim_jax.core.machine import machine
    from mysim_jax.io.output import staged_output
    from mysim_jax.io.trajectory import write_trajectory_csv
    from mysim_jax.perception.track import run_tracking
    from mysim_jax.perception.track_report import tracking_summary_lines, write_tracking_report

    t0 = time.perf_counter()
    try:
        record = run_tracking(config, detector, intr, frame_rate=args.camera_rate, t_end=args.t_end,
                              initial_cue=not args.no_cue, range_sigma=args.range_sigma,
                              team_seed=None if args.no_teammates else args.seed, progress=not args.no_progress)
    except PerceptionError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    wall = time.perf_counter() - t0
    with staged_output(out) as tmp:
        (tmp / "config.yaml").write_text(dump_config(config))
        write_trajectory_csv(tmp / "trajectory.csv", record.columns)
        extra = {"scene": config.name, "frames": int(len(record.t)), "frame_rate_hz": args.camera_rate,
                 "image": list(args.size), "detector": args.detector, "det_noise_px": args.det_noise,
                 "miss_rate": args.miss_rate, "initial_cue": not args.no_cue, "wall_time_s": wall,
                 "machine": machine()}
        if hasattr(detector, "stats"):
            extra["detection_time"] = detector.stats()
        metrics = write_tracking_report(record, tmp, pose_noise=pose_noise, extra=extra, progress=not args.no_progress,
                                        range_sigma=args.range_sigma, pose_seeds=args.pose_seeds,
                                        first_pose_seed=args.pose_seed_start, ranging=ranging)
    print("\n".join(tracking_summary_lines(config.name, record, metrics, args.camera_rate, wall, out)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
