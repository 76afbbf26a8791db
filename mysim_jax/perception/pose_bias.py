"""Self-calibration of the cameras' pose biases from the target's rays (causal, frame by frame).

The camera poses the fusion uses (:mod:`mysim_jax.perception.localize`) come from each UAV's
own estimate (VIO): per camera a position error ``dp`` (m) and a small rotation ``ω`` (rad,
world frame: the believed camera-to-world rotation is ``exp([ω]×) R``) that change slowly
(a Gauss-Markov process with a correlation time of seconds). The believed ray of camera
``i`` (origin ``p'``, bearing ``b'``) then meets the target ``x`` (range ``r``) where

    P' (x − p') + P' dp − r [b']× ω = 0,        P' = I − b' b'ᵀ

(``b ≈ b' + b' × ω``, ``p = p' − dp``). When several cameras see the target their rays
disagree by the differences of these errors, so the differences are observable; the error
all cameras share is not (a common shift moves the target with it) and stays at its prior
mean, zero. State: ``θ`` (6 per camera: ``dp``, ``ω``), a Kalman filter over the frames:
each frame, predict (``θ ← ρ θ``, ``Σ ← ρ² Σ + (1 − ρ²) Σ₀``, ``ρ = exp(−Δt / τ)``,
``Σ₀`` from ``pose_sigma``), fuse the corrected rays (``fuse(method)``) into ``x₀``,
keep the rays whose miss from ``x₀`` is within ``gate`` standard deviations, stack their
across-ray rows of the equation above in ``(x, θ)`` weighted by ``1 / (σ_a r)²``,
eliminate ``x`` (Schur complement) and add the rest to ``θ``'s information. The target is
then the fusion of the rays corrected by the updated ``θ``.

Three choices keep the filter from explaining the detector's own errors as pose errors.
The formation's scale mode (every origin moved away from the cameras' centroid by ``s``
times its offset, the target with them) leaves every bearing as it is, yet least squares
would shrink it to shrink the detector's misses (they scale with it), a drift frame after
frame; it is projected out of each frame's information. The box-size ranges are not used
for ``θ`` (a drone's box-size range is biased by its attitude for many frames on end,
which ``dp`` along the ray would absorb). A frame's information is divided by
``frames_per_independent`` (the detector's box errors follow the target's attitude and are
correlated over several frames, not independent). With ``pose_sigma`` zero nothing is
calibrated and the points are ``fuse(method)`` of the rays as given.

**Ranges between the cameras** (:class:`TeamRanging`, UWB-like radios on the UAVs; optional).
The rays see neither the common shift nor the scale mode; a measured distance ``d_ij``
between cameras ``i`` and ``j`` does see the scale mode and every other relative position
bias along the pair's baseline: with ``c = p' − dp`` the true origins,
``d_ij = |c_i − c_j| + noise``, linearised at the current estimate
(``u`` the unit vector from ``c_j`` to ``c_i``) ``d_ij − |ĉ_i − ĉ_j| ≈ −uᵀ(dp_i − d̂p_i) + uᵀ(dp_j − d̂p_j)``,
a Kalman update of ``θ`` per frame (every pair, white noise of the stated spread). What the
filter does not model is each pair's constant bias (antenna delays): :class:`TeamRanging`
draws one so that its cost shows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mysim_jax.core.npgeom import skew
from mysim_jax.perception.camera import PerceptionError
from mysim_jax.perception.localize import Localisation, PoseNoise, fuse, record_rays


@dataclass(frozen=True)
class TeamRanging:
    """Distances between the team's cameras measured every frame (UWB-like radios, one on each
    UAV at its camera): the true distance plus white noise of spread ``sigma_m`` (m) and a
    constant per-pair bias drawn once per run with spread ``bias_m`` (m); ``seed`` draws both
    (a stream of its own, apart from :class:`~mysim_jax.perception.localize.PoseNoise`'s)."""

    sigma_m: float = 0.1
    bias_m: float = 0.0
    seed: int = 0

    def __post_init__(self):
        if not (self.sigma_m > 0 and self.bias_m >= 0):
            raise PerceptionError(f"team ranging needs a noise sigma > 0 m and a bias spread >= 0 m; got "
                                  f"{self.sigma_m} and {self.bias_m}")

    def measure(self, camera_p: np.ndarray) -> np.ndarray:
        """Measured distances (F, G, G) m, symmetric, NaN on the diagonal, from the true camera
        positions ``camera_p`` (F, G, 3)."""
        camera_p = np.asarray(camera_p, float)
        F, G, _ = camera_p.shape
        rng = np.random.default_rng([self.seed, 0x55B])
        bias = np.triu(rng.normal(0.0, self.bias_m, (G, G)), 1) if self.bias_m > 0 else np.zeros((G, G))
        noise = np.triu(rng.normal(0.0, self.sigma_m, (F, G, G)), 1)
        d = np.linalg.norm(camera_p[:, :, None] - camera_p[:, None], axis=-1) + bias + noise
        d = np.triu(d, 1)
        d = d + np.swapaxes(d, 1, 2)
        d[:, np.arange(G), np.arange(G)] = np.nan
        return d


def _range_update(th, S, p, distances, sigma: float):
    """The Kalman update of the biases ``th`` (6 G,) and their covariance ``S`` from one
    frame's measured distances (G, G) (NaN: none) between cameras at believed origins ``p``
    (G, 3) (module doc)."""
    G = len(p)
    rows, z = [], []
    c = p - th.reshape(G, 6)[:, :3]
    for i in range(G):
        for j in range(i + 1, G):
            if not np.isfinite(distances[i, j]):
                continue
            d = c[i] - c[j]
            u = d / np.linalg.norm(d)
            h = np.zeros(6 * G)
            h[6 * i:6 * i + 3], h[6 * j:6 * j + 3] = -u, u
            rows.append(h)
            z.append(distances[i, j] - np.linalg.norm(d))
    if not rows:
        return th, S
    H, z = np.array(rows), np.array(z)
    K = np.linalg.solve(H @ S @ H.T + sigma * sigma * np.eye(len(z)), H @ S).T
    S = S - K @ H @ S
    return th + K @ z, (S + S.T) / 2.0


def _corrected(p: np.ndarray, b: np.ndarray, th: np.ndarray, cams: np.ndarray):
    """Origins (n, 3) and unit bearings (n, 3) of cameras ``cams`` corrected by biases ``th`` (6 G,)."""
    th = th.reshape(-1, 6)[cams]
    bc = b + np.cross(b, th[:, 3:])
    return p - th[:, :3], bc / np.linalg.norm(bc, axis=1, keepdims=True)


def _frame_information(p, b, x0, cams, n_cams: int, angle_sigma: float):
    """Information matrix (6 G, 6 G) and vector (6 G,) on the biases from one frame's rays of
    ``cams`` (believed origins ``p`` and bearings ``b``, (n, 3)), the target eliminated."""
    n = 3 + 6 * n_cams
    N, v = np.zeros((n, n)), np.zeros(n)
    for pi, bi, i in zip(p, b, cams):
        P = np.eye(3) - np.outer(bi, bi)
        r = np.linalg.norm(x0 - pi)
        A = np.zeros((3, n))
        A[:, :3] = P
        A[:, 3 + 6 * i:6 + 6 * i] = P
        A[:, 6 + 6 * i:9 + 6 * i] = -r * skew(bi)
        w = 1.0 / (angle_sigma * r) ** 2
        N += w * A.T @ A
        v += w * A.T @ (P @ pi)
    Nxx_inv = np.linalg.inv(N[:3, :3])
    J = N[3:, 3:] - N[:3, 3:].T @ Nxx_inv @ N[:3, 3:]
    h = v[3:] - N[:3, 3:].T @ Nxx_inv @ v[:3]
    # the scale mode (every origin moved away from the cameras' centroid, the target with them)
    # leaves the bearings as they are; least squares would shrink it to shrink the detector's misses
    u = np.zeros(6 * n_cams)
    for pi, i in zip(p, cams):
        u[6 * i:6 * i + 3] = pi - p.mean(0)
    u /= np.linalg.norm(u)
    Q = np.eye(6 * n_cams) - np.outer(u, u)
    return Q @ J @ Q, Q @ h


def _inliers(pc, bc, x0, cams, S, angle_sigma: float, gate: float) -> np.ndarray:
    """(n,) bool: corrected rays whose miss from ``x0`` is within ``gate`` standard deviations
    (the detector's angular noise and the biases' remaining uncertainty ``S``)."""
    d = x0 - pc
    r = np.linalg.norm(d, axis=1)
    miss = np.linalg.norm(d - np.einsum("ij,ij->i", d, bc)[:, None] * bc, axis=1)
    diag = np.diag(S).reshape(-1, 6)[cams]
    var = (angle_sigma * r) ** 2 + (diag[:, :3].sum(1) + diag[:, 3:].sum(1) * r * r) / 3.0
    return miss < gate * np.sqrt(var)


def self_calibrated_points(t, has, origins, bearings, ranges, pose_sigma, correlation_time: float,
                           angle_sigma: float = 2e-3, range_sigma: float = 0.05, method: str = "triples_weighted",
                           frames_per_independent: float = 5.0, gate: float = 3.0,
                           distances: np.ndarray | None = None, distance_sigma: float = 0.1):
    """Target points (F, 3) m (NaN: none that frame) and the bias estimates (F, G, 6) (m, rad)
    from the believed rays of ``G`` cameras over ``F`` frames (see the module doc).

    ``t`` (F,) s; ``has`` (F, G) bool (a detection); ``origins``, ``bearings`` (F, G, 3);
    ``ranges`` (F, G) m (NaN: none), used by the fusion only; ``pose_sigma`` (position m per
    axis, rotation rad about a random axis, as :class:`~mysim_jax.perception.localize.PoseNoise`);
    ``correlation_time`` s (0: the biases are constant); ``distances`` (F, G, G) m, measured
    distances between the cameras (:meth:`TeamRanging.measure`; NaN: none), taken as carrying
    white noise of spread ``distance_sigma`` m."""
    has = np.asarray(has, bool)
    F, G = has.shape
    sp, st = (float(v) for v in pose_sigma)
    if not (sp >= 0 and st >= 0 and correlation_time >= 0 and frames_per_independent >= 1 and gate > 0):
        raise PerceptionError(f"self-calibration needs pose_sigma (>= 0 m, >= 0 rad), correlation_time >= 0, "
                              f"frames_per_independent >= 1 and gate > 0; got {pose_sigma}, {correlation_time}, "
                              f"{frames_per_independent}, {gate}")
    if distances is not None and (np.shape(distances) != (F, G, G) or not distance_sigma > 0):
        raise PerceptionError(f"self-calibration: distances between the cameras must be (frames, cameras, cameras) "
                              f"= {(F, G, G)} with a noise sigma > 0; got {np.shape(distances)} and {distance_sigma}")
    calibrate = sp > 0 or st > 0
    S0 = np.diag(np.tile(np.r_[np.full(3, max(sp * sp, 1e-12)), np.full(3, max(st * st / 3.0, 1e-12))], G))
    S, th = S0.copy(), np.zeros(6 * G)
    points, biases = np.full((F, 3), np.nan), np.zeros((F, G, 6))
    sig = dict(angle_sigma=angle_sigma, range_sigma=range_sigma)
    for k in range(F):
        if k and correlation_time > 0:
            rho = float(np.exp(-(t[k] - t[k - 1]) / correlation_time))
            th, S = rho * th, rho * rho * S + (1.0 - rho * rho) * S0
        if distances is not None and calibrate:
            th, S = _range_update(th, S, origins[k], distances[k], distance_sigma)
        cams = np.flatnonzero(has[k])
        if cams.size:
            p, b, r = origins[k, cams], bearings[k, cams], ranges[k, cams]
            x0 = fuse(method, *(_corrected(p, b, th, cams) if calibrate else (p, b)), r, **sig)
            if x0 is not None and cams.size >= 3 and calibrate:
                keep = _inliers(*_corrected(p, b, th, cams), x0, cams, S, angle_sigma, gate * np.sqrt(2.0))
                if keep.sum() >= 3:
                    J, h = _frame_information(p[keep], b[keep], x0, cams[keep], G, angle_sigma)
                    S_inv = np.linalg.inv(S)
                    S = np.linalg.inv(S_inv + J / frames_per_independent)
                    th = S @ (S_inv @ th + h / frames_per_independent)
                x0 = fuse(method, *_corrected(p, b, th, cams), r, **sig)
            if x0 is not None:
                points[k] = x0
        biases[k] = th.reshape(G, 6)
    return points, biases


def localize_self_calibrated(record, pose_noise: PoseNoise | None = None, pose_sigma=None,
                             correlation_time: float | None = None, angle_sigma: float = 2e-3,
                             range_sigma: float = 0.05, method: str = "triples_weighted",
                             ranging: TeamRanging | None = None, **options) -> Localisation:
    """:func:`~mysim_jax.perception.localize.localize_record` with the cameras' pose biases
    self-calibrated (:func:`self_calibrated_points`; estimates under ``"self_calibrated"``),
    from the rays and, with ``ranging``, the distances it measures between the record's true
    camera positions. ``pose_sigma`` and ``correlation_time`` default to ``pose_noise``'s;
    ``options``: ``frames_per_independent``, ``gate``."""
    if pose_sigma is None or correlation_time is None:
        if pose_noise is None:
            raise PerceptionError("self-calibration needs pose_sigma and correlation_time, or pose_noise")
        pose_sigma = (pose_noise.position_m, pose_noise.rotation_rad) if pose_sigma is None else pose_sigma
        correlation_time = pose_noise.correlation_time if correlation_time is None else correlation_time
    has, p, b, r = record_rays(record, pose_noise)
    if ranging is not None:
        options = {**options, "distances": ranging.measure(record.camera_p), "distance_sigma": ranging.sigma_m}
    points, _ = self_calibrated_points(record.t, has, p, b, r, pose_sigma, correlation_time,
                                       angle_sigma=angle_sigma, range_sigma=range_sigma, method=method, **options)
    return Localisation(t=np.asarray(record.t), truth=np.asarray(record.target_pos),
                        estimates={"self_calibrated": points}, n_detecting=has.sum(1))
