"""Closed-form derivatives of the quadrotor reference with a ramp that is not 1 s.

``r_d(t) = c + A ⊙ sin(m ⊙ 2π s(t)/T + φ)`` with the time warp ``s(t)``: its rate ``ṡ``
rises from 0 to 1 over ``ramp`` seconds by the quintic smooth step ``6x⁵ − 15x⁴ + 10x³``
(``x = t/ramp``), so ``s = ramp (x⁶ − 3x⁵ + 5x⁴/2)`` during the ramp (the integral of
``ṡ``) and ``t − ramp/2`` after. Every derivative of ``s`` during the ramp carries a
power of ``1/ramp``; with ``ramp = 1`` (as in ``tests/test_pid.py``) a missing factor is
invisible. Here ``ramp = 0.7`` s and ``T = 2.3`` s, and the reference is re-written below
from that definition and differentiated by nested forward-mode autodiff.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.control.reference import reference_derivatives

pytestmark = pytest.mark.float64

RAMP, PERIOD = 0.7, 2.3
CENTER, AMPLITUDE = np.array([0.1, -0.2, 1.5]), np.array([1.2, 0.8, 0.3])
MULTIPLE, PHASE = np.array([1.0, 2.0, 3.0]), np.array([0.3, 0.0, -1.0])
YAW = {"center": 0.2, "amplitude": 0.6, "multiple": 2.0, "phase": 0.5}


def _warp(t):
    x = jnp.clip(t / RAMP, 0.0, 1.0)
    return jnp.where(t < RAMP, RAMP * (x ** 6 - 3.0 * x ** 5 + 2.5 * x ** 4), t - 0.5 * RAMP)


def _position(t):
    return CENTER + AMPLITUDE * jnp.sin(MULTIPLE * 2.0 * jnp.pi * _warp(t) / PERIOD + PHASE)


def _yaw(t):
    return YAW["center"] + YAW["amplitude"] * jnp.sin(YAW["multiple"] * 2.0 * jnp.pi * _warp(t) / PERIOD + YAW["phase"])


def _derivative(f, n):
    for _ in range(n):
        f = (lambda g: (lambda u: jax.jvp(g, (u,), (jnp.ones_like(u),))[1]))(f)
    return f


def test_reference_derivatives_with_a_ramp_of_0_7_s():
    raw = {
        "name": "ramp",
        "sim": {"t_end": 1.0, "dt": 1e-3, "output_dt": 1e-3, "integrator": "rk4", "precision": "float64"},
        "bodies": [{"name": "uav0", "mass": 0.28, "inertia": [1.4e-4, 1.4e-4, 2.17e-4], "pos": CENTER.tolist()}],
        "quadrotors": [{"body": "uav0", "reference": {
            "center": CENTER.tolist(), "amplitude": AMPLITUDE.tolist(), "multiple": MULTIPLE.tolist(),
            "phase": PHASE.tolist(), "period": PERIOD, "ramp": RAMP, "yaw": YAW}}],
    }
    _, params, _ = build(config_from_dict(raw, "test"))
    ref = params.controller.reference
    closed = jax.jit(lambda t: reference_derivatives(ref, t))
    ours = jax.jit(lambda t: ([_derivative(_position, n)(t) for n in range(5)],
                              [_derivative(_yaw, n)(t) for n in range(3)]))
    worst = 0.0
    for t in (0.05, 0.31, 0.55, 0.69, 0.9, 2.4):         # through the ramp and after it
        (pos, yaw), (pos_ref, yaw_ref) = closed(jnp.asarray(t)), ours(jnp.asarray(t))
        for n in range(5):
            scale = max(1.0, float(np.abs(pos_ref[n]).max()))
            worst = max(worst, float(np.abs(np.asarray(pos[n])[0] - np.asarray(pos_ref[n])).max()) / scale)
        for n in range(3):
            scale = max(1.0, abs(float(yaw_ref[n])))
            worst = max(worst, abs(float(np.asarray(yaw[n])[0]) - float(yaw_ref[n])) / scale)
    # measured worst error (relative to max(1, |value|)) over position, velocity, acceleration,
    # jerk, snap and yaw, yaw rate, yaw acceleration: 5.3e-14
    assert worst < 5e-13, worst
