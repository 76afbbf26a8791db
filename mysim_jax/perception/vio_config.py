"""Settings of the VIO estimator (:class:`VioConfig`), checked when made; what each one
does is in the doc of :mod:`mysim_jax.perception.vio`."""

from __future__ import annotations

from dataclasses import dataclass

from mysim_jax.perception.camera import PerceptionError
from mysim_jax.perception.features import FeatureTrackerConfig


@dataclass(frozen=True)
class VioConfig:
    """Settings of the estimator (see :mod:`mysim_jax.perception.vio` for what each does).

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
