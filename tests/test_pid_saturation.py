"""Motor saturation in the cascaded PID's allocation (``mysim_jax/control/pid.py``, step 4).

``saturation: clip`` (the default) clips each motor alone; ``attitude_priority`` keeps the
roll and pitch torque, then the yaw torque, and moves the collective thrust to the nearest
that fits the motor limits. The reference is a linear program per case (SciPy's HiGHS, not
the closed form of :func:`attitude_priority_speeds`), on the paper's allocation matrix
written out here from the rotor constants (as ``tests/test_quadrotor.py`` does), with the
priorities of the controller's docstring:

1. the whole torque fits at some thrust: keep it;
2. else, if roll and pitch fit with no yaw: keep them, keep the largest fraction of yaw
   that fits;
3. else: drop yaw, keep the largest fraction of roll and pitch that fits;

then the thrust closest to the demand that fits what was kept.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linprog

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.control.pid import attitude_priority_speeds
from mysim_jax.sim import rollout

C, K, L, M, G = 2.88e-7, 7.24e-9, 0.096, 0.28, 9.81
INERTIA = [1.4e-4, 1.4e-4, 2.17e-4]
H = math.sqrt(2) / 2 * L * C
PAPER = np.array([[C, C, C, C], [H, -H, -H, H], [-H, -H, H, H], [K, -K, K, -K]])   # (T, τx, τy, τz) = PAPER ω²
INV = np.linalg.inv(PAPER)


def _reference(thrust, torque, com, lo, hi):
    """The priorities above as linear programs in (T, g_rp, g_y, t): motor speeds² and
    which case applied."""
    c = np.cross(com, [0.0, 0.0, 1.0])
    a = INV @ np.concatenate([[1.0], c])                      # ω² per N of thrust
    rp = INV @ np.array([0.0, torque[0], torque[1], 0.0])
    yaw = INV @ np.array([0.0, 0.0, 0.0, torque[2]])
    # motors: lo <= a T + g_rp rp + g_y yaw <= hi
    rows = np.stack([a, rp, yaw, np.zeros(4)], axis=1)
    a_ub = np.concatenate([rows, -rows])
    b_ub = np.concatenate([np.full(4, hi), np.full(4, -lo)])

    def solve(objective, g_rp, g_y):
        bounds = [(None, None), g_rp, g_y, (0.0, None)]
        res = linprog(objective, A_ub=a_ub, b_ub=b_ub, bounds=bounds, method="highs")
        return res

    full = solve([0, 0, 0, 0], (1, 1), (1, 1))
    if full.status == 0:
        case, g_rp, g_y = 1, 1.0, 1.0
    elif solve([0, 0, 0, 0], (1, 1), (0, 0)).status == 0:
        case, g_rp = 2, 1.0
        g_y = solve([0, 0, -1, 0], (1, 1), (0, 1)).x[2]
    else:
        case, g_y = 3, 0.0
        g_rp = solve([0, -1, 0, 0], (0, 1), (0, 0)).x[1]
    # nearest thrust: min t with t >= |T - thrust|
    extra_ub = np.array([[1.0, 0, 0, -1.0], [-1.0, 0, 0, -1.0]])
    res = linprog([0, 0, 0, 1], A_ub=np.concatenate([a_ub, extra_ub]),
                  b_ub=np.concatenate([b_ub, [thrust, -thrust]]),
                  bounds=[(None, None), (g_rp, g_rp), (g_y, g_y), (0.0, None)], method="highs")
    assert res.status == 0
    t_kept = res.x[0]
    return a * t_kept + g_rp * rp + g_y * yaw, case


@pytest.mark.float64
def test_attitude_priority_allocation_solves_the_priority_programs():
    rng = np.random.default_rng(7)
    hi_nominal = 2440.0 ** 2
    cases, n = [], 300
    thrust = rng.uniform(0.0, 9.0, n)                           # the four motors give 6.86 N at most
    torque = rng.normal(size=(n, 3)) * np.array([0.06, 0.06, 0.05]) * rng.uniform(0, 2, (n, 1))
    com = rng.normal(size=(n, 3)) * 0.004 * (rng.uniform(size=(n, 1)) < 0.5)   # half with a camera's offset
    lo = np.where(rng.uniform(size=n) < 0.3, rng.uniform(0, 0.2, n) * hi_nominal, 0.0)
    hi = hi_nominal * rng.uniform(0.3, 1.0, n)
    got = np.asarray(attitude_priority_speeds(
        jnp.asarray(np.broadcast_to(INV, (n, 4, 4))), jnp.asarray(thrust), jnp.asarray(torque), jnp.asarray(com),
        jnp.asarray(lo)[:, None], jnp.asarray(hi)[:, None]))
    for i in range(n):
        want, case = _reference(thrust[i], torque[i], com[i], lo[i], hi[i])
        cases.append(case)
        # measured: at most 6e-16 of the top speed² over these draws; allowed 1e-14
        np.testing.assert_allclose(got[i], want, rtol=0, atol=1e-14 * hi[i], err_msg=f"case {case}, draw {i}")
        assert np.all(got[i] >= lo[i] - 1e-9 * hi[i]) and np.all(got[i] <= hi[i] * (1 + 1e-9))
    # every branch was exercised, most draws saturating
    counts = {c: cases.count(c) for c in (1, 2, 3)}
    assert min(counts.values()) >= 20, counts


def _hover(saturation, omega_max, rate0=(0.0, 0.0, 0.0), z_ref=1.0, t_end=2.0):
    raw = {
        "name": "saturation", "sim": {"t_end": t_end, "dt": 1e-3, "output_dt": 1e-2, "integrator": "rk4",
                                      "precision": "float64"},
        "bodies": [{"name": "uav0", "mass": M, "inertia": INERTIA, "pos": [0.0, 0.0, 1.0],
                    "angvel": list(rate0)}],
        "quadrotors": [{"body": "uav0", "reference": {"center": [0.0, 0.0, z_ref]},
                        "rotors": {"omega_max": omega_max},
                        "controller": {"saturation": saturation, "feedforward": "none"}}],
    }
    scene, params, state = build(config_from_dict(raw, "t"))
    n = int(round(t_end / 1e-3))
    _, traj = jax.jit(lambda p, s: rollout(scene, p, s, n, 10))(params, state)
    quat = np.asarray(traj.phys.body_quat[:, 0])             # (w, x, y, z)
    tilt = np.arccos(np.clip(1 - 2 * (quat[:, 1] ** 2 + quat[:, 2] ** 2), -1, 1))
    return tilt, np.asarray(traj.phys.body_pos[:, 0, 2])


@pytest.mark.float64
def test_a_vehicle_short_of_thrust_keeps_its_attitude_only_with_attitude_priority():
    """Top thrust 1.1x the weight (omega_max 1630 rad/s instead of 2440), a setpoint 2 m
    above, a roll rate of 3 rad/s at the start: the climb asks for more than the motors
    give. Clipped motor by motor the four sit at the top speed, no torque is left and the
    vehicle tips and falls; with attitude priority it stops the roll and climbs (measured:
    clip 1.46 rad of tilt and 2.35 m lower after 2 s; attitude priority 0.15 rad at most,
    1.77 m higher)."""
    omega_max = math.sqrt(1.1 * M * G / (4 * C))
    tilt_clip, z_clip = _hover("clip", omega_max, rate0=(3.0, 0.0, 0.0), z_ref=3.0)
    tilt_prio, z_prio = _hover("attitude_priority", omega_max, rate0=(3.0, 0.0, 0.0), z_ref=3.0)
    assert tilt_clip.max() > 1.2 and z_clip[-1] < 0.0, (tilt_clip.max(), z_clip[-1])
    assert tilt_prio.max() < 0.3 and z_prio[-1] > 2.5, (tilt_prio.max(), z_prio[-1])


@pytest.mark.float64
def test_a_command_inside_the_limits_is_the_same_under_both():
    tilt_clip, z_clip = _hover("clip", 2440.0, rate0=(0.5, -0.3, 0.1), z_ref=1.2, t_end=0.5)
    tilt_prio, z_prio = _hover("attitude_priority", 2440.0, rate0=(0.5, -0.3, 0.1), z_ref=1.2, t_end=0.5)
    np.testing.assert_array_equal(tilt_clip, tilt_prio)
    np.testing.assert_array_equal(z_clip, z_prio)


def _sideways(thrust_limit, omega_max, t_end=3.0):
    """A vehicle at (-9.5, 0, 3) m with attitude priority sent to (9.5, 0, 3) m: the
    position loop asks for the tilt limit's horizontal force; returns (x, z) (T,) m."""
    raw = {
        "name": "thrust_limit", "sim": {"t_end": t_end, "dt": 1e-3, "output_dt": 1e-2, "integrator": "rk4",
                                        "precision": "float64"},
        "bodies": [{"name": "uav0", "mass": M, "inertia": INERTIA, "pos": [-9.5, 0.0, 3.0]}],
        "quadrotors": [{"body": "uav0", "reference": {"center": [9.5, 0.0, 3.0]},
                        "rotors": {"omega_max": omega_max},
                        "controller": {"saturation": "attitude_priority", "thrust_limit": thrust_limit,
                                       "feedforward": "none"}}],
    }
    scene, params, state = build(config_from_dict(raw, "t"))
    n = int(round(t_end / 1e-3))
    _, traj = jax.jit(lambda p, s: rollout(scene, p, s, n, 10))(params, state)
    pos = np.asarray(traj.phys.body_pos[:, 0])
    return pos[:, 0], pos[:, 2]


@pytest.mark.float64
def test_vertical_priority_keeps_the_height_of_a_vehicle_short_of_thrust():
    """Top thrust 1.25x the weight (a motor fault's half thrust on the capture UAVs), the
    position loop asking for the tilt limit's horizontal force (|F_d| = 1.44x the weight):
    handed on, the demand tilts the vehicle and the allocation's lower collective loses
    height; limited vertical first, the vehicle keeps more of it (measured: lowest 2.413 m
    against 2.695 m of the 3 m start). With the motors' full range (top thrust 2.5x the
    weight) the limit never acts and the flights are identical."""
    weak = math.sqrt(1.25 * M * G / (4 * C))
    _, z_none = _sideways("none", weak)
    _, z_vert = _sideways("vertical_priority", weak)
    assert z_none.min() < 2.45 and z_vert.min() > 2.65, (z_none.min(), z_vert.min())
    x_none, z_none = _sideways("none", 2440.0)
    x_vert, z_vert = _sideways("vertical_priority", 2440.0)
    np.testing.assert_array_equal(x_none, x_vert)
    np.testing.assert_array_equal(z_none, z_vert)
