"""``controller.descent_limit: braking`` (``mysim_jax.control.setpoint.brake_descent``):
a velocity-mode descent slowed to what the vehicle can stop from above the flyable box's
floor, planned on the rotors' present top thrust (which a motor fault lowers).

The vehicle is one quadrotor with the capture scenes' controller gains, commanded straight
down at 3 m/s from 4 m over a box whose floor is 1.5 m."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.control.setpoint import Setpoint
from mysim_jax.core.config_base import ConfigError
from mysim_jax.sim import step

C, M, G = 2.88e-7, 0.28, 9.81
CAPTURE_GAINS = {"position": {"kp": [2.0, 2.0, 4.0], "ki": [0.3, 0.3, 1.0], "kd": [1.2, 1.2, 2.0]},
                 "attitude": {"kp": [2e5, 2e5, 6e4], "ki": [2e4, 2e4, 500.0], "kd": [4e4, 4e4, 1.2e4]}}


def _raw(descent_limit, omega_max, mode="velocity"):
    return {"name": "descent", "sim": {"t_end": 3.0, "dt": 1e-3, "output_dt": 1e-2, "integrator": "rk4",
                                       "precision": "float64"},
            "bodies": [{"name": "uav0", "mass": M, "inertia": [1.4e-4, 1.4e-4, 2.17e-4], "pos": [0.0, 0.0, 4.0]}],
            "quadrotors": [{"body": "uav0", "rotors": {"omega_max": omega_max},
                            "controller": {"saturation": "attitude_priority", "descent_limit": descent_limit,
                                           "setpoint_mode": mode, **CAPTURE_GAINS,
                                           "flyable_box": {"low": [-5.0, -5.0, 1.5], "high": [5.0, 5.0, 7.0]}}}]}


def _heights(descent_limit, omega_max):
    """(3000,) m: the vehicle's height every millisecond for 3 s."""
    scene, params, state = build(config_from_dict(_raw(descent_limit, omega_max), "t"))
    down = Setpoint.from_velocity(jnp.array([[0.0, 0.0, -3.0]]))

    def one(s, _):
        s = step(scene, params, s, down)
        return s, s.phys.body_pos[0, 2]

    _, z = jax.jit(lambda s: jax.lax.scan(one, s, None, length=3000))(state)
    return np.asarray(z)


@pytest.mark.float64
def test_a_vehicle_short_of_thrust_stops_above_the_floor_only_with_braking():
    """Top thrust 1.25x the weight: commanded down at 3 m/s, the box's floor zeroes the
    setpoint at 1.5 m too late to stop and the vehicle reaches the ground; braking slows
    the descent in time (measured: lowest -0.36 m without, 1.444 m with). With the motors'
    full range the two fly alike for the first half second (the limit is not yet binding)
    and braking stops higher (1.246 m against 1.050 m)."""
    weak = math.sqrt(1.25 * M * G / (4 * C))
    z_none, z_brake = _heights("none", weak), _heights("braking", weak)
    assert z_none.min() < 0.0 and z_brake.min() > 1.4, (z_none.min(), z_brake.min())
    z_none, z_brake = _heights("none", 2440.0), _heights("braking", 2440.0)
    np.testing.assert_array_equal(z_none[:500], z_brake[:500])
    assert z_brake.min() > z_none.min() + 0.15, (z_none.min(), z_brake.min())


def test_braking_needs_velocity_setpoints():
    with pytest.raises(ConfigError, match="descent_limit: braking limits velocity setpoints"):
        config_from_dict(_raw("braking", 2440.0, mode="position"), "t")
