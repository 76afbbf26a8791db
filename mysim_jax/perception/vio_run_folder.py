"""The perception stage on a run folder written by ``scripts/simulate.py``: check the inputs
(cheap, before any long work), render the camera's images of the ground, simulate the IMU,
run VIO (:mod:`mysim_jax.perception.vio`) and dead reckoning
(:mod:`mysim_jax.perception.imu_preintegration`), write trajectories, metrics, plots,
images and a video. ``scripts/perceive.py`` calls it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
import json
from pathlib import Path
import time
from typing import Iterator

import cv2
import numpy as np
from tqdm import tqdm

from mysim_jax.config.scene import load_config
from mysim_jax.core.config_base import ConfigError
from mysim_jax.core.npgeom import matrix_to_quat, quat_to_matrix
from mysim_jax.io.trajectory import read_trajectory_csv
from mysim_jax.perception.camera import (CameraPoses, Intrinsics, PerceptionError, R_BODY_CV, body_pose_columns,
                                         camera_poses, check_sees_ground, intrinsics)
from mysim_jax.perception.ground import GroundTexture
from mysim_jax.perception.imu import ImuConfig, ImuError, simulate_imu
from mysim_jax.perception.imu_preintegration import ImuNoise, ImuSamples, NavState, dead_reckoning
from mysim_jax.perception.metrics import PoseTrack, gauss_markov_fit, plot_estimates, trajectory_errors, write_tum
from mysim_jax.perception.render import Renderer
from mysim_jax.perception.vio import CameraModel, VioEstimator
from mysim_jax.perception.vio_config import VioConfig


@dataclass(frozen=True)
class PerceptionJob:
    """Everything :func:`run_perception` needs, checked by :func:`prepare_perception`."""

    run_dir: str
    columns: dict                  # trajectory columns, name -> (N,)
    config: object                 # the run's SceneConfig
    body: str                      # the UAV body whose pose is estimated
    camera: str                    # its fixed camera
    camera_model: CameraModel
    rows: np.ndarray               # (F,) trajectory rows of the camera's images
    camera_rate: float             # Hz
    gravity: float                 # m/s^2, along -z
    imu_config: object             # mysim_jax.perception.imu.ImuConfig
    imu: ImuSamples                # the simulated IMU's samples, in the body frame
    seed: int                      # of the IMU noise, the ground texture and the image noise


def _fixed_cameras(config) -> dict[str, tuple[str, object]]:
    """Camera name -> (carrying body, CameraConfig) for every camera of the run's quadrotors."""
    return {cam.name: (q.body, cam) for q in config.quadrotors for cam in q.cameras}


def camera_model_from_config(intr: Intrinsics, camera_config) -> CameraModel:
    """The pose on the body of a ``mount: fixed`` camera of a scene (its ``offset`` and ``quat``)."""
    return CameraModel(intr=intr, body_R_cam=quat_to_matrix(np.asarray(camera_config.quat)) @ R_BODY_CV,
                       body_t_cam=np.asarray(camera_config.offset, dtype=float))


def _needed_columns(body: str, camera: str) -> dict[str, str]:
    """Columns the perception stage reads, with what each is for."""
    need = {"time": "the time of every row"}
    for k in ("x", "y", "z", "qw", "qx", "qy", "qz"):
        need[f"{body}_{k}"] = "the body's pose: the ground truth and the initial state"
        need[f"{camera}_{k}"] = "the camera's pose: rendering its images"
    for k in ("vx", "vy", "vz"):
        need[f"{body}_{k}"] = "the body's velocity: the initial state"
    for k in ("ax", "ay", "az", "wx", "wy", "wz"):
        need[f"{body}_{k}"] = "the body's acceleration and angular velocity: simulating the IMU"
    return need


def imu_in_body_frame(data, config) -> ImuSamples:
    """IMU samples turned from the IMU's axes into the body's (``config.orientation``, IMU -> body)."""
    R_bi = quat_to_matrix(np.asarray(config.orientation, dtype=float))
    return ImuSamples(t=np.asarray(data.t, dtype=float), gyro=np.asarray(data.gyro) @ R_bi.T,
                      accel=np.asarray(data.accel) @ R_bi.T)


def _pick_camera(config, camera, body, run_dir):
    """The fixed camera VIO uses (the first on ``body`` when ``camera`` is None), its body
    and its config; PerceptionError naming the options otherwise."""
    cameras = _fixed_cameras(config)
    if not cameras:
        raise PerceptionError(f"{run_dir}: the scene has no cameras; VIO needs a quadrotor with a fixed camera "
                              f"(a 'cameras:' entry with mount: fixed, as in configs/uav_vio_flight.yaml)")
    quad_bodies = sorted({q.body for q in config.quadrotors})
    if body is not None and body not in quad_bodies:
        raise PerceptionError(f"body '{body}' is not a quadrotor of the run (quadrotor bodies: "
                              f"{', '.join(quad_bodies)})")
    if camera is None:
        options = [n for n, (b, c) in cameras.items() if c.mount == "fixed" and (body is None or b == body)]
        if not options:
            listed = ", ".join(f"{n} ({c.mount}, on {b})" for n, (b, c) in cameras.items())
            raise PerceptionError(f"no fixed camera on {'body ' + repr(body) if body else 'any quadrotor'} "
                                  f"(cameras: {listed})")
        camera = options[0]
    if camera not in cameras:
        raise PerceptionError(f"camera '{camera}' is not in the run (cameras: "
                              f"{', '.join(f'{n} (on {b})' for n, (b, _) in cameras.items())})")
    carrier, cam_cfg = cameras[camera]
    if cam_cfg.mount != "fixed":
        raise PerceptionError(f"camera '{camera}' is on a {cam_cfg.mount} mount; VIO needs a camera fixed to the "
                              f"body (its pose on the body is the calibration); choose a fixed camera")
    if body is not None and body != carrier:
        raise PerceptionError(f"camera '{camera}' is on body '{carrier}', not '{body}'")
    return camera, carrier, cam_cfg


def _read_columns(run: Path, body: str, camera: str, t_end: float | None = None) -> dict:
    """The run's trajectory columns (up to ``t_end``), checked for what VIO reads (present,
    finite, at increasing times)."""
    try:
        columns = read_trajectory_csv(run / "trajectory.csv")
    except (OSError, ValueError) as exc:
        raise PerceptionError(f"{run / 'trajectory.csv'}: cannot be read ({exc})") from None
    need = _needed_columns(body, camera)
    missing = [k for k in need if k not in columns]
    if missing:
        why = sorted({need[k] for k in missing})
        raise PerceptionError(f"{run / 'trajectory.csv'} lacks the columns {', '.join(missing)} (needed for "
                              f"{'; '.join(why)}); write the run with scripts/simulate.py")
    t = np.asarray(columns["time"], dtype=float)
    if len(t) < 3 or not np.all(np.diff(t) > 0):
        raise PerceptionError(f"{run / 'trajectory.csv'}: needs at least 3 rows at increasing times")
    if t_end is not None:
        columns = _until(columns, t_end, run)
    bad = [k for k in need if not np.all(np.isfinite(columns[k]))]
    if bad:
        raise PerceptionError(f"{run / 'trajectory.csv'}: non-finite values in {', '.join(bad[:6])}; the run "
                              f"diverged (see its metrics.json)")
    return columns


def _until(columns: dict, t_end: float, run: Path) -> dict:
    """The rows of ``columns`` at times up to ``t_end`` (s)."""
    t = np.asarray(columns["time"], dtype=float)
    if not (np.isfinite(t_end) and t_end > t[0]):
        raise PerceptionError(f"t_end {t_end!r} s: must be after the run's start, t = {t[0]:g} s")
    n = int(np.searchsorted(t, t_end, side="right"))
    if n < 3:
        raise PerceptionError(f"t_end {t_end:g} s keeps only {n} rows of {run / 'trajectory.csv'}; "
                              f"VIO needs at least 3")
    return {k: v[:n] for k, v in columns.items()}


def _image_rows(t: np.ndarray, camera_rate: float) -> np.ndarray:
    """The rows of the run the camera takes its images at (a whole multiple of the output
    interval; at least 3)."""
    output_dt = float(np.median(np.diff(t)))
    stride = (1.0 / camera_rate) / output_dt
    if stride < 1 - 1e-6 or abs(stride - round(stride)) > 1e-6:
        raise PerceptionError(f"camera rate {camera_rate:g} Hz: the images are taken at rows of the run, so the "
                              f"camera period must be a whole multiple of the run's output interval "
                              f"{output_dt:g} s (e.g. {1.0 / output_dt / 10:g} Hz)")
    rows = np.arange(0, len(t), int(round(stride)))
    if len(rows) < 3:
        raise PerceptionError(f"the run ({t[-1] - t[0]:g} s) gives only {len(rows)} images at "
                              f"{camera_rate:g} Hz; VIO needs at least 3")
    return rows


def prepare_perception(run_dir: str | os.PathLike, camera: str | None = None, body: str | None = None,
                       size: tuple[int, int] = (640, 360), camera_rate: float = 20.0, seed: int = 0,
                       imu_config=None, t_end: float | None = None) -> PerceptionJob:
    """Read and check a run folder (``trajectory.csv`` and ``config.yaml``) for perception,
    and simulate the body's IMU (``imu_config``, default the paper's; seeded).

    ``t_end`` (s of the run's time, default its end) keeps only the rows up to that time:
    the part of a run before its UAV crashes or tumbles, when its camera still sees ground.

    Raises :class:`PerceptionError` naming what is wrong: a missing folder or file, a
    body or camera not in the run (listing those that are), a camera that is not on a
    fixed mount, missing trajectory columns (which, and what they are for), an image size
    or camera rate that cannot be used, a camera that does not see the ground, a run the
    IMU cannot sample.
    """
    run = Path(run_dir)
    if not run.is_dir():
        raise PerceptionError(f"{run_dir}: no such run folder; give a folder written by scripts/simulate.py "
                              f"(python scripts/simulate.py configs/uav_vio_flight.yaml --out {run_dir})")
    for name in ("trajectory.csv", "config.yaml"):
        if not (run / name).is_file():
            raise PerceptionError(f"{run_dir}: no {name}; the folder is not a complete run of scripts/simulate.py")
    width, height = size
    for what, value in (("width", width), ("height", height)):
        if not isinstance(value, (int, np.integer)) or value < 16:
            raise PerceptionError(f"image {what} must be a whole number of at least 16 pixels, got {value!r}")
    intr = intrinsics(width=int(width), height=int(height))
    if not (np.isfinite(camera_rate) and camera_rate > 0):
        raise PerceptionError(f"camera rate must be positive (Hz), got {camera_rate!r}")
    try:
        config = load_config(run / "config.yaml")
    except ConfigError as err:
        raise PerceptionError(f"{run / 'config.yaml'}: {err}") from None
    camera, body, cam_cfg = _pick_camera(config, camera, body, run_dir)
    gravity = np.asarray(config.gravity, dtype=float)
    if abs(gravity[0]) > 0 or abs(gravity[1]) > 0 or not gravity[2] < 0:
        raise PerceptionError(f"the run's gravity {gravity.tolist()} is not along -z; the estimator assumes it is")
    columns = _read_columns(run, body, camera, t_end)
    rows = _image_rows(np.asarray(columns["time"], dtype=float), camera_rate)

    poses = camera_poses(columns, camera)
    try:
        check_sees_ground(intr, CameraPoses(name=camera, t=poses.t[rows], R=poses.R[rows], p=poses.p[rows]))
    except PerceptionError as err:
        raise PerceptionError(f"{err}; to estimate the part of the run before that, end it earlier "
                              f"(perceive.py --t-end S)") from None

    imu_config = imu_config or ImuConfig()
    try:
        imu = simulate_imu(columns, body, imu_config, gravity=tuple(gravity.tolist()), seed=seed)
    except ImuError as err:
        raise PerceptionError(f"{run / 'trajectory.csv'}: the IMU cannot be simulated: {err}") from None
    return PerceptionJob(run_dir=str(run_dir), columns=columns, config=config, body=body, camera=camera,
                         camera_model=camera_model_from_config(intr, cam_cfg), rows=rows,
                         camera_rate=float(camera_rate), gravity=float(-gravity[2]), imu_config=imu_config,
                         imu=imu_in_body_frame(imu, imu_config), seed=int(seed))


def true_trajectory(columns: dict, body: str, rows: np.ndarray | None = None) -> PoseTrack:
    """The body's true poses (all rows, or ``rows``) from trajectory columns."""
    pos, quat = body_pose_columns(columns, body)
    t = np.asarray(columns["time"], dtype=float)
    rows = np.arange(len(t)) if rows is None else np.asarray(rows)
    q = quat[rows] / np.linalg.norm(quat[rows], axis=1, keepdims=True)
    return PoseTrack(t=t[rows], p=pos[rows], q=q * np.where(q[:, :1] < 0, -1.0, 1.0))


def initial_state(columns: dict, body: str, row: int = 0) -> NavState:
    """The body's true state at ``row`` (the estimator's initial state)."""
    pos, quat = body_pose_columns(columns, body)
    v = np.array([columns[f"{body}_v{k}"][row] for k in "xyz"], dtype=float)
    return NavState(t=float(columns["time"][row]), R=quat_to_matrix(quat[row]), p=pos[row], v=v)


def render_scene_images(job: PerceptionJob, noise_sigma: float = 1.0,
                        seed: int = 0) -> Iterator[tuple[float, np.ndarray]]:
    """(t s, (H, W) uint8 image) of the job's camera at its image rows, as the full renderer
    (:class:`mysim_jax.perception.render.Renderer`) draws it: the textured ground (the same
    :class:`~mysim_jax.perception.ground.GroundTexture` of ``seed``) under sun and haze, and
    every other UAV, the net, the tethers and the target that come into view (moving
    objects whose features the front end has to reject), in grey levels 0-255 (OpenCV's
    RGB -> grey weights), plus white pixel noise of ``noise_sigma`` grey levels (seeded)."""
    renderer = Renderer(job.config, job.camera_model.intr, texture=GroundTexture(seed=seed))
    rng = np.random.default_rng(seed)
    for frame in renderer.render_many(job.columns, job.camera, [int(r) for r in job.rows], progress=False):
        grey = cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY).astype(np.float64)
        grey += rng.normal(0.0, noise_sigma, grey.shape)
        yield float(frame.t), np.clip(np.rint(grey), 0, 255).astype(np.uint8)


def draw_features(image: np.ndarray, features, text: str = "") -> np.ndarray:
    """(H, W, 3) BGR copy of a grey image with its features: tracked ones green, new ones red."""
    out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    n_old = len(features.ids) - features.n_new
    radius = max(2, image.shape[1] // 200)
    for i, (u, v) in enumerate(features.uv):
        colour = (0, 200, 0) if i < n_old else (0, 0, 255)
        cv2.circle(out, (int(round(u)), int(round(v))), radius, colour, 1, lineType=cv2.LINE_AA)
    if text:
        scale = image.shape[1] / 1280
        cv2.putText(out, text, (int(8 * scale + 2), int(24 * scale + 6)), cv2.FONT_HERSHEY_SIMPLEX, scale,
                    (255, 255, 0), 1, cv2.LINE_AA)
    return out


def _fly_images(job: PerceptionJob, est, out: Path, n_snapshots: int, video: bool, progress: bool):
    """Render the camera's images and feed them to the estimator ``est``; draw the tracked
    features into ``features.mp4`` (with ``video``) and ``n_snapshots`` PNGs. Returns the
    estimates ``(t, R, p, v)`` per image, the snapshots' names and whether a video was written."""
    seed = job.seed
    intr = job.camera_model.intr
    writer = None
    if video:
        writer = cv2.VideoWriter(str(out / "features.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), job.camera_rate,
                                 (intr.width, intr.height))
        if not writer.isOpened():
            writer = None
    snap_at = set(np.linspace(0, len(job.rows) - 1, n_snapshots).round().astype(int).tolist()) if n_snapshots else set()
    ts, Rs, ps, vs = [], [], [], []
    snapshots = []
    frames = render_scene_images(job, seed=seed)
    for i, (t, image) in enumerate(tqdm(frames, total=len(job.rows), desc="render + VIO", unit="img",
                                        disable=not progress)):
        R, p, v = est.add_image(t, image)
        ts.append(t)
        Rs.append(R)
        ps.append(p)
        vs.append(v)
        if writer is not None or i in snap_at:
            d = est.last_frame()
            drawn = draw_features(image, est.features, f"t = {t:.2f} s  features {d['n_features']}  "
                                  f"inliers {d['n_inliers']}" + ("  keyframe" if d["keyframe"] else ""))
            if writer is not None:
                writer.write(drawn)
            if i in snap_at:
                name = f"frame_{t:07.3f}s.png"
                cv2.imwrite(str(out / name), drawn)
                snapshots.append(name)
    if writer is not None:
        writer.release()
    return ts, Rs, ps, vs, snapshots, writer is not None


def _write_estimates(out: Path, vio: PoseTrack, dr: PoseTrack, truth: PoseTrack, diag, v_vio, v_true) -> None:
    """The TUM trajectories, the per-image diagnostics and the velocities."""
    write_tum(out / "trajectory_vio.tum", vio)
    write_tum(out / "trajectory_dead_reckoning.tum", dr)
    write_tum(out / "trajectory_true.tum", truth)
    cols = diag.as_columns()
    np.savetxt(out / "vio_frames.csv", np.column_stack([cols[k].astype(float) for k in cols]), delimiter=",",
               header=",".join(cols), comments="", fmt="%.6g")
    np.savetxt(out / "velocity_vio.csv", np.column_stack([vio.t, v_vio, v_true]), delimiter=",",
               header="t,vx,vy,vz,true_vx,true_vy,true_vz", comments="", fmt="%.9g")


def run_perception(job: PerceptionJob, out_dir: str | os.PathLike, config: VioConfig = VioConfig(),
                   progress: bool = True, rpe_delta_m: float = 10.0, n_snapshots: int = 4,
                   video: bool = True) -> dict:
    """Render the images, run VIO and dead reckoning, write the results into ``out_dir``.

    Writes ``trajectory_vio.tum``, ``trajectory_dead_reckoning.tum``, ``trajectory_true.tum``
    (body poses at the camera's images), ``velocity_vio.csv`` (estimated and true world
    velocity at the images, m/s), ``vio_frames.csv`` (per-image diagnostics,
    :class:`FrameDiagnostics`), ``metrics.json``, the plots of
    :func:`mysim_jax.perception.metrics.plot_estimates`, ``n_snapshots`` images with their
    tracked features (``frame_<t>.png``) and, with ``video``, ``features.mp4`` (the image
    sequence with the features drawn). Returns the metrics.
    """
    out = Path(out_dir)
    seed = job.seed
    imu = job.imu
    t0 = time.perf_counter()
    noise = ImuNoise.from_config(job.imu_config)
    init = initial_state(job.columns, job.body, int(job.rows[0]))
    est = VioEstimator(job.camera_model, imu, init, noise, config, gravity=job.gravity)
    intr = job.camera_model.intr
    ts, Rs, ps, vs, snapshots, video_written = _fly_images(job, est, out, n_snapshots, video, progress)
    vio_wall = time.perf_counter() - t0
    vio = PoseTrack(t=np.asarray(ts), p=np.asarray(ps), q=matrix_to_quat(np.asarray(Rs)))
    t1 = time.perf_counter()
    dr = dead_reckoning(imu, init, vio.t, noise, gravity=job.gravity)
    dr_wall = time.perf_counter() - t1
    truth = true_trajectory(job.columns, job.body, job.rows)
    diag = est.diagnostics()
    v_true = np.stack([np.asarray(job.columns[f"{job.body}_v{k}"], float)[job.rows] for k in "xyz"], axis=-1)
    v_vio = np.asarray(vs)
    _write_estimates(out, vio, dr, truth, diag, v_vio, v_true)
    errors = {"vio": trajectory_errors(truth, vio, rpe_delta_m),
              "dead_reckoning": trajectory_errors(truth, dr, rpe_delta_m)}
    # what a policy flying on these estimates sees: unaligned errors, as Gauss-Markov processes
    error_model = {"position_m": gauss_markov_fit(vio.t, vio.p - truth.p),
                   "velocity_m_s": gauss_markov_fit(vio.t, v_vio - v_true)}
    plots = plot_estimates(truth, {"VIO": vio, "dead reckoning": dr}, out,
                           title=f"{job.config.name}: {job.body} from {job.camera} + IMU", diagnostics=diag)
    distance = errors["vio"]["distance_m"]
    v_ate, d_ate = errors["vio"]["ate_aligned_rmse_m"], errors["dead_reckoning"]["ate_aligned_rmse_m"]
    metrics = {
        "run": job.run_dir,
        "scene": job.config.name,
        "body": job.body,
        "camera": job.camera,
        "image_size": [intr.width, intr.height],
        "camera_rate_hz": job.camera_rate,
        "seed": seed,
        "initial_state": "true pose and velocity of the body at the first image (ground truth); IMU bias zero",
        "imu": job.imu_config.model_dump(mode="json"),
        "frames": len(vio.t),
        "keyframes": int(diag.keyframe.sum()),
        "landmarks": int(est.n_landmarks),
        "backend_resets": int(est.n_resets),
        "imu_shock_intervals": int(est.n_shocks),
        "mean_features": float(diag.n_features.mean()),
        "mean_tracked_inliers": float(diag.n_inliers[1:].mean()) if len(diag.t) > 1 else 0.0,
        "errors": errors,
        "error_model": error_model,
        "summary": {
            "distance_m": distance,
            "vio_ate_aligned_rmse_m": v_ate,
            "vio_ate_rmse_m": errors["vio"]["ate_rmse_m"],
            "dead_reckoning_ate_aligned_rmse_m": d_ate,
            "dead_reckoning_ate_rmse_m": errors["dead_reckoning"]["ate_rmse_m"],
            "vio_ate_percent_of_distance": 100.0 * v_ate / distance if distance > 0 else None,
            "dead_reckoning_over_vio_ate": d_ate / v_ate if v_ate > 0 else None,
        },
        "wall_time_s": {"render_imu_vio": vio_wall, "dead_reckoning": dr_wall},
        "plots": plots,
        "snapshots": snapshots,
        "video": "features.mp4" if video_written else None,
        "vio_config": {k: (v if not hasattr(v, "__dataclass_fields__") else vars(v))
                       for k, v in vars(config).items()},
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics


def vio_summary_lines(metrics: dict, wall: float, out) -> list[str]:
    """What ``scripts/perceive.py`` prints after a VIO run: the distance flown, the errors of
    VIO and of dead reckoning, the back end's resets."""
    lines = []
    s = metrics["summary"]
    lines.append(f"{metrics['scene']}: {metrics['body']} from {metrics['camera']} + IMU, {metrics['frames']} images "
                 f"({metrics['keyframes']} keyframes) in {wall:.1f} s; wrote {out}/")
    lines.append(f"  distance flown {s['distance_m']:.2f} m")
    if metrics.get("backend_resets"):
        lines.append(f"  the VIO back end failed and was re-initialised {metrics['backend_resets']} time(s)")
    for name, key in (("VIO", "vio"), ("dead reckoning", "dead_reckoning")):
        e = metrics["errors"][key]
        rpe = ("" if e["rpe_translation_rmse_m"] is None else
               f", RPE over {e['rpe_delta_m']:g} m {e['rpe_translation_rmse_m']:.4g} m / "
               f"{e['rpe_rotation_rmse_deg']:.3g} deg")
        lines.append(f"  {name}: ATE {e['ate_aligned_rmse_m']:.4g} m aligned (SE(3)), {e['ate_rmse_m']:.4g} m not aligned"
                     f"{rpe}")
    if s["vio_ate_percent_of_distance"] is not None:
        lines.append(f"  VIO ATE (aligned) = {s['vio_ate_percent_of_distance']:.3g} % of the distance; dead reckoning's "
                     f"is {s['dead_reckoning_over_vio_ate']:.3g} x VIO's")
    return lines
