"""IMU preintegration for the VIO estimator, and IMU-only dead reckoning, with gtsam.

The IMU's samples (body frame, at the body origin) are fed to gtsam's
``PreintegratedImuMeasurements`` (gravity along -z) one sample interval at a time, each at
its midpoint (:class:`_ImuIntegrator`); the estimator of :mod:`mysim_jax.perception.vio`
builds its IMU factors from these preintegrations and predicts the KLT search of its
features from the gyro's rotation between images.

Dead reckoning (the baseline of VIO): the same IMU samples, integrated the same way from the
same initial state and zero bias, with no camera: the NavState is predicted from each image's
time to the next (``PreintegratedImuMeasurements.predict``) over the whole run.

Frames: world z-up (gravity -z); the IMU measures at the body origin in body axes (angular
rate rad/s, specific force m/s^2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mysim_jax.core.npgeom import matrix_to_quat
from mysim_jax.perception.camera import PerceptionError
from mysim_jax.perception.metrics import PoseTrack

GRAVITY = 9.81          # m/s^2, along -z of the world


# --- inputs --------------------------------------------------------------------------


@dataclass(frozen=True)
class ImuNoise:
    """The IMU's noise specification as the estimator models it (paper Table IMU_simulator;
    the fields of :class:`mysim_jax.perception.imu.ImuConfig` of the same names).

    Continuous-time white-noise densities and bias random-walk densities; the estimator
    uses the simulated sensor's numbers, scaled by
    :attr:`~mysim_jax.perception.vio_config.VioConfig.imu_noise_scale` and
    :attr:`~mysim_jax.perception.vio_config.VioConfig.bias_walk_scale`.
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
class NavState:
    """A body's navigation state: X_world = R @ X_body + p."""

    t: float                # s
    R: np.ndarray           # (3, 3) body -> world
    p: np.ndarray           # (3,) m, world
    v: np.ndarray           # (3,) m/s, world



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
