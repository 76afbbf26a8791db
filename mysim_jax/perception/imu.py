"""Simulated IMU: gyroscope and accelerometer readings of one rigid body, computed from a
saved trajectory after the simulation (NumPy only; no JAX, never inside jit).

Model
-----
The IMU sits at the body's origin, which is its centre of mass (the point whose position,
velocity and acceleration the trajectory holds), so it feels no lever-arm (centripetal or
Euler) acceleration. Its axes are turned in the body by ``ImuConfig.orientation``, a unit
quaternion ``q_bi`` (scalar-first, rotating IMU-frame vectors into the body frame, the
convention of every quaternion in mysim_jax). At every IMU sample ``k`` (as written for
``sampling: point``; the default reads the means of the same quantities over a window
around the sample, see *Sampling* below)::

    true_gyro[k]  = R_bi^T ω_b                                   rad/s
    true_accel[k] = R_bi^T R_wb^T (a_w - g)                      m/s²  (specific force)
    gyro[k]       = true_gyro[k]  + gyro_bias[k]  + σ_g √rate · n_g[k]
    accel[k]      = true_accel[k] + accel_bias[k] + σ_a √rate · n_a[k]
    bias[k+1]     = bias[k] + σ_b √Δt · w[k]                     Δt = 1 / rate

with ``R_wb`` the body's attitude (columns ``NAME_qw..qz``, body → world), ``ω_b`` its
body-frame angular velocity (``NAME_wx..wz``), ``a_w`` its world-frame acceleration as the
dynamics computed it (``NAME_ax..az``; never a finite difference of positions), ``g`` the
gravity vector, and ``n``, ``w`` independent standard normal draws per sample and axis,
in the IMU frame. A body at rest and level reads ``accel = (0, 0, +9.81)``, ``gyro = 0``.

Noise parameters are the continuous-time densities of the Kalibr / EuRoC ``imu.yaml``:

* white-noise densities ``σ_g`` (``gyro_noise_density``, rad/s/√Hz) and ``σ_a``
  (``accel_noise_density``, m/s²/√Hz): on an Allan-deviation plot the −½ slope,
  ``ADEV(τ) = σ / √τ``, so ``σ`` is the ADEV at τ = 1 s;
* bias random-walk densities ``σ_bg`` (``gyro_random_walk``, rad/s²/√Hz) and ``σ_ba``
  (``accel_random_walk``, m/s³/√Hz): the +½ slope, ``ADEV(τ) = σ_b √(τ / 3)``.

The defaults are the paper's Table IMU_simulator. The paper gives the two "bias drift"
values in m/s³ and rad/s² without the /√Hz; they are read here as random-walk densities,
Kalibr's ``accelerometer_random_walk`` and ``gyroscope_random_walk``.

Sampling (``ImuConfig.sampling``): the IMU's samples are at every ``k``-th row of the
trajectory, so its rate must be the trajectory's output rate divided by a whole number
``k``: a scene saved every ``sim.output_dt = 1e-3`` s (1 kHz) can feed IMUs at 1000, 500,
250, 200, ... Hz (``scripts/simulate.py --set sim.output_dt=...`` sets the interval).

* ``"interval_mean"`` (default): each reading is the mean over ``[t_k - Δt, t_k + Δt]``
  (``Δt = 1 / rate``; clipped to the run at its ends) of the body-frame specific force and
  body rate, the way an integrating (delta-velocity / delta-angle) IMU with an anti-aliasing
  filter reports them. Over each interval between saved rows the world-frame velocity
  change ``v[j+1] - v[j] - g h`` (the dynamics' velocity, i.e. the exact integral of their
  acceleration) is rotated into the body by the interval's midpoint attitude, and the
  attitude change ``R_j^T R_{j+1}`` gives the rotation vector; those are summed over the
  window. The readings' time integral therefore equals the dynamics' velocity and attitude
  change exactly, however short an impact or a tether jerk is: nothing is aliased. The
  window's response is ``sinc(2 f / rate)`` (-1.6 % at 10 Hz for a 200 Hz IMU, zero at
  the Nyquist frequency). It needs the body's ``NAME_vx..vz`` columns.
* ``"point"``: instantaneous samples of the rows' ``a_w`` and ``ω_b`` (formulas above), no
  anti-aliasing. A shock shorter than ``Δt`` is then either missed or read as lasting a
  whole sample interval (a 400 m/s² jerk of 1 ms becomes a 2 m/s velocity error at 200 Hz).

File format (:func:`write_imu_csv`, :func:`read_imu_csv`): EuRoC's ``imu0/data.csv``, one
header line then one row per sample::

    #timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]
    0,1.0e-4,...

time in whole nanoseconds since the start of the run, then the measured gyro (rad/s) and
specific force (m/s²) in the IMU frame. The file holds measurements only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal
from pathlib import Path

import allantools
import numpy as np

from mysim_jax.core.config_base import NonNegFloat, PosFloat, StrictModel, UnitQuat, Vec3

EUROC_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")

_XYZ = ("x", "y", "z")
# A trajectory CSV keeps 12 significant digits (mysim_jax.io.trajectory), so the spacing
# of its times is exact only to ~1e-11 of the largest time; on top of that, steps may
# differ from their mean by this fraction of a step.
_TIME_STEP_RTOL = 1e-6
# Largest accepted | |q| - 1 | of a body quaternion (float32 runs stay near 1e-7).
_QUAT_NORM_TOL = 1e-3


class ImuError(ValueError):
    """The input to the IMU simulator is unusable; the message says what and how to fix it."""


class ImuConfig(StrictModel):
    """One IMU rigidly mounted at a body's centre of mass (see the module docstring).

    Defaults: paper Table IMU_simulator, at 200 Hz, no initial bias, IMU axes = body axes.
    A density of zero switches that noise off.
    """

    rate: PosFloat = 200.0                       # Hz, samples per second
    gyro_noise_density: NonNegFloat = 1e-4       # rad/s/√Hz (white noise)
    accel_noise_density: NonNegFloat = 2e-3      # m/s²/√Hz (white noise)
    gyro_random_walk: NonNegFloat = 1e-6         # rad/s²/√Hz (bias random walk)
    accel_random_walk: NonNegFloat = 1e-4        # m/s³/√Hz (bias random walk)
    gyro_bias_initial: Vec3 = (0.0, 0.0, 0.0)    # rad/s, bias at the first sample, IMU frame
    accel_bias_initial: Vec3 = (0.0, 0.0, 0.0)   # m/s², bias at the first sample, IMU frame
    orientation: UnitQuat = (1.0, 0.0, 0.0, 0.0)  # (w, x, y, z), rotates IMU frame → body frame
    sampling: Literal["interval_mean", "point"] = "interval_mean"   # anti-aliased means or point samples


@dataclass(frozen=True, eq=False)
class ImuData:
    """IMU samples of one body, all vectors in the IMU frame.

    Data read back from a file (:func:`read_imu_csv`) has measurements only: its truth
    and bias fields are None.
    """

    t: np.ndarray                           # (N,) s, sample times
    gyro: np.ndarray                        # (N, 3) rad/s, measured angular velocity
    accel: np.ndarray                       # (N, 3) m/s², measured specific force
    true_gyro: np.ndarray | None = None     # (N, 3) rad/s, noise- and bias-free angular velocity
    true_accel: np.ndarray | None = None    # (N, 3) m/s², noise- and bias-free specific force
    gyro_bias: np.ndarray | None = None     # (N, 3) rad/s, bias contained in ``gyro``
    accel_bias: np.ndarray | None = None    # (N, 3) m/s², bias contained in ``accel``
    body: str = ""                          # the body carrying the IMU ("" when unknown)

    @property
    def rate(self) -> float:
        """Samples per second (Hz), from the first and last sample times."""
        if len(self.t) < 2:
            raise ImuError("an IMU record of fewer than 2 samples has no rate")
        return (len(self.t) - 1) / float(self.t[-1] - self.t[0])


def simulate_imu(columns: dict[str, np.ndarray], body: str, config: ImuConfig | None = None,
                 gravity=(0.0, 0.0, -9.81), seed: int = 0) -> ImuData:
    """Simulate the IMU of ``body`` along a saved trajectory.

    ``columns``: the mapping of :func:`mysim_jax.io.trajectory.read_trajectory_csv` (or
    :func:`~mysim_jax.io.trajectory.trajectory_columns`): ``time`` (s, uniformly spaced)
    and the body's ``NAME_qw..qz``, ``NAME_ax..az`` (m/s², world) and ``NAME_wx..wz``
    (rad/s, body frame), each ``(n_rows,)``. ``config``: the IMU (default
    ``ImuConfig()``). ``gravity``: the scene's gravity vector (m/s², world frame; the
    scene's ``gravity`` setting). ``seed``: the noise is a deterministic function of the
    seed and the number of samples.

    Raises :class:`ImuError` for an unknown body, missing columns, fewer than 2 rows,
    non-finite values, non-uniform time, or an IMU rate that does not divide the
    trajectory's output rate.
    """
    config = ImuConfig() if config is None else config
    mean = config.sampling == "interval_mean"
    time, quat, acc_world, rate_body, vel_world = _body_columns(columns, body, velocity=mean)
    n_rows = len(time)
    step = _uniform_step(time)
    every = _decimation(step, config.rate)

    rows = slice(0, n_rows, every)
    t = np.array(time[rows])
    norm = np.linalg.norm(quat, axis=-1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > _QUAT_NORM_TOL)
    if bad.size:
        row = bad[0]
        raise ImuError(f"{body}_qw..qz is not a unit quaternion at row {row} (t = {time[row]:g} s, norm "
                       f"{norm[row]:.6g}): the columns must hold the body's attitude as a scalar-first unit "
                       "quaternion, as scripts/simulate.py writes it")
    r_bi = _rotation_matrices(np.asarray(config.orientation, float))  # (3, 3) IMU → body
    gravity = np.asarray(gravity, float)
    if mean:
        force_body, rate_body_mean = _interval_means(time, quat / norm[:, None], vel_world, gravity, every)
        true_accel, true_gyro = force_body @ r_bi, rate_body_mean @ r_bi
    else:
        r_wb = _rotation_matrices(quat[rows] / norm[rows, None])          # (n, 3, 3) body → world
        # row-vector form: (R_bi^T R_wb^T f)^T = f^T R_wb R_bi
        specific_force_world = acc_world[rows] - gravity
        true_accel = np.einsum("ni,nij,jk->nk", specific_force_world, r_wb, r_bi)
        true_gyro = np.einsum("ni,ij->nj", rate_body[rows], r_bi)

    n = len(t)
    rng = np.random.default_rng(seed)
    white_gyro = config.gyro_noise_density * np.sqrt(config.rate) * rng.standard_normal((n, 3))
    white_accel = config.accel_noise_density * np.sqrt(config.rate) * rng.standard_normal((n, 3))
    dt = 1.0 / config.rate
    gyro_bias = _random_walk(rng, config.gyro_bias_initial, config.gyro_random_walk * np.sqrt(dt), n)
    accel_bias = _random_walk(rng, config.accel_bias_initial, config.accel_random_walk * np.sqrt(dt), n)

    return ImuData(t=t, gyro=true_gyro + gyro_bias + white_gyro, accel=true_accel + accel_bias + white_accel,
                   true_gyro=true_gyro, true_accel=true_accel, gyro_bias=gyro_bias, accel_bias=accel_bias,
                   body=body)


def _interval_means(time, quat, vel, gravity, every: int) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame specific force (m/s²) and body rate (rad/s), ``(n_samples, 3)`` each, of
    the ``"interval_mean"`` sampling: the means over ``[t_k - Δt, t_k + Δt]`` at every
    ``every``-th row (see the module docstring)."""
    r = _rotation_matrices(quat)                                       # (n, 3, 3) body → world
    h = np.diff(time)                                                  # (n-1,) s
    rel = np.einsum("nji,njk->nik", r[:-1], r[1:])                     # R_j^T R_{j+1}
    theta = _so3_log(rel)                                              # (n-1, 3) rad, body frame at j
    r_mid = np.einsum("nij,njk->nik", r[:-1], _so3_exp(0.5 * theta))   # attitude at the interval's middle
    dv = vel[1:] - vel[:-1] - gravity * h[:, None]                     # (n-1, 3) m/s, world
    dv_body = np.einsum("ni,nij->nj", dv, r_mid)                       # R_mid^T dv
    cum_v = np.concatenate([np.zeros((1, 3)), np.cumsum(dv_body, axis=0)])
    cum_a = np.concatenate([np.zeros((1, 3)), np.cumsum(theta, axis=0)])
    n = len(time)
    centre = np.arange(0, n, every)
    lo, hi = np.maximum(centre - every, 0), np.minimum(centre + every, n - 1)
    span = (time[hi] - time[lo])[:, None]
    return (cum_v[hi] - cum_v[lo]) / span, (cum_a[hi] - cum_a[lo]) / span


def _so3_exp(w: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` rotation matrices of rotation vectors ``(..., 3)`` (rad; Rodrigues)."""
    angle = np.linalg.norm(w, axis=-1)[..., None, None]
    k = np.zeros(w.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    k = k - np.swapaxes(k, -1, -2)
    small = angle < 1e-8
    a = np.where(small, 1.0 - angle**2 / 6, np.sin(angle) / np.where(small, 1.0, angle))
    b = np.where(small, 0.5 - angle**2 / 24, (1 - np.cos(angle)) / np.where(small, 1.0, angle) ** 2)
    return np.eye(3) + a * k + b * (k @ k)


def _so3_log(r: np.ndarray) -> np.ndarray:
    """``(..., 3)`` rotation vectors (rad) of rotation matrices ``(..., 3, 3)`` with angles
    below π (consecutive saved attitudes of a body)."""
    cos = np.clip((np.trace(r, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    angle = np.arccos(cos)
    vee = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], axis=-1)
    sin = np.sin(angle)
    small = angle < 1e-6
    scale = np.where(small, 0.5 + angle**2 / 12, angle / (2 * np.where(small, 1.0, sin)))
    return scale[..., None] * vee


def _rotation_matrices(q: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` matrices of unit quaternions ``(..., 4)`` (w, x, y, z); the columns
    are the rotated frame's axes (``v_world = R @ v_body`` for a body → world quaternion)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    r = np.empty(q.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - w * z)
    r[..., 0, 2] = 2 * (x * z + w * y)
    r[..., 1, 0] = 2 * (x * y + w * z)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - w * x)
    r[..., 2, 0] = 2 * (x * z - w * y)
    r[..., 2, 1] = 2 * (y * z + w * x)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def _random_walk(rng: np.random.Generator, start, step_std: float, n: int) -> np.ndarray:
    """``(n, 3)`` walk from ``start`` with independent N(0, step_std²) steps per axis."""
    walk = np.empty((n, 3))
    walk[0] = start
    walk[1:] = np.asarray(start, float) + np.cumsum(step_std * rng.standard_normal((n - 1, 3)), axis=0)
    return walk


def _body_columns(columns, body: str, velocity: bool = False):
    """``time (n,)``, ``quat (n, 4)``, ``acc (n, 3)``, ``angvel (n, 3)`` and ``vel (n, 3)`` (None
    unless ``velocity``) of ``body``, checked."""
    bodies = sorted(name[: -len("_qw")] for name in columns if name.endswith("_qw"))
    if body not in bodies:
        listed = ", ".join(bodies) if bodies else "none"
        if f"{body}_x" in columns:
            raise ImuError(f"'{body}' is a point mass (no attitude columns {body}_qw..qz): an IMU needs a rigid "
                           f"body; the trajectory's bodies are: {listed}")
        raise ImuError(f"no body '{body}' in the trajectory; its bodies are: {listed}")
    names = (["time"] + [f"{body}_q{a}" for a in ("w",) + _XYZ] + [f"{body}_a{a}" for a in _XYZ]
             + [f"{body}_w{a}" for a in _XYZ] + ([f"{body}_v{a}" for a in _XYZ] if velocity else []))
    missing = [name for name in names if name not in columns]
    if missing:
        raise ImuError(f"the trajectory has no column {', '.join(missing)}: the IMU needs the time, the body's "
                       "attitude, its acceleration from the dynamics and its body rates (and, for the default "
                       "sampling 'interval_mean', its velocity), which every trajectory.csv of scripts/simulate.py "
                       "holds (mysim_jax.io.trajectory); simulate the scene with it")
    arrays = {name: np.asarray(columns[name], dtype=float) for name in names}
    n_rows = arrays["time"].shape
    for name, values in arrays.items():
        if values.ndim != 1 or values.shape != n_rows:
            raise ImuError(f"column {name} has shape {values.shape}, the time column {n_rows}: every column must be "
                           "one value per row of the trajectory")
    if n_rows[0] < 2:
        raise ImuError(f"the trajectory has {n_rows[0]} row(s); the IMU needs at least 2 to know the sampling "
                       "interval: simulate for longer (sim.t_end) or save more often (sim.output_dt)")
    for name, values in arrays.items():
        finite = np.isfinite(values)
        if not finite.all():
            row = int(np.argmin(finite))
            when = "" if name == "time" else f" (t = {arrays['time'][row]:g} s)"
            raise ImuError(f"column {name} is not finite at row {row}{when}: a run that failed there (scripts/"
                           "simulate.py keeps the finite part of a failed run) must be fixed, or its rows before "
                           "that time passed on their own")
    quat = np.stack([arrays[f"{body}_q{a}"] for a in ("w",) + _XYZ], axis=-1)
    acc = np.stack([arrays[f"{body}_a{a}"] for a in _XYZ], axis=-1)
    angvel = np.stack([arrays[f"{body}_w{a}"] for a in _XYZ], axis=-1)
    vel = np.stack([arrays[f"{body}_v{a}"] for a in _XYZ], axis=-1) if velocity else None
    return arrays["time"], quat, acc, angvel, vel


def _uniform_step(time: np.ndarray) -> float:
    """The trajectory's output interval (s); every step must match it."""
    n = len(time)
    step = (time[-1] - time[0]) / (n - 1)
    steps = np.diff(time)
    tol = _TIME_STEP_RTOL * abs(step) + 1e-11 * np.max(np.abs(time))
    bad = np.flatnonzero(~(np.abs(steps - step) <= tol) | (steps <= 0))
    if step <= 0 or bad.size:
        row = int(bad[0]) if bad.size else 0
        raise ImuError(f"time is not uniformly increasing: rows {row} and {row + 1} are {steps[row]:g} s apart, the "
                       f"mean step is {step:g} s; the IMU needs a trajectory saved at a fixed interval (scripts/"
                       "simulate.py writes one every sim.output_dt): do not join runs or drop rows")
    return float(step)


def _decimation(step: float, imu_rate: float) -> int:
    """How many trajectory rows one IMU sample spans (a whole number, else an error)."""
    out_rate = 1.0 / step
    ratio = out_rate / imu_rate
    every = int(round(ratio))
    if every < 1 or abs(ratio - every) > _TIME_STEP_RTOL * ratio:
        raise ImuError(
            f"an IMU at {imu_rate:g} Hz needs a trajectory saved at a whole multiple of {imu_rate:g} Hz, i.e. "
            f"sim.output_dt = 1 / ({imu_rate:g} k) s for a whole k (e.g. --set sim.output_dt={1.0 / imu_rate:.6g}; it "
            f"must also be a multiple of sim.dt), but this one is saved every {step:.6g} s ({out_rate:.6g} Hz); "
            f"or choose an IMU rate of {out_rate:.6g} Hz divided by a whole number")
    return every


# --- files -----------------------------------------------------------------------------


def write_imu_csv(path: str | Path, data: ImuData) -> None:
    """Write the measurements of ``data`` as an EuRoC ``imu0/data.csv`` (module docstring):
    time in whole nanoseconds, gyro (rad/s) and accel (m/s²) with 17 significant digits
    (they read back exactly)."""
    table = np.empty(len(data.t), dtype=[("t", np.int64)] + [(f"c{i}", float) for i in range(6)])
    table["t"] = np.rint(np.asarray(data.t) * 1e9).astype(np.int64)
    for i in range(3):
        table[f"c{i}"] = data.gyro[:, i]
        table[f"c{i + 3}"] = data.accel[:, i]
    np.savetxt(path, table, delimiter=",", header=EUROC_HEADER, comments="", fmt=["%d"] + ["%.17g"] * 6)


def read_imu_csv(path: str | Path, body: str = "") -> ImuData:
    """Read an IMU CSV in EuRoC format (as :func:`write_imu_csv` writes it) into
    :class:`ImuData` (measurements only; ``body`` names the body if known). Raises
    :class:`ImuError` naming the file if it is not such a file."""
    path = Path(path)
    with open(path) as fh:
        header = fh.readline().strip()
    if not header.startswith("#") or len(header.split(",")) != 7:
        raise ImuError(f"{path}: not an IMU CSV: the first line must be the EuRoC header of 7 columns "
                       f"({EUROC_HEADER})")
    try:
        stamps = np.loadtxt(path, delimiter=",", skiprows=1, usecols=0, dtype=np.int64, ndmin=1)
        values = np.loadtxt(path, delimiter=",", skiprows=1, usecols=range(1, 7), dtype=float, ndmin=2)
    except ValueError as exc:
        raise ImuError(f"{path}: not an IMU CSV (rows of an integer timestamp in ns and 6 numbers): {exc}") from None
    return ImuData(t=stamps * 1e-9, gyro=values[:, :3], accel=values[:, 3:], body=body)


# --- Allan deviation -------------------------------------------------------------------


def allan_deviation(x, rate: float, taus) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of a rate signal (allantools ``oadev``, frequency data).

    ``x``: ``(N,)`` or ``(N, k)`` samples at ``rate`` Hz, e.g. a gyro's rad/s or
    ``measured - true``. ``taus``: ``(M,)`` averaging times (s). Each τ is rounded to a
    whole number of samples; τ shorter than one sample or longer than half the record,
    and duplicates, are dropped. Returns ``(taus_used (M',), adev (M',) or (M', k))``, the
    deviation in the units of ``x``.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim not in (1, 2) or len(x) < 3:
        raise ImuError(f"allan_deviation takes (N,) or (N, k) samples with N >= 3, got shape {x.shape}")
    if not np.isfinite(x).all():
        raise ImuError("allan_deviation: the samples contain NaN or inf")
    taus = np.atleast_1d(np.asarray(taus, dtype=float))
    samples = np.round(taus * rate)
    # oadev needs at least 2 second differences x[i + 2m] - 2 x[i + m] + x[i] of the N + 1
    # phase points: m <= (N - 1) / 2
    keep = (samples >= 1) & (samples <= (len(x) - 1) // 2)
    if not keep.any():
        raise ImuError(f"allan_deviation: no τ between one sample ({1 / rate:g} s) and half the record "
                       f"({(len(x) - 1) // 2 / rate:g} s) among those asked for")
    columns = x[:, None] if x.ndim == 1 else x
    used, devs = None, []
    for col in columns.T:
        used, dev, _, _ = allantools.oadev(col, rate=float(rate), data_type="freq", taus=taus[keep])
        devs.append(dev)
    adev = np.stack(devs, axis=-1)
    return np.asarray(used), adev[:, 0] if x.ndim == 1 else adev
