"""Visual-inertial odometry (VIO) of a UAV from its fixed camera and its IMU, with gtsam: the
estimator. Runs after simulation on saved runs, outside jit; the job that runs it over a run
folder and writes the results is :mod:`mysim_jax.perception.vio_run_folder`, its settings
are :class:`~mysim_jax.perception.vio_config.VioConfig`, and the IMU preintegration and the
dead-reckoning baseline are :mod:`mysim_jax.perception.imu_preintegration`.

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
  its midpoint, see :class:`~mysim_jax.perception.imu_preintegration._ImuIntegrator`) with
  the IMU's noise densities (scaled by ``imu_noise_scale``), and a
  ``BetweenFactorConstantBias`` ``B(k-1) -> B(k)`` with the bias random walk over the
  interval (``sigma = walk * sqrt(dt)``, scaled by ``bias_walk_scale``). This is the model
  of gtsam's ``CombinedImuFactor`` without its cross-covariance of bias and preintegration
  noise. With the paper's very stable IMU the combined factor's 15 x 15 covariance mixes
  bias blocks many orders of magnitude smaller than its pose blocks, and iSAM2's Cholesky
  declares the window indeterminate even with an inflated bias walk; the separate factors
  are better conditioned (see :class:`VioConfig` for the limit that remains);
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
hundreds of m/s^2 for milliseconds, sizes in docs/perception.md, "On a capture run"; a
point-sampled IMU aliases them and even an anti-aliased one integrates them with its
attitude and timing errors) are detected as jumps between consecutive samples
(``shock_accel_jump``, ``shock_gyro_jump``); the ImuFactor of the keyframe interval holding
one has its noise densities scaled by ``shock_noise_scale`` (the camera then sets that
keyframe's pose) and its observations skip the gate. **Failure recovery**: if the
smoother's update still raises (iSAM2 finds the window indeterminate), the smoother is
re-initialised at the keyframe, at the IMU's prediction from the last good estimate, with
priors on pose, velocity (``reset_pose_sigma``, ``reset_velocity_sigma``) and the last bias
estimate, and without landmarks (as VINS-Mono's failure detection restarts its estimator);
resets are counted (``VioEstimator.n_resets``, ``FrameDiagnostics.reset``,
``backend_resets`` in metrics.json).

Frames: world z-up (gravity -z); the IMU measures at the body origin in body axes
(angular rate rad/s, specific force m/s^2); camera pixels follow
:mod:`mysim_jax.perception.camera` (OpenCV frame). Estimated poses are those of the body.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Iterable

import numpy as np

from mysim_jax.core.npgeom import matrix_to_quat
from mysim_jax.perception.camera import Intrinsics, PerceptionError
from mysim_jax.perception.features import FeatureTracker
from mysim_jax.perception.imu_preintegration import (GRAVITY, ImuNoise, NavState, _gtsam, _gtsam_nav, _ImuIntegrator,
                                                     _preintegration_params)
from mysim_jax.perception.metrics import PoseTrack
from mysim_jax.perception.vio_config import VioConfig


# --- inputs and results ----------------------------------------------------------------


@dataclass(frozen=True)
class CameraModel:
    """A camera rigidly mounted on the body: intrinsics and its pose on the body."""

    intr: Intrinsics
    body_R_cam: np.ndarray    # (3, 3) OpenCV camera frame -> body frame
    body_t_cam: np.ndarray    # (3,) m, optical centre in the body frame


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
