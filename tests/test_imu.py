"""The simulated IMU (mysim_jax/perception/imu.py): noise-free signals against references
derived independently, the noise's Allan deviation against the configured densities,
determinism, decimation, files, and bad input."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from pydantic import ValidationError
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

from mysim_jax.perception.imu import (EUROC_HEADER, ImuConfig, ImuError, allan_deviation, read_imu_csv,
                                      simulate_imu, write_imu_csv)

from conftest import CONFIGS

G = 9.81
NOISE_FREE = ImuConfig(gyro_noise_density=0.0, accel_noise_density=0.0, gyro_random_walk=0.0, accel_random_walk=0.0)
FLIGHT_RATE = 1000.0      # Hz, output rate of the simulated flight
FLIGHT_SECONDS = 4.0


def body_columns(n, rate, quat=(1.0, 0.0, 0.0, 0.0), acc=(0.0, 0.0, 0.0), angvel=(0.0, 0.0, 0.0), name="b",
                 turning=True):
    """Trajectory columns of one body with constant acceleration and body rates from rest at
    the origin with attitude ``quat``, ``n`` rows at ``rate`` Hz: velocities ``acc t`` and
    attitudes ``quat ⊗ exp(angvel t)`` (SciPy; with ``turning=False`` the attitude stays
    ``quat`` while the rate columns say otherwise, which only point sampling, reading each
    row's own columns, accepts). Constant columns are broadcast views (no memory per row)."""
    t = np.arange(n) / rate
    cols = {"time": t}
    if any(angvel) and turning:
        q0 = Rotation.from_quat(np.roll(quat, -1))                           # SciPy: scalar last
        q = np.roll((q0 * Rotation.from_rotvec(np.outer(t, angvel))).as_quat(canonical=False), 1, axis=-1)
        cols.update({f"{name}_q{a}": q[:, i] for i, a in enumerate("wxyz")})
    else:
        cols.update({f"{name}_q{a}": np.broadcast_to(float(v), (n,)) for a, v in zip("wxyz", quat)})
    for i, axis in enumerate("xyz"):
        cols[f"{name}_a{axis}"] = np.broadcast_to(float(acc[i]), (n,))
        cols[f"{name}_w{axis}"] = np.broadcast_to(float(angvel[i]), (n,))
        cols[f"{name}_{axis}"] = 0.5 * acc[i] * t**2 if acc[i] else np.broadcast_to(0.0, (n,))
        cols[f"{name}_v{axis}"] = acc[i] * t if acc[i] else np.broadcast_to(0.0, (n,))
    return cols


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """4 s of the small figure-eight (uav_track_small.yaml) in float64, saved at 1 kHz,
    written to and read back from a trajectory CSV as scripts/simulate.py does."""
    from mysim_jax.build import build
    from mysim_jax.config.scene import load_config
    from mysim_jax.io.trajectory import read_trajectory_csv, trajectory_columns, write_trajectory_csv
    from mysim_jax.driver import simulate

    with jax.enable_x64(True):
        config = load_config(CONFIGS / "uav_track_small.yaml", [
            f"sim.t_end={FLIGHT_SECONDS}", f"sim.output_dt={1 / FLIGHT_RATE}", "sim.precision=float64"])
        scene, params, state = build(config)
        traj = simulate(scene, params, state, config.run_settings(), progress=False)
    assert traj.ok
    path = tmp_path_factory.mktemp("flight") / "trajectory.csv"
    write_trajectory_csv(path, trajectory_columns(scene, traj))
    return read_trajectory_csv(path)


def stacked(cols, body, keys, rows=slice(None)):
    return np.stack([np.asarray(cols[f"{body}_{k}"])[rows] for k in keys], axis=-1)


# --- noise-free signals ----------------------------------------------------------------


def test_level_body_at_rest_reads_gravity_up_and_no_rotation():
    data = simulate_imu(body_columns(50, 200.0), "b", NOISE_FREE)
    # the window means sum velocity changes: round-off of a few ulp
    np.testing.assert_allclose(data.accel, np.tile([0.0, 0.0, G], (50, 1)), rtol=0, atol=1e-13)
    np.testing.assert_array_equal(data.gyro, np.zeros((50, 3)))
    assert data.t.shape == (50,) and data.body == "b" and data.rate == pytest.approx(200.0)


def test_tilted_body_and_rotated_imu_read_the_rotated_values():
    """The point-sampling formulas, row by row (attitude held while the rates are read)."""
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    point = ImuConfig(**{**NOISE_FREE.model_dump(), "sampling": "point"})
    # body rolled +90° about world x: world up is the body's +y axis
    rolled = body_columns(10, 200.0, quat=(c, s, 0.0, 0.0), angvel=(0.1, 0.2, 0.3), turning=False)
    data = simulate_imu(rolled, "b", point)
    np.testing.assert_allclose(data.accel, np.tile([0.0, G, 0.0], (10, 1)), atol=1e-14)
    np.testing.assert_allclose(data.gyro, np.tile([0.1, 0.2, 0.3], (10, 1)), atol=1e-15)
    # level body, IMU turned +90° about body z (IMU x = body y, IMU y = -body x)
    turned = ImuConfig(**{**point.model_dump(), "orientation": (c, 0.0, 0.0, s)})
    data = simulate_imu(body_columns(10, 200.0, angvel=(0.1, 0.2, 0.3), turning=False), "b", turned)
    np.testing.assert_allclose(data.accel, np.tile([0.0, 0.0, G], (10, 1)), atol=1e-14)
    np.testing.assert_allclose(data.gyro, np.tile([0.2, -0.1, 0.3], (10, 1)), atol=1e-15)
    # a body accelerating at +g upwards feels 2 g; in free fall it feels nothing
    for acc, felt in (((0.0, 0.0, G), 2 * G), ((0.0, 0.0, -G), 0.0)):
        for config in (point, NOISE_FREE):
            data = simulate_imu(body_columns(3, 200.0, acc=acc), "b", config)
            np.testing.assert_allclose(data.accel, np.tile([0.0, 0.0, felt], (3, 1)), atol=1e-13)


def test_interval_means_of_a_turning_body():
    """A body turning at a constant rate while accelerating: the anti-aliased readings are
    the constant rate, and the specific force R(t)^T (a - g) averaged over the window, which
    is the point reading at the window's centre to second order in the turn per sample."""
    rate_b, acc = np.array([0.4, -0.3, 0.9]), np.array([1.0, -2.0, 3.0])
    cols = body_columns(400, 1000.0, quat=(0.9, 0.1, -0.3, 0.2) / np.linalg.norm((0.9, 0.1, -0.3, 0.2)),
                        acc=acc, angvel=rate_b)
    mean = simulate_imu(cols, "b", ImuConfig(**{**NOISE_FREE.model_dump(), "rate": 200.0}))
    point = simulate_imu(cols, "b", ImuConfig(**{**NOISE_FREE.model_dump(), "rate": 200.0, "sampling": "point"}))
    np.testing.assert_array_equal(mean.t, point.t)
    # measured: 4.2e-14 rad/s; 1.5e-5 m/s² inside, 7.6e-3 m/s² at the ends (one-sided windows)
    np.testing.assert_allclose(mean.gyro, np.tile(rate_b, (80, 1)), rtol=0, atol=4e-13)
    np.testing.assert_allclose(mean.accel[1:-1], point.accel[1:-1], rtol=0, atol=1.5e-4)
    assert np.abs(point.accel[1:-1] - point.accel[0]).max() > 0.1        # the specific force does turn


def test_a_short_shock_is_integrated_not_aliased():
    """A level body at rest takes a 1 ms, 400 m/s² upward jerk (a tether snapping taut) in a
    trajectory saved at 1 kHz, read by a 200 Hz IMU: the anti-aliased readings integrate to
    the velocity change (0.4 m/s) wherever the jerk falls, point samples to 0 or 2 m/s."""
    n, jerk = 101, 400.0
    for row in (50, 51, 52):                                # on an IMU sample, and between samples
        cols = body_columns(n, 1000.0)
        az, vz = np.zeros(n), np.zeros(n)
        az[row], vz[row + 1:] = jerk, jerk * 1e-3
        cols.update(b_az=az, b_vz=vz)
        for sampling, expected in (("interval_mean", 0.4), ("point", 2.0 if row % 5 == 0 else 0.0)):
            data = simulate_imu(cols, "b", ImuConfig(**{**NOISE_FREE.model_dump(), "sampling": sampling}))
            dv = np.sum(data.accel[:, 2] - G) / data.rate                 # ∫ (f_z - g) dt over the samples
            assert dv == pytest.approx(expected, abs=1e-12), (row, sampling)


def test_strapdown_integration_of_the_true_signals_reproduces_the_flight(flight):
    """Integrate the noise-free gyro and specific force of a rotated IMU (cubic splines
    through the 200 Hz samples, SciPy's DOP853) from the flight's initial state; the result
    must follow the simulator's positions, velocities and attitudes."""
    q_bi = Rotation.from_euler("xyz", [0.3, -0.2, 0.5])
    config = ImuConfig(**{**NOISE_FREE.model_dump(), "orientation": tuple(np.roll(q_bi.as_quat(), 1))})
    data = simulate_imu(flight, "uav0", config)
    rows = slice(0, None, 5)                                    # 1 kHz trajectory, 200 Hz IMU
    np.testing.assert_array_equal(data.t, flight["time"][rows])
    gyro, accel = CubicSpline(data.t, data.true_gyro), CubicSpline(data.t, data.true_accel)
    gravity = np.array([0.0, 0.0, -G])

    def rhs(t, y):                   # y = (R_world←imu (9), v (3), p (3))
        r = y[:9].reshape(3, 3)
        wx, wy, wz = gyro(t)
        omega = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
        return np.concatenate([(r @ omega).ravel(), r @ accel(t) + gravity, y[9:12]])

    attitude = Rotation.from_quat(stacked(flight, "uav0", ("qx", "qy", "qz", "qw"), rows)) * q_bi   # SciPy: scalar last
    pos, vel = stacked(flight, "uav0", "xyz", rows), stacked(flight, "uav0", ("vx", "vy", "vz"), rows)
    y0 = np.concatenate([attitude[0].as_matrix().ravel(), vel[0], pos[0]])
    sol = solve_ivp(rhs, (data.t[0], data.t[-1]), y0, method="DOP853", rtol=1e-11, atol=1e-12, t_eval=data.t)
    assert sol.success
    r = sol.y[:9].T.reshape(-1, 3, 3)
    angle = Rotation.from_matrix(np.einsum("nji,njk->nik", attitude.as_matrix(), r)).magnitude()
    # Measured with the default anti-aliased sampling: 3.3e-5 rad (the window's sinc response
    # on the turn rates), 0.11 mm/s, 0.15 mm after 4 s. With point samples: 8e-6 rad,
    # 0.26 mm/s, 0.42 mm: the flight's saved accelerations hold the controller's input of
    # the step that starts there (zero-order hold), half a step ahead of the average.
    assert np.ptp(pos, axis=0).min() > 0.19 and np.abs(data.true_gyro).max() > 0.7   # a real manoeuvre
    assert angle.max() < 1e-4
    assert np.abs(sol.y[9:12].T - vel).max() < 1e-3
    assert np.abs(sol.y[12:].T - pos).max() < 1.5e-3


# --- Allan deviation of the noise ------------------------------------------------------


def white_and_walk_densities(taus, adev):
    """Fit ADEV(τ)² = N²/τ + K²τ/3 (white noise N, bias random walk K) to one ADEV curve.

    Linear least squares in (N², K²) on residuals relative to the curve, weighted by
    1/√τ: the relative scatter of an ADEV point grows like √(τ / duration)."""
    weight = taus ** -0.5
    design = np.stack([1.0 / taus, taus / 3.0], axis=-1) / adev[:, None] ** 2 * weight[:, None]
    (n2, k2), *_ = np.linalg.lstsq(design, weight, rcond=None)
    return np.sqrt(n2), np.sqrt(k2)


def check_densities(data, config):
    """Estimated N and K of every axis of both sensors, over τ from 2 samples to 1/20 of
    the record, against the configured densities."""
    duration = len(data.t) / config.rate
    taus = np.logspace(np.log10(2.0 / config.rate), np.log10(duration / 20.0), 24)
    for noise, white, walk in ((data.gyro - data.true_gyro, config.gyro_noise_density, config.gyro_random_walk),
                               (data.accel - data.true_accel, config.accel_noise_density, config.accel_random_walk)):
        used, adev = allan_deviation(noise, config.rate, taus)
        assert len(used) == 24
        for axis in range(3):
            n, k = white_and_walk_densities(used, adev[:, axis])
            # scatter over 20 seeds (std of N/N0, K/K0): N 0.07 %, K 1-2 % (at most 5.6 %)
            assert n == pytest.approx(white, rel=0.01)
            assert k == pytest.approx(walk, rel=0.10)


def test_allan_deviation_of_a_static_run_gives_the_table_densities():
    """The paper's densities, whose crossovers (τ = √3 N / K) are at 35 s (accelerometer)
    and 173 s (gyroscope): the gyro's needs ~4000 crossovers of data for a K within a few
    percent, 8 days, affordable at 2 Hz (the densities do not depend on the rate)."""
    config = ImuConfig(rate=2.0)
    assert (config.accel_noise_density, config.gyro_noise_density) == (2e-3, 1e-4)
    assert (config.accel_random_walk, config.gyro_random_walk) == (1e-4, 1e-6)
    data = simulate_imu(body_columns(int(8 * 24 * 3600 * config.rate), config.rate), "b", config, seed=1)
    check_densities(data, config)


def test_allan_deviation_of_a_moving_run(flight):
    """The simulated flight, repeated for ~2 h, through a rotated IMU at 200 Hz with initial
    biases. Its random walks are raised (K = N numerically) to put both crossovers at
    √3 s, where ~4000 crossovers take 2 h of samples."""
    lap = {name: values[:4000:5] for name, values in flight.items() if name.startswith("uav0_")}   # 4 s at 200 Hz
    laps = 1732
    cols = {name: np.tile(values, laps) for name, values in lap.items()}
    cols["time"] = np.arange(len(lap["uav0_qw"]) * laps) / 200.0
    config = ImuConfig(rate=200.0, gyro_random_walk=1e-4, accel_random_walk=2e-3, gyro_bias_initial=(0.01, -0.02, 0.03),
                       accel_bias_initial=(0.1, 0.2, -0.1), orientation=(0.9, 0.1, -0.3, 0.2))
    data = simulate_imu(cols, "uav0", config, seed=2)
    assert np.ptp(data.true_gyro, axis=0).min() > 1.0                # the signal moves
    np.testing.assert_allclose(data.gyro_bias[0], config.gyro_bias_initial, rtol=1e-15)
    np.testing.assert_allclose(data.accel_bias[0], config.accel_bias_initial, rtol=1e-15)
    check_densities(data, config)


def test_allan_deviation_shapes_and_taus():
    x = np.random.default_rng(0).standard_normal((1000, 2))
    used, adev = allan_deviation(x, 100.0, [0.001, 0.01, 0.0149, 0.02, 1.0, 4.99, 5.0, 100.0])
    # dropped: below one sample, past half the record, repeats (0.0149 s rounds to 1 sample)
    np.testing.assert_allclose(used, [0.01, 0.02, 1.0, 4.99])
    assert adev.shape == (4, 2)
    used1, adev1 = allan_deviation(x[:, 1], 100.0, used)
    np.testing.assert_array_equal(used1, used)
    np.testing.assert_allclose(adev1, adev[:, 1], rtol=1e-14)
    with pytest.raises(ImuError, match="no τ between"):
        allan_deviation(x, 100.0, [100.0])
    with pytest.raises(ImuError, match="NaN or inf"):
        allan_deviation(np.full(10, np.nan), 1.0, [1.0])


# --- determinism, decimation, files ------------------------------------------------------


def test_same_seed_same_data_another_seed_different():
    cols = body_columns(500, 200.0)
    a, b, c = (simulate_imu(cols, "b", seed=s) for s in (7, 7, 8))
    for field in ("gyro", "accel", "gyro_bias", "accel_bias"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        assert not np.any(getattr(a, field)[1:] == getattr(c, field)[1:])


def test_decimation_takes_every_kth_row(flight):
    full = simulate_imu(flight, "uav0", ImuConfig(rate=FLIGHT_RATE, sampling="point"))
    for rate, k in ((500.0, 2), (200.0, 5), (100.0, 10)):
        data = simulate_imu(flight, "uav0", ImuConfig(rate=rate, sampling="point"))
        assert len(data.t) == int(FLIGHT_SECONDS * rate) + 1 and data.rate == pytest.approx(rate)
        np.testing.assert_array_equal(data.t, flight["time"][::k])
        np.testing.assert_array_equal(data.true_gyro, full.true_gyro[::k])
        np.testing.assert_array_equal(data.true_accel, full.true_accel[::k])
    with pytest.raises(ImuError, match=r"IMU at 300 Hz.*sim.output_dt.*saved every 0.001 s \(1000 Hz\)"):
        simulate_imu(flight, "uav0", ImuConfig(rate=300.0))
    with pytest.raises(ImuError, match="IMU at 2000 Hz"):                      # faster than the trajectory
        simulate_imu(flight, "uav0", ImuConfig(rate=2000.0))


def test_csv_round_trip(tmp_path):
    data = simulate_imu(body_columns(200, 200.0, angvel=(0.1, 0.2, 0.3)), "b", seed=3)
    path = tmp_path / "imu0.csv"
    write_imu_csv(path, data)
    lines = path.read_text().splitlines()
    assert lines[0] == EUROC_HEADER and len(lines) == 201
    assert lines[2].split(",")[0] == "5000000"                                    # ns
    back = read_imu_csv(path, body="b")
    np.testing.assert_allclose(back.t, data.t, rtol=0, atol=0.5e-9)
    np.testing.assert_array_equal(back.gyro, data.gyro)
    np.testing.assert_array_equal(back.accel, data.accel)
    assert back.body == "b" and back.true_gyro is None
    (tmp_path / "bad.csv").write_text("time,x\n0,1\n")
    with pytest.raises(ImuError, match="bad.csv: not an IMU CSV"):
        read_imu_csv(tmp_path / "bad.csv")
    (tmp_path / "short.csv").write_text(EUROC_HEADER + "\n0,1,2,3\n")
    with pytest.raises(ImuError, match="short.csv: not an IMU CSV"):
        read_imu_csv(tmp_path / "short.csv")


# --- bad input -----------------------------------------------------------------------------


def _without(cols, *names):
    return {k: v for k, v in cols.items() if k not in names}


def _with(cols, name, row, value):
    out = dict(cols)
    out[name] = np.array(cols[name], dtype=float)
    out[name][row] = value
    return out


GOOD = body_columns(20, 200.0)
BAD_INPUTS = {
    "unknown body": (GOOD, "uav9", r"no body 'uav9' in the trajectory; its bodies are: b"),
    "point mass": ({**GOOD, "knot_x": GOOD["b_x"]}, "knot", r"'knot' is a point mass.*bodies are: b"),
    "no accelerations": (_without(GOOD, "b_ax", "b_ay", "b_az"), "b",
                         r"no column b_ax, b_ay, b_az.*scripts/simulate.py"),
    "no body rates": (_without(GOOD, "b_wz"), "b", r"no column b_wz.*scripts/simulate.py"),
    "no velocities": (_without(GOOD, "b_vx"), "b", r"no column b_vx.*'interval_mean', its velocity"),
    "no time": (_without(GOOD, "time"), "b", r"no column time"),
    "one row": ({k: v[:1] for k, v in GOOD.items()}, "b", r"1 row\(s\); the IMU needs at least 2"),
    "NaN": (_with(GOOD, "b_ay", 7, np.nan), "b", r"column b_ay is not finite at row 7 \(t = 0.035 s\)"),
    "inf time": (_with(GOOD, "time", 19, np.inf), "b", r"column time is not finite at row 19"),
    "uneven time": (_with(GOOD, "time", 5, 0.0251), "b", r"not uniformly increasing: rows 4 and 5 are 0.0051 s apart"),
    "backwards time": ({**GOOD, "time": GOOD["time"][::-1]}, "b", r"not uniformly increasing"),
    "not a unit quaternion": (_with(GOOD, "b_qw", 3, 2.0), "b", r"b_qw..qz is not a unit quaternion at row 3"),
    "ragged column": ({**GOOD, "b_wx": np.zeros(19)}, "b", r"column b_wx has shape \(19,\)"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_is_a_clear_error(case):
    cols, body, message = BAD_INPUTS[case]
    with pytest.raises(ImuError, match=message):
        simulate_imu(cols, body)


def test_config_is_validated():
    assert ImuConfig(orientation=(2.0, 0.0, 0.0, 0.0)).orientation == (1.0, 0.0, 0.0, 0.0)   # normalised
    for bad in ({"rate": 0.0}, {"gyro_noise_density": -1e-4}, {"accel_random_walk": float("nan")},
                {"gyro_bias_initial": (0.0, 0.0)}, {"orientation": (0.0, 0.0, 0.0, 0.0)}, {"rte": 200.0}):
        with pytest.raises(ValidationError):
            ImuConfig(**bad)
