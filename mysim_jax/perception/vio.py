"""Visual-inertial odometry (VIO) of a UAV from its fixed camera and its IMU, and IMU-only
dead reckoning, with gtsam. Runs after simulation on saved runs, outside jit.

This is the estimator of the paper's Alg. drone_state_estimation_process (the paper uses
VINS-Mono); it sees only what a vehicle would: the camera's images, the IMU's noisy and
biased samples, the camera's calibration (intrinsics and its fixed pose on the body) and
the IMU's noise specification. **Ground truth enters in one place: the initial state**
(pose and velocity of the body at the first image), as usual when odometry is evaluated;
the IMU biases start at zero (their true values are unknown to the estimator) and are
estimated. Everything after the first image is estimated.

Front end (:mod:`mysim_jax.perception.features`): KLT-tracked Shi-Tomasi corners with a
forward-backward check and essential-matrix RANSAC, replenished every image. The KLT
search of every feature starts where the gyro-measured rotation since the last image
moves it (a rotation-only prediction, no depth needed).

Keyframes. An image becomes a keyframe when the features it shares with the last keyframe
moved by ``keyframe_parallax_px`` on average, when fewer than ``keyframe_min_shared`` of
them are left, or ``keyframe_max_interval`` seconds after the last one. Only keyframes
enter the back end; the pose at every other image is the IMU's prediction from the latest
keyframe's estimate.

Back end: a sliding-window smoother (gtsam ``IncrementalFixedLagSmoother``, i.e. iSAM2
with the states older than ``lag`` seconds marginalised out) over, per keyframe ``k``,
the body pose ``X(k)`` (gtsam ``Pose3``, body -> world), velocity ``V(k)`` (m/s, world)
and IMU bias ``B(k)``, plus landmarks ``L(j)`` (world points, m):

* ``ImuFactor`` between consecutive keyframes: the IMU samples between them preintegrated
  (``PreintegratedImuMeasurements``, gravity along -z; each sample interval integrated at
  its midpoint, see :class:`_ImuIntegrator`) with the IMU's noise densities (scaled by
  ``imu_noise_scale``), and a ``BetweenFactorConstantBias`` ``B(k-1) -> B(k)`` with the
  bias random walk over the interval (``sigma = walk * sqrt(dt)``, scaled by
  ``bias_walk_scale``). This is the model of gtsam's ``CombinedImuFactor`` without its
  cross-covariance of bias and preintegration noise. With the paper's very stable IMU
  the combined factor's 15 x 15 covariance mixes bias blocks ~1e-14 with pose blocks
  ~1e-9, and iSAM2's Cholesky declares the window indeterminate even with the bias walk
  inflated 10x; the separate factors are better conditioned (see
  :class:`VioConfig` for the limit that remains);
* ``GenericProjectionFactorCal3_S2`` per landmark and keyframe that sees it, with the
  camera's pose on the body as ``body_P_sensor``, pixel noise ``pixel_sigma`` under a
  Huber loss. A track becomes a landmark once ``min_observations`` keyframes in the
  window saw it and its rays from those keyframes span at least
  ``min_triangulation_deg``: it is triangulated (linear, from the current pose
  estimates) and kept if it lies in front of every camera and reprojects within
  ``max_reprojection_px``; its later observations are added as they come. A landmark
  whose reprojection error in the newest keyframe exceeds ``max_reprojection_px`` after
  an update gets no further observations;
* priors on the first keyframe's pose and velocity (the true initial state, tight) and
  bias (zero, with ``initial_bias_sigma_*``).

Robustness to a non-static world (other UAVs, the net and tethers move through the view):
a landmark must lie between ``min_depth`` and ``max_depth`` in front of every camera that
saw it; a landmark's new observation is first checked against its projection at the
IMU-predicted pose (``gate_px``) and its track is dropped if it is off (features on moving
objects drift away from their landmark). IMU shocks (a tether jerking taut, an impact:
hundreds of m/s^2 for a few milliseconds, which a point-sampled IMU aliases and which even an
anti-aliased one integrates with its attitude and timing errors) are detected as jumps
between consecutive samples (``shock_accel_jump``, ``shock_gyro_jump``); the ImuFactor of the
keyframe interval holding one has its noise densities scaled by ``shock_noise_scale`` (the
camera then sets that keyframe's pose) and its observations skip the gate. **Failure recovery**: if the smoother's update
still raises (iSAM2 finds the window indeterminate), the smoother is re-initialised at the
keyframe, at the IMU's prediction from the last good estimate, with priors on pose,
velocity (``reset_pose_sigma``, ``reset_velocity_sigma``) and the last bias estimate,
and without landmarks (as VINS-Mono's failure detection restarts its estimator); resets
are counted (``VioEstimator.n_resets``, ``FrameDiagnostics.reset``, ``backend_resets``
in metrics.json).

Dead reckoning (the baseline): the same IMU samples, integrated the same way from the same
initial state and zero bias, with no camera: the NavState is predicted from each image's
time to the next (``PreintegratedImuMeasurements.predict``) over the whole run.

Frames: world z-up (gravity -z); the IMU measures at the body origin in body axes
(angular rate rad/s, specific force m/s^2); camera pixels follow
:mod:`mysim_jax.perception.camera` (OpenCV frame). Estimated poses are those of the body.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
import json
from pathlib import Path
import time
from typing import Iterable, Iterator

import cv2
import numpy as np
from tqdm import tqdm

from mysim_jax.config.scene import load_config
from mysim_jax.core.config_base import ConfigError
from mysim_jax.core.npgeom import matrix_to_quat, quat_to_matrix
from mysim_jax.io.trajectory import read_trajectory_csv
from mysim_jax.perception.camera import (CameraPoses, Intrinsics, PerceptionError, R_BODY_CV, body_pose_columns,
                                         camera_poses, check_sees_ground, intrinsics)
from mysim_jax.perception.features import FeatureTracker, FeatureTrackerConfig
from mysim_jax.perception.ground import GroundTexture
from mysim_jax.perception.imu import ImuConfig, ImuError, simulate_imu
from mysim_jax.perception.metrics import PoseTrack, gauss_markov_fit, plot_estimates, trajectory_errors, write_tum
from mysim_jax.perception.render import Renderer

GRAVITY = 9.81          # m/s^2, along -z of the world


# --- inputs --------------------------------------------------------------------------


@dataclass(frozen=True)
class ImuNoise:
    """The IMU's noise specification as the estimator models it (paper Table IMU_simulator;
    the fields of :class:`mysim_jax.perception.imu.ImuConfig` of the same names).

    Continuous-time white-noise densities and bias random-walk densities; the estimator
    uses the simulated sensor's numbers, scaled by :attr:`VioConfig.imu_noise_scale` and
    :attr:`VioConfig.bias_walk_scale`.
    """

    gyro_noise_density: float = 1.0e-4         # rad/s/sqrt(Hz)
    accel_noise_density: float = 2.0e-3        # m/s^2/sqrt(Hz)
    gyro_random_walk: float = 1.0e-6           # rad/s^2/sqrt(Hz)
    accel_random_walk: float = 1.0e-4          # m/s^3/sqrt(Hz)

    @classmethod
    def from_config(cls, config) -> "ImuNoise":
        """The noise of an :class:`mysim_jax.perception.imu.ImuConfig`."""
        return cls(**{name: float(getattr(config, name)) for name in cls.__dataclass_fields__})


@dataclass(frozen=True)
class ImuSamples:
    """IMU samples in the body frame at the body origin (any object with these fields works)."""

    t: np.ndarray       # (N,) s, increasing
    gyro: np.ndarray    # (N, 3) rad/s
    accel: np.ndarray   # (N, 3) m/s^2, specific force


@dataclass(frozen=True)
class CameraModel:
    """A camera rigidly mounted on the body: intrinsics and its pose on the body."""

    intr: Intrinsics
    body_R_cam: np.ndarray    # (3, 3) OpenCV camera frame -> body frame
    body_t_cam: np.ndarray    # (3,) m, optical centre in the body frame


@dataclass(frozen=True)
class NavState:
    """A body's navigation state: X_world = R @ X_body + p."""

    t: float                # s
    R: np.ndarray           # (3, 3) body -> world
    p: np.ndarray           # (3,) m, world
    v: np.ndarray           # (3,) m/s, world


@dataclass(frozen=True)
class VioConfig:
    """Settings of the estimator (see the module doc for what each does).

    ``bias_walk_scale``: with the sensor's own bias random walk (1e-6 rad/s^2/sqrt(Hz) for
    the paper's gyro), consecutive keyframes' biases are tied ~1e4 times tighter (in
    standard deviation) than the initial-bias prior that sets their common value, and
    iSAM2's Cholesky factorisation loses the precision to solve the window (gtsam raises
    IndeterminantLinearSystemException); the default lets the estimated bias wander 30x
    more than the sensor's does, a ratio of a few hundred, which it solves reliably.
    """

    tracker: FeatureTrackerConfig = FeatureTrackerConfig()
    pixel_sigma: float = 1.0                  # px, standard deviation of a feature position
    huber_k: float = 1.5                      # Huber threshold, in units of pixel_sigma
    keyframe_parallax_px: float = 10.0        # px, mean feature motion since the last keyframe
    keyframe_min_shared: int = 40             # features shared with the last keyframe
    keyframe_max_interval: float = 0.5        # s
    lag: float = 2.0                          # s, sliding-window length
    min_observations: int = 3                 # keyframes that saw a track before it is triangulated
    min_triangulation_deg: float = 1.0        # deg, spread of its rays
    max_reprojection_px: float = 3.0          # px
    min_depth: float = 0.1                    # m, a landmark closer to (or behind) a camera is rejected
    gate_px: float = 8.0                      # px, a landmark's new observation farther than this from its
                                              # projection at the IMU-predicted pose is an outlier (track dropped)
    shock_accel_jump: float = 30.0            # m/s^2 between consecutive IMU samples: a shock (impact, tether jerk)
    shock_gyro_jump: float = 2.0              # rad/s between consecutive IMU samples: a shock
    shock_noise_scale: float = 1000.0         # IMU noise densities x this over a keyframe interval with a shock
    max_depth: float = 200.0                  # m, a landmark farther from a camera is rejected (ill-conditioned)
    reset_pose_sigma: tuple[float, float] = (1e-3, 1e-2)       # rad, m: priors of a smoother re-initialised
    reset_velocity_sigma: float = 0.05        # m/s        after a failed update (see VioEstimator)
    imu_noise_scale: float = 1.0              # the estimator's IMU noise densities = this x the sensor's
    bias_walk_scale: float = 30.0             # the estimator's bias random walks = this x the sensor's (see below)
    initial_pose_sigma: tuple[float, float] = (1e-4, 1e-4)     # rad, m
    initial_velocity_sigma: float = 1e-3      # m/s
    initial_bias_sigma_accel: float = 0.1     # m/s^2
    initial_bias_sigma_gyro: float = 0.01     # rad/s
    relinearize_threshold: float = 0.01
    factorization: str = "CHOLESKY"           # iSAM2's: CHOLESKY or QR
    extra_iterations: int = 0                 # smoother updates without new factors after each keyframe

    def __post_init__(self):
        positive = ("pixel_sigma", "huber_k", "keyframe_parallax_px", "keyframe_max_interval", "lag",
                    "min_triangulation_deg", "max_reprojection_px", "min_depth", "max_depth", "gate_px", "shock_accel_jump", "shock_gyro_jump", "shock_noise_scale", "reset_velocity_sigma", "imu_noise_scale",
                    "bias_walk_scale", "initial_velocity_sigma", "initial_bias_sigma_accel",
                    "initial_bias_sigma_gyro", "relinearize_threshold")
        bad = [f"{k} (must be positive)" for k in positive if not getattr(self, k) > 0]
        if min(self.initial_pose_sigma) <= 0 or min(self.reset_pose_sigma) <= 0:
            bad.append("initial_pose_sigma and reset_pose_sigma (must be positive)")
        if self.max_depth <= self.min_depth:
            bad.append("max_depth (must exceed min_depth)")
        if self.min_observations < 2:
            bad.append("min_observations (at least 2)")
        if self.keyframe_min_shared < 0 or self.extra_iterations < 0:
            bad.append("keyframe_min_shared and extra_iterations (not negative)")
        if self.lag <= self.keyframe_max_interval:
            bad.append("lag (must exceed keyframe_max_interval)")
        if self.factorization not in ("CHOLESKY", "QR"):
            bad.append("factorization (CHOLESKY or QR)")
        if bad:
            raise PerceptionError(f"VioConfig: invalid {'; '.join(bad)}")


@dataclass(frozen=True)
class FrameDiagnostics:
    """Per image: what the front end tracked and what the back end used."""

    t: np.ndarray               # (F,) s
    n_features: np.ndarray      # (F,) features in the image after replenishing
    n_tracked: np.ndarray       # (F,) tracked from the previous image (KLT + forward-backward)
    n_inliers: np.ndarray       # (F,) of those, essential-matrix inliers
    n_new: np.ndarray           # (F,) corners added
    keyframe: np.ndarray        # (F,) bool
    n_landmarks: np.ndarray     # (F,) landmarks observed in the image (keyframes; 0 otherwise)
    n_new_landmarks: np.ndarray  # (F,) landmarks triangulated at the image
    update_s: np.ndarray        # (F,) s, wall time of the back-end update
    reset: np.ndarray           # (F,) bool, the back end failed at the image and was re-initialised

    def as_columns(self) -> dict[str, np.ndarray]:
        return {name: np.asarray(getattr(self, name)) for name in self.__dataclass_fields__}


@dataclass(frozen=True)
class VioResult:
    """Estimates at every image (causal: each uses only the images and IMU samples up to it)."""

    trajectory: PoseTrack
    velocity: np.ndarray        # (F, 3) m/s, world
    accel_bias: np.ndarray      # (F, 3) m/s^2, estimate
    gyro_bias: np.ndarray       # (F, 3) rad/s, estimate
    diagnostics: FrameDiagnostics


# --- rotations -----------------------------------------------------------------------


def _gtsam():
    """The gtsam module. Imported here, not at the top, because gtsam is a large compiled
    library that only the estimator uses: camera models, IMU samples and TUM files load
    without it."""
    import gtsam

    return gtsam


def _so3_exp(w: np.ndarray) -> np.ndarray:
    """(3,) rotation vector (rad) -> (3, 3) rotation matrix."""
    theta = float(np.linalg.norm(w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-9:
        return np.eye(3) + K
    return np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta ** 2 * K @ K


# --- IMU -----------------------------------------------------------------------------


def _check_imu(imu) -> None:
    t = np.asarray(imu.t)
    problems = []
    if t.ndim != 1 or len(t) < 2:
        problems.append(f"t must be (N,) with N >= 2, got shape {t.shape}")
    elif not np.all(np.diff(t) > 0):
        problems.append("t must increase strictly")
    for name in ("gyro", "accel"):
        a = np.asarray(getattr(imu, name))
        if a.shape != (len(t), 3):
            problems.append(f"{name} must be ({len(t)}, 3), got {a.shape}")
        elif not np.all(np.isfinite(a)):
            problems.append(f"{name} has non-finite samples")
    if problems:
        raise PerceptionError("IMU samples: " + "; ".join(problems))


def _preintegration_params(noise: ImuNoise, scale: float = 1.0, gravity: float = GRAVITY):
    gtsam = _gtsam()

    params = gtsam.PreintegrationParams.MakeSharedU(gravity)
    I3 = np.eye(3)
    params.setAccelerometerCovariance(I3 * (scale * noise.accel_noise_density) ** 2)
    params.setGyroscopeCovariance(I3 * (scale * noise.gyro_noise_density) ** 2)
    params.setIntegrationCovariance(I3 * 1e-8)
    return params


class _ImuIntegrator:
    """Feeds the IMU samples between two times to a gtsam preintegration.

    Each sample interval [t_i, t_i+1] (clipped to the requested span) is integrated with
    the IMU's values interpolated linearly at its midpoint (the mean of the two end
    samples for a whole interval), the specific force rotated to the interval's midpoint
    attitude: second-order accurate in the interval length.
    """

    def __init__(self, imu):
        _check_imu(imu)
        self.t = np.asarray(imu.t, dtype=float)
        self.gyro = np.asarray(imu.gyro, dtype=float)
        self.accel = np.asarray(imu.accel, dtype=float)

    def _at(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        i = int(np.clip(np.searchsorted(self.t, s, side="right") - 1, 0, len(self.t) - 2))
        w = (s - self.t[i]) / (self.t[i + 1] - self.t[i])
        return ((1 - w) * self.accel[i] + w * self.accel[i + 1], (1 - w) * self.gyro[i] + w * self.gyro[i + 1])

    def integrate(self, pim, ta: float, tb: float) -> None:
        """Add the IMU's motion from ``ta`` to ``tb`` (s) to the preintegration ``pim``."""
        if tb <= ta:
            return
        if ta < self.t[0] - 1e-9 or tb > self.t[-1] + 1e-9:
            raise PerceptionError(f"the IMU samples cover {self.t[0]:g} to {self.t[-1]:g} s; "
                                  f"cannot integrate {ta:g} to {tb:g} s")
        knots = self.t[(self.t > ta) & (self.t < tb)]
        edges = np.concatenate([[ta], knots, [tb]])
        for a, b in zip(edges[:-1], edges[1:]):
            if b - a > 1e-12:
                acc, gyr = self._at(0.5 * (a + b))
                # gtsam rotates the interval's specific force by the attitude at its start;
                # rotating it by half the interval's rotation first makes that the midpoint
                # attitude (otherwise a half-sample attitude lag: velocity errors ~ dt g w / 2)
                pim.integrateMeasurement(_so3_exp(0.5 * (b - a) * gyr) @ acc, gyr, b - a)

    def rotation(self, ta: float, tb: float, gyro_bias: np.ndarray) -> np.ndarray:
        """(3, 3) body rotation from ``ta`` to ``tb`` measured by the gyro (R_a^T R_b)."""
        R = np.eye(3)
        knots = self.t[(self.t > ta) & (self.t < tb)]
        edges = np.concatenate([[ta], knots, [tb]])
        for a, b in zip(edges[:-1], edges[1:]):
            if b - a > 1e-12:
                R = R @ _so3_exp((self._at(0.5 * (a + b))[1] - gyro_bias) * (b - a))
        return R


def _gtsam_nav(state: NavState):
    gtsam = _gtsam()

    return gtsam.NavState(gtsam.Rot3(np.asarray(state.R, dtype=float)), np.asarray(state.p, dtype=float),
                          np.asarray(state.v, dtype=float))


def dead_reckoning(imu, initial: NavState, times: np.ndarray, noise: ImuNoise = ImuNoise(),
                   gravity: float = GRAVITY) -> PoseTrack:
    """IMU-only poses at ``times`` (s, increasing, >= initial.t), integrated from ``initial``
    with zero bias: the NavState is predicted from one time to the next with a fresh
    preintegration each time (one preintegration over a long run loses accuracy once its
    rotation grows large)."""
    gtsam = _gtsam()

    times = np.asarray(times, dtype=float)
    if len(times) and (times[0] < initial.t - 1e-9 or np.any(np.diff(times) < 0)):
        raise PerceptionError("dead_reckoning: times must increase and start at or after the initial state")
    integ = _ImuIntegrator(imu)
    params = _preintegration_params(noise, gravity=gravity)
    zero = gtsam.imuBias.ConstantBias()
    state = _gtsam_nav(initial)
    p = np.empty((len(times), 3))
    R = np.empty((len(times), 3, 3))
    last = initial.t
    for i, t in enumerate(times):
        pim = gtsam.PreintegratedImuMeasurements(params, zero)
        integ.integrate(pim, last, t)
        if t > last:
            state = pim.predict(state, zero)
        last = max(last, t)
        p[i] = state.position()
        R[i] = state.attitude().matrix()
    return PoseTrack(t=times, p=p, q=matrix_to_quat(R))


# --- back end ------------------------------------------------------------------------


def _X(k):
    gtsam = _gtsam()
    return gtsam.symbol("x", k)


def _V(k):
    gtsam = _gtsam()
    return gtsam.symbol("v", k)


def _B(k):
    gtsam = _gtsam()
    return gtsam.symbol("b", k)


def _L(j):
    gtsam = _gtsam()
    return gtsam.symbol("l", j)


@dataclass
class _Track:
    """A feature track's keyframe observations and its landmark (if triangulated)."""

    obs: list = field(default_factory=list)   # [(keyframe index, (2,) px)]
    landmark: int | None = None               # landmark index, once triangulated
    rejected: bool = False


def triangulate(cam_R: list[np.ndarray], cam_p: list[np.ndarray], rays: list[np.ndarray]) -> np.ndarray:
    """(3,) world point closest (least squares) to rays from camera centres.

    ``cam_R``: (3, 3) camera -> world; ``cam_p``: (3,) centres; ``rays``: (3,) directions in
    the camera frame (e.g. K^-1 (u, v, 1)).
    """
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for R, p, r in zip(cam_R, cam_p, rays):
        d = R @ r
        d = d / np.linalg.norm(d)
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ p
    return np.linalg.lstsq(A, b, rcond=None)[0]


class VioEstimator:
    """Sliding-window visual-inertial odometry (see the module doc). Feed images in order
    with :meth:`add_image`; each call returns the body's pose estimate at that image."""

    def __init__(self, camera: CameraModel, imu, initial: NavState, noise: ImuNoise = ImuNoise(),
                 config: VioConfig = VioConfig(), gravity: float = GRAVITY):
        gtsam = _gtsam()

        self.camera = camera
        self.config = config
        self.noise = noise
        self.integ = _ImuIntegrator(imu)
        self.initial = initial
        intr = camera.intr
        self.K = gtsam.Cal3_S2(intr.fx, intr.fy, 0.0, intr.cx, intr.cy)
        self.Kinv = np.linalg.inv(intr.K)
        self.body_P_cam = gtsam.Pose3(gtsam.Rot3(np.asarray(camera.body_R_cam, float)),
                                      np.asarray(camera.body_t_cam, float))
        self.params = _preintegration_params(noise, config.imu_noise_scale, gravity)
        self.shock_params = _preintegration_params(noise, config.imu_noise_scale * config.shock_noise_scale, gravity)
        # IMU shocks (impacts, tether jerks): their integration is unreliable (aliased by a
        # point-sampled IMU); the keyframe interval that holds one gets a loose ImuFactor
        jump_a = np.linalg.norm(np.diff(self.integ.accel, axis=0), axis=1)
        jump_w = np.linalg.norm(np.diff(self.integ.gyro, axis=0), axis=1)
        shock = (jump_a > config.shock_accel_jump) | (jump_w > config.shock_gyro_jump)
        self.shock_t = self.integ.t[1:][shock]        # times of the samples after a jump
        self.n_shocks = 0                             # keyframe intervals with a shock
        self.bias_walk = config.bias_walk_scale * np.r_[np.full(3, noise.accel_random_walk),
                                                        np.full(3, noise.gyro_random_walk)]
        isam = gtsam.ISAM2Params()
        isam.setRelinearizeThreshold(config.relinearize_threshold)
        isam.relinearizeSkip = 1
        isam.setFactorization(config.factorization)
        self.smoother = gtsam.IncrementalFixedLagSmoother(config.lag, isam)
        self.pixel_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(config.huber_k),
            gtsam.noiseModel.Isotropic.Sigma(2, config.pixel_sigma))
        self.tracker = FeatureTracker(intr, config.tracker)
        self.tracks: dict[int, _Track] = {}
        self.n_landmarks = 0
        self.landmark_last_t: dict[int, float] = {}
        self.landmark_pos: dict[int, np.ndarray] = {}  # landmark -> world point, latest estimate
        self.kf_t: list[float] = []                   # keyframe times
        self.kf_cam: dict[int, tuple[np.ndarray, np.ndarray]] = {}   # keyframe -> camera (R, p) estimate
        self.kf_ids: np.ndarray | None = None         # track ids and pixels of the last keyframe
        self.kf_uv: np.ndarray | None = None
        self.nav = None                               # gtsam NavState of the last keyframe
        self.bias = gtsam.imuBias.ConstantBias()
        self.pim = None
        self.last_t: float | None = None
        self.features = None                          # FrameFeatures of the last image
        self._diag: list[tuple] = []
        self.n_resets = 0                             # back-end failures recovered from (see _reset)
        self._reset_now = False
        self._isam_params = isam

    # camera pose of a body NavState / Pose3
    def _camera_pose(self, pose) -> tuple[np.ndarray, np.ndarray]:
        cam = pose.compose(self.body_P_cam)
        return cam.rotation().matrix(), cam.translation()

    def _predict_uv(self, t: float) -> np.ndarray | None:
        """Where the current features move under the gyro-measured rotation since the last image."""
        uv = self.tracker.uv
        if self.last_t is None or not len(uv):
            return None
        Rb = self.integ.rotation(self.last_t, t, self.bias.gyroscope())
        Rc = self.camera.body_R_cam
        R_cur_prev = Rc.T @ Rb.T @ Rc           # previous camera frame -> current camera frame
        rays = np.c_[uv, np.ones(len(uv))] @ self.Kinv.T @ R_cur_prev.T
        ok = rays[:, 2] > 1e-3
        proj = rays @ self.camera.intr.K.T
        pred = np.where(ok[:, None], proj[:, :2] / np.where(ok, proj[:, 2], 1.0)[:, None], uv)
        return pred

    def add_image(self, t: float, image: np.ndarray) -> tuple:
        """Process the image taken at ``t`` (s); return the body's (R (3, 3), p (3,), v (3,)) estimate."""
        gtsam = _gtsam()

        predicted = self._predict_uv(t)
        ff = self.tracker.track(image, predicted)
        self.features = ff
        if self.nav is None:                       # the first image: the known initial state
            if abs(t - self.initial.t) > 1e-6:
                raise PerceptionError(f"the first image is at t = {t:g} s but the initial state at "
                                      f"{self.initial.t:g} s")
            self.nav = _gtsam_nav(self.initial)
            self.pim = gtsam.PreintegratedImuMeasurements(self.params, self.bias)
            keyframe = True
        else:
            self.integ.integrate(self.pim, self.last_t, t)
            keyframe = self._is_keyframe(t, ff)
        self.last_t = t
        n_obs = n_new_lm = 0
        update_s = 0.0
        if keyframe:
            n_obs, n_new_lm, update_s = self._add_keyframe(t, ff)
            state = self.nav
        else:
            state = self.pim.predict(self.nav, self.bias)
        self._diag.append((t, len(ff.ids), ff.n_tracked, ff.n_inliers, ff.n_new, keyframe, n_obs, n_new_lm,
                           update_s, self._reset_now))
        self._reset_now = False
        return state.attitude().matrix(), np.asarray(state.position()), np.asarray(state.velocity())

    def _is_keyframe(self, t: float, ff) -> bool:
        c = self.config
        if t - self.kf_t[-1] >= c.keyframe_max_interval - 1e-9:
            return True
        _, ia, ib = np.intersect1d(self.kf_ids, ff.ids, return_indices=True)
        if len(ia) < c.keyframe_min_shared:
            return True
        return float(np.mean(np.linalg.norm(ff.uv[ib] - self.kf_uv[ia], axis=1))) >= c.keyframe_parallax_px

    def _in_window(self, t_obs: float, t_now: float) -> bool:
        return t_obs > t_now - self.config.lag + 1e-6

    def _add_keyframe(self, t: float, ff) -> tuple[int, int, float]:
        gtsam = _gtsam()

        c = self.config
        k = len(self.kf_t)
        shock = False
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        stamps = {}
        if k == 0:
            pose = self.nav.pose()
            vel = self.nav.velocity()
            rs, ps = c.initial_pose_sigma
            graph.add(gtsam.PriorFactorPose3(_X(0), pose, gtsam.noiseModel.Diagonal.Sigmas(
                np.r_[np.full(3, rs), np.full(3, ps)])))
            graph.add(gtsam.PriorFactorVector(_V(0), vel,
                                              gtsam.noiseModel.Isotropic.Sigma(3, c.initial_velocity_sigma)))
            graph.add(gtsam.PriorFactorConstantBias(_B(0), self.bias, gtsam.noiseModel.Diagonal.Sigmas(
                np.r_[np.full(3, c.initial_bias_sigma_accel), np.full(3, c.initial_bias_sigma_gyro)])))
        else:
            pred = self.pim.predict(self.nav, self.bias)
            pose, vel = pred.pose(), pred.velocity()
            shock = bool(np.any((self.shock_t > self.kf_t[-1] - 0.01) & (self.shock_t <= t + 0.01)))
            if shock:
                self.n_shocks += 1
                self.pim = gtsam.PreintegratedImuMeasurements(self.shock_params, self.bias)
                self.integ.integrate(self.pim, self.kf_t[-1], t)
            graph.add(gtsam.ImuFactor(_X(k - 1), _V(k - 1), _X(k), _V(k), _B(k - 1), self.pim))
            dt = t - self.kf_t[-1]
            graph.add(gtsam.BetweenFactorConstantBias(_B(k - 1), _B(k), gtsam.imuBias.ConstantBias(),
                                                      gtsam.noiseModel.Diagonal.Sigmas(self.bias_walk * np.sqrt(dt))))
        values.insert(_X(k), pose)
        values.insert(_V(k), vel)
        values.insert(_B(k), self.bias)
        for key in (_X(k), _V(k), _B(k)):
            stamps[key] = t
        self.kf_t.append(t)
        self.kf_cam[k] = self._camera_pose(pose)
        R_pred, p_pred = self.kf_cam[k]
        for old in [j for j in self.kf_cam if not self._in_window(self.kf_t[j], t)]:
            del self.kf_cam[old]

        n_obs, n_new, observed = self._visual_factors(k, t, ff, shock, R_pred, p_pred, graph, values, stamps)
        t0 = time.perf_counter()
        try:
            self.smoother.update(graph, values, stamps)
            for _ in range(c.extra_iterations):
                self.smoother.update()
            est = self.smoother.calculateEstimate()
            if not np.all(np.isfinite(est.atPose3(_X(k)).translation())):
                raise RuntimeError("non-finite estimate")
        except RuntimeError:
            # failure recovery (as VINS-Mono's failure detection): the window cannot be solved
            # (e.g. iSAM2 finds it indeterminate); restart the smoother at this keyframe from
            # the IMU's prediction from the last good estimate, with priors, and no landmarks
            est = self._reset(k, t, pose, vel)
            n_obs = n_new = 0
            observed = []
        update_s = time.perf_counter() - t0
        pose = est.atPose3(_X(k))
        self.nav = gtsam.NavState(pose.rotation(), pose.translation(), est.atVector(_V(k)))
        self.bias = est.atConstantBias(_B(k))
        self.pim = gtsam.PreintegratedImuMeasurements(self.params, self.bias)
        for j in list(self.kf_cam):
            if est.exists(_X(j)):
                self.kf_cam[j] = self._camera_pose(est.atPose3(_X(j)))
        self._drop_unexplained(k, ff, est, pose, observed)
        self.kf_ids, self.kf_uv = ff.ids, ff.uv
        return n_obs, n_new, update_s

    def _visual_factors(self, k: int, t: float, ff, shock: bool, R_pred, p_pred, graph, values, stamps):
        """Projection factors of keyframe ``k``'s features: on landmarks still in the window
        (after an outlier gate at the IMU-predicted camera pose ``R_pred``, ``p_pred``), and on
        new landmarks triangulated from tracks seen often enough. Returns ``(observations,
        new landmarks, [(track id, landmark)])``."""
        gtsam = _gtsam()
        c = self.config
        n_obs = n_new = 0
        observed = []
        alive = set(ff.ids.tolist())
        for tid in [tid for tid in self.tracks if tid not in alive]:
            del self.tracks[tid]
        for tid, uv in zip(ff.ids.tolist(), ff.uv):
            track = self.tracks.setdefault(tid, _Track())
            if track.rejected:
                continue
            track.obs.append((k, uv))
            if track.landmark is not None and self._in_window(self.landmark_last_t[track.landmark], t):
                if shock:                          # the IMU-predicted pose is not reliable
                    Xc = None
                # outlier gate: the landmark seen from the IMU-predicted pose must be in front
                # and near the feature (features on moving objects drift away from it)
                else:
                    Xc = R_pred.T @ (self.landmark_pos[track.landmark] - p_pred)
                if Xc is not None and (not c.min_depth <= Xc[2] <= c.max_depth
                        or np.linalg.norm((self.camera.intr.K @ (Xc / Xc[2]))[:2] - uv) > c.gate_px):
                    track.rejected = True
                    track.obs.pop()
                    continue
                graph.add(gtsam.GenericProjectionFactorCal3_S2(uv, self.pixel_noise, _X(k), _L(track.landmark),
                                                               self.K, self.body_P_cam))
                self.landmark_last_t[track.landmark] = t
                stamps[_L(track.landmark)] = t
                observed.append((tid, track.landmark))
                n_obs += 1
                continue
            if track.landmark is not None:         # its landmark was marginalised: start again
                track.landmark = None
            obs = [(j, z) for j, z in track.obs if j in self.kf_cam]
            if len(obs) < c.min_observations:
                continue
            point = self._triangulate(obs)
            if point is None:
                continue
            j = self.n_landmarks
            self.n_landmarks += 1
            track.landmark = j
            values.insert(_L(j), point)
            stamps[_L(j)] = t
            self.landmark_last_t[j] = t
            for kk, z in obs:
                graph.add(gtsam.GenericProjectionFactorCal3_S2(z, self.pixel_noise, _X(kk), _L(j), self.K,
                                                               self.body_P_cam))
            observed.append((tid, j))
            n_new += 1
            n_obs += 1
        return n_obs, n_new, observed

    def _drop_unexplained(self, k: int, ff, est, pose, observed) -> None:
        """Stop following landmarks that the newest keyframe (solved as ``est``) does not
        explain: behind the camera or reprojected too far from their feature."""
        gtsam = _gtsam()
        c = self.config
        cam = gtsam.PinholeCameraCal3_S2(pose.compose(self.body_P_cam), self.K)
        by_id = dict(zip(ff.ids.tolist(), ff.uv))
        for tid, j in observed:
            point = est.atPoint3(_L(j))
            self.landmark_pos[j] = point
            Rc, pc = self.kf_cam[k]
            depth = (point - pc) @ Rc[:, 2]
            if depth < c.min_depth or np.linalg.norm(cam.project(point) - by_id[tid]) > c.max_reprojection_px:
                self.tracks[tid].rejected = True

    def _reset(self, k: int, t: float, pose, vel):
        """Re-initialise the smoother at keyframe ``k`` (time ``t``) with priors on the pose
        ``pose``, velocity ``vel`` and the last bias estimate; forget every landmark."""
        gtsam = _gtsam()

        c = self.config
        self.n_resets += 1
        self._reset_now = True
        self.smoother = gtsam.IncrementalFixedLagSmoother(c.lag, self._isam_params)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        rs, ps = c.reset_pose_sigma
        graph.add(gtsam.PriorFactorPose3(_X(k), pose, gtsam.noiseModel.Diagonal.Sigmas(
            np.r_[np.full(3, rs), np.full(3, ps)])))
        graph.add(gtsam.PriorFactorVector(_V(k), vel, gtsam.noiseModel.Isotropic.Sigma(3, c.reset_velocity_sigma)))
        graph.add(gtsam.PriorFactorConstantBias(_B(k), self.bias, gtsam.noiseModel.Diagonal.Sigmas(
            np.r_[np.full(3, c.initial_bias_sigma_accel), np.full(3, c.initial_bias_sigma_gyro)])))
        values.insert(_X(k), pose)
        values.insert(_V(k), vel)
        values.insert(_B(k), self.bias)
        self.smoother.update(graph, values, {_X(k): t, _V(k): t, _B(k): t})
        self.kf_cam = {k: self._camera_pose(pose)}
        for track in self.tracks.values():
            track.landmark = None
            track.obs = [(j, z) for j, z in track.obs if j == k]
        self.landmark_last_t.clear()
        self.landmark_pos.clear()
        return self.smoother.calculateEstimate()

    def _triangulate(self, obs: list) -> np.ndarray | None:
        c = self.config
        Rs = [self.kf_cam[j][0] for j, _ in obs]
        ps = [self.kf_cam[j][1] for j, _ in obs]
        rays = [self.Kinv @ np.r_[z, 1.0] for _, z in obs]
        dirs = [R @ r / np.linalg.norm(r) for R, r in zip(Rs, rays)]
        spread = max(np.degrees(np.arccos(np.clip(dirs[a] @ dirs[b], -1, 1)))
                     for a in range(len(dirs)) for b in range(a + 1, len(dirs)))
        if spread < c.min_triangulation_deg:
            return None
        X = triangulate(Rs, ps, rays)
        for R, p, (_, z) in zip(Rs, ps, obs):
            Xc = R.T @ (X - p)
            if not c.min_depth <= Xc[2] <= c.max_depth:
                return None
            uv = self.camera.intr.K @ (Xc / Xc[2])
            if np.linalg.norm(uv[:2] - z) > c.max_reprojection_px:
                return None
        return X

    def last_frame(self) -> dict:
        """The diagnostics of the last image (the fields of :class:`FrameDiagnostics`, one value each)."""
        return dict(zip(FrameDiagnostics.__dataclass_fields__, self._diag[-1]))

    def diagnostics(self) -> FrameDiagnostics:
        """Per-image diagnostics of every image so far."""
        cols = list(zip(*self._diag)) if self._diag else [[]] * 10
        names = list(FrameDiagnostics.__dataclass_fields__)
        dtypes = [float, int, int, int, int, bool, int, int, float, bool]
        return FrameDiagnostics(**{n: np.asarray(col, dtype=d) for n, col, d in zip(names, cols, dtypes)})


def run_vio(frames: Iterable[tuple[float, np.ndarray]], imu, camera: CameraModel, initial: NavState,
            noise: ImuNoise = ImuNoise(), config: VioConfig = VioConfig(), gravity: float = GRAVITY) -> VioResult:
    """Run the estimator over ``frames`` ((t s, (H, W) uint8 image) in time order)."""
    est = VioEstimator(camera, imu, initial, noise, config, gravity)
    ts, Rs, ps, vs, bas, bgs = [], [], [], [], [], []
    for t, image in frames:
        R, p, v = est.add_image(float(t), image)
        ts.append(float(t))
        Rs.append(R)
        ps.append(p)
        vs.append(v)
        bas.append(est.bias.accelerometer())
        bgs.append(est.bias.gyroscope())
    if not ts:
        raise PerceptionError("run_vio: no images")
    traj = PoseTrack(t=np.asarray(ts), p=np.asarray(ps), q=matrix_to_quat(np.asarray(Rs)))
    return VioResult(trajectory=traj, velocity=np.asarray(vs), accel_bias=np.asarray(bas),
                     gyro_bias=np.asarray(bgs), diagnostics=est.diagnostics())


# --- run folders ---------------------------------------------------------------------
#
# The perception stage on a run folder written by scripts/simulate.py: check the inputs
# (cheap, before any long work), render the camera's images of the ground, simulate the
# IMU, run VIO and dead reckoning, write trajectories, metrics, plots, images and a video.


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


def _read_columns(run: Path, body: str, camera: str) -> dict:
    """The run's trajectory columns, checked for what VIO reads (present, finite, at
    increasing times)."""
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
    bad = [k for k in need if not np.all(np.isfinite(columns[k]))]
    if bad:
        raise PerceptionError(f"{run / 'trajectory.csv'}: non-finite values in {', '.join(bad[:6])}; the run "
                              f"diverged (see its metrics.json)")
    return columns


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
                       imu_config=None) -> PerceptionJob:
    """Read and check a run folder (``trajectory.csv`` and ``config.yaml``) for perception,
    and simulate the body's IMU (``imu_config``, default the paper's; seeded).

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
    columns = _read_columns(run, body, camera)
    rows = _image_rows(np.asarray(columns["time"], dtype=float), camera_rate)

    poses = camera_poses(columns, camera)
    check_sees_ground(intr, CameraPoses(name=camera, t=poses.t[rows], R=poses.R[rows], p=poses.p[rows]))

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
