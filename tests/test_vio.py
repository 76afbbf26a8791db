"""Visual-inertial odometry (mysim_jax/perception/vio.py, imu_preintegration.py, features.py, metrics.py).

The flights here are analytic (no simulator): a figure-eight with rolling, pitching and
yawing attitude whose positions, velocities, accelerations and body rates are exact, so
the IMU samples derived from them are exact too. The 30 s flight of
configs/uav_vio_flight.yaml is measured by scripts/perceive.py, not here.
"""

from __future__ import annotations

import numpy as np
import pytest

from mysim_jax.core.npgeom import matrix_to_quat, quat_to_matrix
from mysim_jax.perception.camera import R_BODY_CV, intrinsics, project
from mysim_jax.perception.features import FeatureTracker, relative_rotation
from mysim_jax.perception.ground import GroundTexture, view_ground
from mysim_jax.perception.metrics import PoseTrack, read_tum, trajectory_errors, write_tum
from mysim_jax.perception.imu_preintegration import ImuNoise, ImuSamples, NavState, dead_reckoning
from mysim_jax.perception.vio import CameraModel, run_vio
from mysim_jax.perception.vio_config import VioConfig

# The paper's fixed camera (Table camera offset), pitched 50 deg down as in
# configs/uav_vio_flight.yaml: quat = rotation about the body y axis, camera -> body.
CAMERA_OFFSET = np.array([0.03, 0.0, -0.03])
CAMERA_QUAT = np.array([np.cos(np.radians(25)), 0.0, np.sin(np.radians(25)), 0.0])
GRAVITY = np.array([0.0, 0.0, -9.81])


def _euler_rotation(roll, pitch, yaw):
    """(N, 3, 3) R = Rz(yaw) Ry(pitch) Rx(roll), body -> world."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    return np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1),
    ], -2)


def synthetic_flight(duration: float, rate: float = 200.0, body: str = "uav0", camera: str = "cam_fixed",
                     camera_quat=CAMERA_QUAT) -> dict:
    """Trajectory columns (as scripts/simulate.py writes them) of an analytic flight.

    Figure-eight x = 1.5 sin wt, y = 0.75 sin 2wt, z = 3 + 0.2 sin wt (w = 2 pi / 6 s),
    roll 0.1 sin 1.3t, pitch 0.12 sin(1.1t + 0.5), yaw 0.5 sin 0.8t (rad); the camera body
    rides at CAMERA_OFFSET turned by ``camera_quat`` (camera -> body).
    """
    t = np.arange(int(round(duration * rate)) + 1) / rate
    w = 2 * np.pi / 6.0
    s1, c1, s2, c2 = np.sin(w * t), np.cos(w * t), np.sin(2 * w * t), np.cos(2 * w * t)
    p = np.stack([1.5 * s1, 0.75 * s2, 3.0 + 0.2 * s1], -1)
    v = np.stack([1.5 * w * c1, 1.5 * w * c2, 0.2 * w * c1], -1)
    a = np.stack([-1.5 * w ** 2 * s1, -3.0 * w ** 2 * s2, -0.2 * w ** 2 * s1], -1)
    roll, droll = 0.1 * np.sin(1.3 * t), 0.13 * np.cos(1.3 * t)
    pitch, dpitch = 0.12 * np.sin(1.1 * t + 0.5), 0.132 * np.cos(1.1 * t + 0.5)
    yaw, dyaw = 0.5 * np.sin(0.8 * t), 0.4 * np.cos(0.8 * t)
    # body rates of R = Rz Ry Rx from the Euler rates
    omega = np.stack([droll - dyaw * np.sin(pitch),
                      dpitch * np.cos(roll) + dyaw * np.sin(roll) * np.cos(pitch),
                      -dpitch * np.sin(roll) + dyaw * np.cos(roll) * np.cos(pitch)], -1)
    R = _euler_rotation(roll, pitch, yaw)
    q = matrix_to_quat(R)
    cols = {"time": t}
    for k, axis in enumerate("xyz"):
        cols[f"{body}_{axis}"] = p[:, k]
    for k, axis in enumerate("wxyz"):
        cols[f"{body}_q{axis}"] = q[:, k]
    for key, arr in (("v", v), ("a", a), ("w", omega)):
        for k, axis in enumerate("xyz"):
            cols[f"{body}_{key}{axis}"] = arr[:, k]
    R_cam = R @ quat_to_matrix(np.asarray(camera_quat, dtype=float))
    p_cam = p + R @ CAMERA_OFFSET
    q_cam = matrix_to_quat(R_cam)
    for k, axis in enumerate("xyz"):
        cols[f"{camera}_{axis}"] = p_cam[:, k]
    for k, axis in enumerate("wxyz"):
        cols[f"{camera}_q{axis}"] = q_cam[:, k]
    return cols


def write_synthetic_run(run_dir, duration: float, camera_quat=CAMERA_QUAT) -> dict:
    """A run folder as scripts/simulate.py writes it (config.yaml, trajectory.csv) holding
    the analytic flight; the config is configs/uav_vio_flight.yaml with the camera's quat."""
    from mysim_jax.config.scene import dump_config, load_config
    from mysim_jax.io.trajectory import write_trajectory_csv

    from conftest import CONFIGS

    quat = "[" + ",".join(f"{x:.12g}" for x in camera_quat) + "]"
    config = load_config(CONFIGS / "uav_vio_flight.yaml",
                         [f"sim.t_end={duration}", f"quadrotors.0.cameras.0.quat={quat}"])
    cols = synthetic_flight(duration, rate=1.0 / config.sim.output_dt, camera_quat=camera_quat)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.yaml").write_text(dump_config(config))
    write_trajectory_csv(run_dir / "trajectory.csv", cols)
    return cols


def _truth(cols, body="uav0"):
    p = np.stack([cols[f"{body}_{a}"] for a in "xyz"], -1)
    q = np.stack([cols[f"{body}_q{a}"] for a in "wxyz"], -1)
    v = np.stack([cols[f"{body}_v{a}"] for a in "xyz"], -1)
    return p, q, v


def _imu(cols, accel_bias=(0.0, 0.0, 0.0), gyro_bias=(0.0, 0.0, 0.0), noise: ImuNoise | None = None, seed=0,
         body="uav0"):
    """Exact IMU samples of the analytic flight, plus constant biases and white noise."""
    _, q, _ = _truth(cols, body)
    R = quat_to_matrix(q)
    a = np.stack([cols[f"{body}_a{k}"] for k in "xyz"], -1)
    w = np.stack([cols[f"{body}_w{k}"] for k in "xyz"], -1)
    f = np.einsum("nji,nj->ni", R, a - GRAVITY)
    t = cols["time"]
    rng = np.random.default_rng(seed)
    if noise is not None:
        rate = 1.0 / (t[1] - t[0])
        f = f + rng.standard_normal(f.shape) * noise.accel_noise_density * np.sqrt(rate)
        w = w + rng.standard_normal(w.shape) * noise.gyro_noise_density * np.sqrt(rate)
    return ImuSamples(t=t, gyro=w + np.asarray(gyro_bias), accel=f + np.asarray(accel_bias))


def _camera_model(intr):
    return CameraModel(intr=intr, body_R_cam=quat_to_matrix(CAMERA_QUAT) @ R_BODY_CV, body_t_cam=CAMERA_OFFSET)


def _camera_poses(cols, rows, camera="cam_fixed"):
    """(F, 3, 3) OpenCV camera -> world rotations and (F, 3) centres at ``rows``."""
    q = np.stack([cols[f"{camera}_q{a}"] for a in "wxyz"], -1)[rows]
    p = np.stack([cols[f"{camera}_{a}"] for a in "xyz"], -1)[rows]
    return quat_to_matrix(q) @ R_BODY_CV, p


def _render(intr, R, p, texture, rng, noise=1.0):
    albedo = view_ground(intr, R, p, texture).albedo
    return np.clip(np.rint(albedo * 255 + rng.normal(0, noise, albedo.shape)), 0, 255).astype(np.uint8)


# --- the flight itself ------------------------------------------------------------


def test_synthetic_flight_is_consistent():
    """The analytic flight's rates and accelerations are the derivatives of its poses."""
    cols = synthetic_flight(2.0, rate=1000.0)
    p, q, v = _truth(cols)
    dt = 1e-3
    np.testing.assert_allclose((p[2:] - p[:-2]) / (2 * dt), v[1:-1], atol=1e-5)
    a = np.stack([cols[f"uav0_a{k}"] for k in "xyz"], -1)
    np.testing.assert_allclose((v[2:] - v[:-2]) / (2 * dt), a[1:-1], atol=1e-5)
    R = quat_to_matrix(q)
    rel = np.einsum("nji,njk->nik", R[:-2], R[2:])          # R_{k-1}^T R_{k+1} = exp(2 dt w)
    w_fd = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0],
                     rel[:, 1, 0] - rel[:, 0, 1]], -1) / (4 * dt)
    w = np.stack([cols[f"uav0_w{k}"] for k in "xyz"], -1)
    np.testing.assert_allclose(w_fd, w[1:-1], atol=1e-5)


# --- front end --------------------------------------------------------------------


@pytest.fixture(scope="module")
def texture():
    return GroundTexture(seed=3)


def test_klt_tracks_follow_the_ground(texture):
    """Features tracked through 20 images (1 s at 20 Hz, 320 x 180) stay on the true
    projections of the ground points they started on. Measured: median 0.21 px, 95th
    percentile 0.85 px over tracks up to 20 images long; 96 % of the last image's
    features were tracked from the one before."""
    intr = intrinsics(width=320, height=180)
    cols = synthetic_flight(1.0)
    rows = np.arange(0, 201, 10)
    Rs, ps = _camera_poses(cols, rows)
    tracker = FeatureTracker(intr)
    rng = np.random.default_rng(0)
    start = {}
    errors = []
    for R, p in zip(Rs, ps):
        view = view_ground(intr, R, p, texture)
        image = np.clip(np.rint(view.albedo * 255 + rng.normal(0, 1, view.albedo.shape)), 0, 255).astype(np.uint8)
        ff = tracker.track(image)
        for tid, uv in zip(ff.ids.tolist(), ff.uv):
            if tid not in start:
                ray = R @ np.linalg.solve(intr.K, np.r_[uv, 1.0])
                start[tid] = p + (-p[2] / ray[2]) * ray            # the ground point under the new corner
            else:
                errors.append(np.linalg.norm(project(intr, R, p, start[tid])[0] - uv))
    errors = np.asarray(errors)
    assert len(errors) > 1000
    assert ff.n_tracked > 0.6 * len(ff.ids)
    assert np.median(errors) < 2.0 and np.percentile(errors, 95) < 8.0


def test_rotation_from_tracked_features(texture):
    """The camera turns about its optical centre by 6 deg (pure rotation, so the images
    are related by the homography K R K^-1): the rotation recovered from the tracked
    features matches the true one (its inverse would be 12 deg off). Measured error 0.02 deg."""
    intr = intrinsics(width=320, height=180)
    R0 = quat_to_matrix(CAMERA_QUAT) @ R_BODY_CV            # level body, camera pitched down
    p = np.array([0.0, 0.0, 3.0])
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    angle = np.radians(6.0)
    tracker = FeatureTracker(intr)
    rng = np.random.default_rng(1)
    from mysim_jax.perception.imu_preintegration import _so3_exp

    first = tracker.track(_render(intr, R0, p, texture, rng))
    for s in np.linspace(0, 1, 7)[1:]:
        last = tracker.track(_render(intr, _so3_exp(axis * angle * s) @ R0, p, texture, rng))
    _, ia, ib = np.intersect1d(first.ids, last.ids, return_indices=True)
    assert len(ia) > 50
    import cv2

    H, _ = cv2.findHomography(first.uv[ia], last.uv[ib], cv2.RANSAC, 1.0)
    M = np.linalg.solve(intr.K, H @ intr.K)                  # ~ R_10 up to scale
    U, _, Vt = np.linalg.svd(M / np.cbrt(np.linalg.det(M)))
    R_est = U @ Vt
    R_true = (_so3_exp(axis * angle) @ R0).T @ R0             # camera 0 -> camera 1
    err = np.degrees(np.arccos(np.clip((np.trace(R_est.T @ R_true) - 1) / 2, -1, 1)))
    assert err < 0.2


def _epipolar_distance_px(intr, R_a, p_a, R_b, p_b, uv_a, uv_b):
    """(n,) px, distance of each pixel of view b from the epipolar line of its match in a."""
    R_ba = R_b.T @ R_a                                      # camera a -> camera b
    t_ba = R_b.T @ (p_a - p_b)
    E = np.array([[0, -t_ba[2], t_ba[1]], [t_ba[2], 0, -t_ba[0]], [-t_ba[1], t_ba[0], 0]]) @ R_ba
    Kinv = np.linalg.inv(intr.K)
    F = Kinv.T @ E @ Kinv
    lines = np.c_[uv_a, np.ones(len(uv_a))] @ F.T           # lines in image b
    return np.abs(np.sum(lines * np.c_[uv_b, np.ones(len(uv_b))], axis=1)) / np.hypot(lines[:, 0], lines[:, 1])


def test_essential_matrix_ransac_rejects_outliers(texture):
    """In three view pairs 0.25 s apart, a quarter of the matches are moved by 5-40 px in
    random directions. Of those moved at least 2 px off their true epipolar line (a move
    along the line cannot be seen by any two-view test), most are flagged as outliers of
    the essential matrix, and the true matches are kept. Not all are flagged: the ground
    is a plane, and the views of a plane fit a family of essential matrices, some of
    which pass near a moved match. Measured: 91 % flagged (of 64), 100 % kept."""
    intr = intrinsics(width=320, height=180)
    cols = synthetic_flight(2.0)
    rng = np.random.default_rng(2)
    flagged, kept = [], []
    for start in (0, 100, 200):
        Rs, ps = _camera_poses(cols, np.arange(start, start + 51, 10))
        tracker = FeatureTracker(intr)
        frames = [tracker.track(_render(intr, R, p, texture, rng)) for R, p in zip(Rs, ps)]
        _, ia, ib = np.intersect1d(frames[0].ids, frames[-1].ids, return_indices=True)
        a, b = frames[0].uv[ia], frames[-1].uv[ib].copy()
        bad = rng.random(len(a)) < 0.25
        angle = rng.uniform(0, 2 * np.pi, bad.sum())
        b[bad] += rng.uniform(5, 40, bad.sum())[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1)
        off_line = _epipolar_distance_px(intr, Rs[0], ps[0], Rs[-1], ps[-1], a, b) > 2.0
        _, _, inliers = relative_rotation(intr, a, b, ransac_px=1.0)
        flagged += (~inliers[bad & off_line]).tolist()
        kept += inliers[~bad].tolist()
    assert len(flagged) > 40
    assert np.mean(flagged) > 0.8
    assert np.mean(kept) > 0.95


# --- IMU integration and the estimator ---------------------------------------------


def _dead_reckoning_error(rate: float, duration: float = 10.0, **bias) -> float:
    """Largest position error (m) of dead reckoning exact IMU samples at ``rate`` Hz."""
    cols = synthetic_flight(duration, rate=rate)
    p, q, v = _truth(cols)
    init = NavState(t=0.0, R=quat_to_matrix(q[0]), p=p[0], v=v[0])
    rows = np.arange(0, len(cols["time"]), int(rate // 20))
    dr = dead_reckoning(_imu(cols, **bias), init, cols["time"][rows])
    return float(np.max(np.linalg.norm(dr.p - p[rows], axis=1)))


def test_dead_reckoning_is_second_order():
    """Dead reckoning of exact IMU samples follows the analytic flight, and its error falls
    4x when the IMU rate doubles (each sample interval is integrated at its midpoint).
    Measured over 10 s: 5.4e-4 m at 200 Hz, 1.4e-4 m at 400 Hz."""
    e200, e400 = _dead_reckoning_error(200.0), _dead_reckoning_error(400.0)
    assert e200 < 5e-3
    assert 3.5 < e200 / e400 < 4.5
    # an accelerometer bias of 0.02 m/s^2 that nobody corrects: 0.5 b t^2 ~ 1 m after 10 s
    assert 0.3 < _dead_reckoning_error(200.0, accel_bias=(0.02, 0.0, 0.0)) < 3.0


@pytest.fixture(scope="module")
def short_vio(texture):
    """VIO and dead reckoning over 4 s of the analytic flight at 320 x 180, 20 Hz, with
    the paper's IMU noise and an accelerometer and gyro bias the estimator does not know."""
    intr = intrinsics(width=320, height=180)
    cols = synthetic_flight(4.0)
    p, q, v = _truth(cols)
    rows = np.arange(0, len(cols["time"]), 10)
    Rs, ps = _camera_poses(cols, rows)
    imu = _imu(cols, accel_bias=(0.03, -0.02, 0.02), gyro_bias=(1e-3, -5e-4, 5e-4), noise=ImuNoise(), seed=4)
    init = NavState(t=0.0, R=quat_to_matrix(q[0]), p=p[0], v=v[0])
    rng = np.random.default_rng(5)
    frames = ((cols["time"][r], _render(intr, R, pc, texture, rng)) for r, R, pc in zip(rows, Rs, ps))
    result = run_vio(frames, imu, _camera_model(intr), init, ImuNoise(), VioConfig())
    dr = dead_reckoning(imu, init, cols["time"][rows])
    truth = PoseTrack(t=cols["time"][rows], p=p[rows], q=q[rows])
    return result, dr, truth


def test_vio_beats_dead_reckoning(short_vio):
    """Over 4 s (6.2 m) with unknown IMU biases, VIO stays on the flight while dead
    reckoning drifts. Measured ATE: VIO 5.3 mm (2.4 mm SE(3)-aligned), dead reckoning
    0.16 m; RPE over 1 m: 6.1 mm against 61 mm; 39 of 81 images were keyframes."""
    result, dr, truth = short_vio
    vio_err = trajectory_errors(truth, result.trajectory, rpe_delta_m=1.0)
    dr_err = trajectory_errors(truth, dr, rpe_delta_m=1.0)
    assert vio_err["ate_rmse_m"] < 0.05 and vio_err["ate_aligned_rmse_m"] < 0.03
    assert dr_err["ate_rmse_m"] > 5 * vio_err["ate_rmse_m"]
    assert vio_err["rpe_translation_rmse_m"] < dr_err["rpe_translation_rmse_m"]
    d = result.diagnostics
    assert d.keyframe[0] and d.keyframe.sum() >= 10
    assert np.all(d.n_features[1:] >= 50) and np.mean(d.n_inliers[1:]) > 100
    assert d.n_new_landmarks.sum() > 100


def test_vio_estimates_the_accelerometer_bias(short_vio):
    """The bias the estimator ends with is closer to the true one (0.03, -0.02, 0.02) m/s^2
    than the zero it started from (0.041 m/s^2 away). Measured error 0.005 m/s^2."""
    result, _, _ = short_vio
    assert np.linalg.norm(result.accel_bias[-1] - np.array([0.03, -0.02, 0.02])) < 0.02


# --- files and metrics -----------------------------------------------------------


def test_tum_round_trip(tmp_path):
    """write_tum -> read_tum gives the poses back; evo reads the same file identically."""
    from evo.tools import file_interface

    cols = synthetic_flight(1.0)
    p, q, _ = _truth(cols)
    traj = PoseTrack(t=cols["time"], p=p, q=q)
    write_tum(tmp_path / "t.tum", traj)
    back = read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(back.t, traj.t, atol=1e-9)
    np.testing.assert_allclose(back.p, traj.p, atol=1e-9)
    np.testing.assert_allclose(back.q, traj.q, atol=1e-9)
    evo_traj = file_interface.read_tum_trajectory_file(str(tmp_path / "t.tum"))
    np.testing.assert_allclose(evo_traj.positions_xyz, p, atol=1e-9)
    np.testing.assert_allclose(evo_traj.orientations_quat_wxyz, q, atol=1e-9)


def test_metrics_of_a_known_offset():
    """An estimate shifted by a constant (0.3, -0.4, 0) m has ATE 0.5 m unaligned, 0 after
    SE(3) alignment, no relative error; one rotated by 2 deg about the vertical through
    the start has a rotation error of 2 deg, which alignment removes."""
    cols = synthetic_flight(12.0, rate=50.0)
    p, q, _ = _truth(cols)
    truth = PoseTrack(t=cols["time"], p=p, q=q)
    shifted = PoseTrack(t=truth.t, p=p + np.array([0.3, -0.4, 0.0]), q=q)
    e = trajectory_errors(truth, shifted, rpe_delta_m=2.0)
    assert e["ate_rmse_m"] == pytest.approx(0.5, abs=1e-9)
    assert e["ate_max_m"] == pytest.approx(0.5, abs=1e-9)
    assert e["ate_aligned_rmse_m"] < 1e-9
    assert e["rpe_translation_rmse_m"] < 1e-9 and e["rpe_rotation_rmse_deg"] < 1e-6
    distance = np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))
    assert e["distance_m"] == pytest.approx(distance, rel=1e-9)

    c, s = np.cos(np.radians(2)), np.sin(np.radians(2))
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    turned = PoseTrack(t=truth.t, p=(p - p[0]) @ Rz.T + p[0], q=matrix_to_quat(Rz @ quat_to_matrix(q)))
    e = trajectory_errors(truth, turned, rpe_delta_m=2.0)
    assert e["ate_rotation_rmse_deg"] == pytest.approx(2.0, abs=1e-6)
    assert e["ate_rmse_m"] > 0.01 and e["ate_aligned_rmse_m"] < 1e-6


class _FailingSmoother:
    """A smoother that raises (as iSAM2 does on an indeterminate window) on its ``fail_at``-th update."""

    def __init__(self, inner, fail_at: int):
        self.inner, self.fail_at, self.calls = inner, fail_at, 0

    def update(self, *args):
        self.calls += 1
        if self.calls == self.fail_at:
            raise RuntimeError("Indeterminant linear system detected while working near variable b5")
        return self.inner.update(*args)

    def calculateEstimate(self):
        return self.inner.calculateEstimate()


def test_vio_recovers_from_a_failed_update(texture):
    """When the back end's update raises, the estimator re-initialises the smoother at the
    IMU's prediction (with priors) and goes on; the reset is counted and flagged."""
    from mysim_jax.perception.vio import VioEstimator

    intr = intrinsics(width=320, height=180)
    cols = synthetic_flight(2.0)
    p, q, v = _truth(cols)
    rows = np.arange(0, len(cols["time"]), 10)
    Rs, ps = _camera_poses(cols, rows)
    imu = _imu(cols, noise=ImuNoise(), seed=4)
    init = NavState(t=0.0, R=quat_to_matrix(q[0]), p=p[0], v=v[0])
    est = VioEstimator(_camera_model(intr), imu, init, ImuNoise(), VioConfig())
    est.smoother = _FailingSmoother(est.smoother, fail_at=6)
    rng = np.random.default_rng(5)
    errors = []
    for r, R, pc in zip(rows, Rs, ps):
        _, p_est, _ = est.add_image(cols["time"][r], _render(intr, R, pc, texture, rng))
        errors.append(np.linalg.norm(p_est - p[r]))
    d = est.diagnostics()
    assert est.n_resets == 1 and d.reset.sum() == 1 and d.keyframe[np.flatnonzero(d.reset)[0]]
    assert max(errors) < 0.05
    assert d.n_landmarks[np.flatnonzero(d.reset)[0] + 1:].max() > 0      # landmarks again after the reset


def test_gauss_markov_fit_recovers_a_simulated_process():
    """An Ornstein-Uhlenbeck error (sigma 0.1 m, correlation time 2 s, 20 Hz) is fitted back
    within its sampling scatter (measured: sigma 0.4 %, tau 0.6 % off for 40,000 samples); a
    white error has a correlation time of 0."""
    from mysim_jax.perception.metrics import gauss_markov_fit

    rng = np.random.default_rng(0)
    dt, tau, sigma, n = 0.05, 2.0, 0.1, 40_000
    rho = np.exp(-dt / tau)
    e = np.empty((n, 3))
    e[0] = sigma * rng.standard_normal(3)
    steps = sigma * np.sqrt(1 - rho ** 2) * rng.standard_normal((n, 3))
    for i in range(1, n):
        e[i] = rho * e[i - 1] + steps[i]
    fit = gauss_markov_fit(np.arange(n) * dt, e)
    assert fit["dt_s"] == pytest.approx(dt)
    assert fit["pooled"]["sigma"] == pytest.approx(sigma, rel=0.05)
    assert fit["pooled"]["correlation_time_s"] == pytest.approx(tau, rel=0.1)
    assert len(fit["axes"]) == 3
    white = gauss_markov_fit(np.arange(n) * dt, rng.standard_normal((n, 2)))
    assert white["pooled"]["correlation_time_s"] < dt          # rho ~ 0 either side


def test_target_filter_tracks_a_falling_target():
    """A target falling from rest (g) and drifting at 1 m/s, fixes at 20 Hz with 5 cm noise
    per axis and a one-second gap: the filter follows its position and velocity without
    the lag a constant-velocity model has under g. Measured (default jerk sigma 5 m/s³):
    velocity RMS 0.22 m/s and position RMS 0.047 m after the first second, 0.93 m/s off
    at the end of the gap."""
    from mysim_jax.perception.target_filter import target_filter

    rng = np.random.default_rng(0)
    t = np.arange(0, 4, 0.05)
    true_p = np.stack([1.0 * t, 0 * t, 10 - 0.5 * 9.81 * t ** 2], axis=1)
    true_v = np.stack([np.ones_like(t), 0 * t, -9.81 * t], axis=1)
    z = true_p + 0.05 * rng.standard_normal(true_p.shape)
    gap = (t > 2.0) & (t < 3.0)
    z[gap] = np.nan
    p, v = target_filter(t, z, position_sigma=0.05)
    settled = (t > 1.0) & ~gap
    assert np.sqrt(np.mean(np.sum((v[settled] - true_v[settled]) ** 2, axis=1))) < 0.4
    assert np.sqrt(np.mean(np.sum((p[settled] - true_p[settled]) ** 2, axis=1))) < 0.07
    assert np.linalg.norm(v[gap][-1] - true_v[gap][-1]) < 2.0                 # predicted through the gap
    with pytest.raises(ValueError, match="t must increase"):
        target_filter(t[::-1], z)
