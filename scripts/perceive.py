#!/usr/bin/env python
"""Estimate a UAV's pose from its fixed camera and IMU (visual-inertial odometry) on a saved run.

    python scripts/simulate.py configs/uav_vio_flight.yaml --out runs/vio_flight
    python scripts/perceive.py runs/vio_flight --out runs/vio_flight/perception

Reads RUN_DIR (``trajectory.csv`` and ``config.yaml`` of scripts/simulate.py), renders the
camera's images at ``--camera-rate`` Hz and ``--size`` pixels,
simulates the UAV's IMU (paper Table IMU_simulator), runs VIO and IMU-only dead reckoning
(mysim_jax/perception/vio.py; the initial state is the true one at the first image) and
writes into OUT: ``trajectory_vio.tum``, ``trajectory_dead_reckoning.tum``,
``trajectory_true.tum`` (t x y z qx qy qz qw), ``metrics.json`` (ATE with and without SE(3)
alignment, RPE, distance flown, from evo; and a Gauss-Markov fit of the unaligned position and
velocity errors, ``error_model``), ``velocity_vio.csv``, ``vio_frames.csv`` (features, inliers,
keyframes per image), plots (``estimation_paths.png``, ``estimation_error.png``,
``vio_features.png``), a few images with their features, ``features.mp4`` and
``replay.html`` (the run in 3D with a time slider, as scripts/simulate.py writes it).
The images are the full renderer's (mysim_jax/perception/render.py): the textured ground
and every other UAV, the net, the tethers and the target in view.

``--camera`` picks a fixed camera (default: the first one, on ``--body`` if given). Bad
input (a missing folder or column, an unknown body or camera, a zero image size, a camera
that sees no ground, an unusable OUT) is a one-line error and exit code 2 before any long
work; outputs are written to a temporary folder and moved into OUT only when complete.
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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", help="run folder written by scripts/simulate.py")
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
    args = parser.parse_args(argv)

    from mysim_jax.io.output import OutputError, check_output_dir
    from mysim_jax.perception.camera import PerceptionError
    from mysim_jax.perception.vio import prepare_perception, run_perception

    try:
        out = check_output_dir(args.out)
        job = prepare_perception(args.run_dir, camera=args.camera, body=args.body, size=args.size,
                                 camera_rate=args.camera_rate, seed=args.seed)
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
    s = metrics["summary"]
    print(f"{metrics['scene']}: {metrics['body']} from {metrics['camera']} + IMU, {metrics['frames']} images "
          f"({metrics['keyframes']} keyframes) in {wall:.1f} s; wrote {out}/")
    print(f"  distance flown {s['distance_m']:.2f} m")
    if metrics.get("backend_resets"):
        print(f"  the VIO back end failed and was re-initialised {metrics['backend_resets']} time(s)")
    for name, key in (("VIO", "vio"), ("dead reckoning", "dead_reckoning")):
        e = metrics["errors"][key]
        rpe = ("" if e["rpe_translation_rmse_m"] is None else
               f", RPE over {e['rpe_delta_m']:g} m {e['rpe_translation_rmse_m']:.4g} m / "
               f"{e['rpe_rotation_rmse_deg']:.3g} deg")
        print(f"  {name}: ATE {e['ate_aligned_rmse_m']:.4g} m aligned (SE(3)), {e['ate_rmse_m']:.4g} m not aligned"
              f"{rpe}")
    if s["vio_ate_percent_of_distance"] is not None:
        print(f"  VIO ATE (aligned) = {s['vio_ate_percent_of_distance']:.3g} % of the distance; dead reckoning's "
              f"is {s['dead_reckoning_over_vio_ate']:.3g} x VIO's")
    return 0


if __name__ == "__main__":
    sys.exit(main())
