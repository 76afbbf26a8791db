"""Reference trajectories ``r_d(t)``, ``ψ_d(t)`` for the quadrotors (paper Sec. 2.2: by
differential flatness, position and yaw are the four outputs a quadrotor can track).

A Lissajous reference per quadrotor (config: :class:`mysim_jax.config.quadrotor.ReferenceConfig`)::

    r_d(t) = center + amplitude ⊙ sin(multiple ⊙ φ(t) + phase),   φ(t) = 2π s(t) / period
    ψ_d(t) = yaw_center + yaw_amplitude sin(yaw_multiple φ(t) + yaw_phase)

with the time warp ``s(t)``: ``ṡ`` rises from 0 to 1 over ``ramp`` seconds by the quintic
smooth step ``6x⁵ − 15x⁴ + 10x³`` (``x = t/ramp``), so the reference starts from rest
with continuous velocity and acceleration; ``s(t) = t − ramp/2`` afterwards. The time
derivatives (up to the snap, which the flatness feed-forward needs) are written out in
closed form: cheaper to compile than nested autodiff, and checked against it in the tests.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct


@struct.dataclass
class ReferenceParams:
    """Traced parameters of every quadrotor's reference."""

    center: jnp.ndarray         # (n_quads, 3) m
    amplitude: jnp.ndarray      # (n_quads, 3) m
    multiple: jnp.ndarray       # (n_quads, 3)
    phase: jnp.ndarray          # (n_quads, 3) rad
    period: jnp.ndarray         # (n_quads,) s
    ramp: jnp.ndarray           # (n_quads,) s
    yaw_center: jnp.ndarray     # (n_quads,) rad
    yaw_amplitude: jnp.ndarray  # (n_quads,) rad
    yaw_multiple: jnp.ndarray   # (n_quads,)
    yaw_phase: jnp.ndarray      # (n_quads,) rad


@struct.dataclass
class Reference:
    """The reference of every quadrotor at one time."""

    pos: jnp.ndarray       # (n_quads, 3) m
    vel: jnp.ndarray       # (n_quads, 3) m/s
    acc: jnp.ndarray       # (n_quads, 3) m/s^2
    yaw: jnp.ndarray       # (n_quads,) rad
    yaw_rate: jnp.ndarray  # (n_quads,) rad/s


def time_warp(t, ramp, order: int = 0):
    """``[s, ṡ, …, s⁽ᵒʳᵈᵉʳ⁾]`` at ``t`` (see module docstring); ``ramp = 0`` gives ``s = t``."""
    ramp_safe = jnp.where(ramp > 0.0, ramp, 1.0)
    x = jnp.clip(t / ramp_safe, 0.0, 1.0)
    ramping = t < ramp
    poly = [
        ramp_safe * x ** 4 * (x * x - 3.0 * x + 2.5),
        x ** 3 * (6.0 * x * x - 15.0 * x + 10.0),
        30.0 * x * x * (x - 1.0) ** 2 / ramp_safe,
        60.0 * x * (2.0 * x * x - 3.0 * x + 1.0) / ramp_safe ** 2,
        60.0 * (6.0 * x * x - 6.0 * x + 1.0) / ramp_safe ** 3,
    ]
    after = [t - 0.5 * ramp, jnp.ones_like(x)] + [jnp.zeros_like(x)] * 3
    return [jnp.where(ramping, poly[k], after[k]) for k in range(order + 1)]


def _sine_derivatives(theta):
    """``dⁿ/dtⁿ sin θ(t)``, n = 0..4, from ``θ, θ̇, …, θ⁽⁴⁾`` (Faà di Bruno, written out)."""
    th, t1, t2, t3, t4 = theta
    s, c = jnp.sin(th), jnp.cos(th)
    return [
        s,
        c * t1,
        -s * t1 * t1 + c * t2,
        -c * t1 ** 3 - 3.0 * s * t1 * t2 + c * t3,
        s * t1 ** 4 - 6.0 * c * t1 * t1 * t2 - 3.0 * s * t2 * t2 - 4.0 * s * t1 * t3 + c * t4,
    ]


def reference_derivatives(ref: ReferenceParams, t):
    """Closed-form time derivatives at ``t``: ``([r_d, ṙ_d, r̈_d, r⃛_d, r⁗_d], [ψ_d, ψ̇_d, ψ̈_d])``,
    positions ``(n_quads, 3)``, yaws ``(n_quads,)``. (Tests check them against autodiff.)"""
    t = jnp.asarray(t, dtype=ref.center.dtype)
    warp = time_warp(t, ref.ramp, 4)
    phi = [2.0 * jnp.pi * w / ref.period for w in warp]                    # (n_quads,) each
    theta = [ref.multiple * p[:, None] for p in phi]
    theta[0] = theta[0] + ref.phase
    sines = _sine_derivatives(theta)
    pos = [ref.center + ref.amplitude * sines[0]] + [ref.amplitude * d for d in sines[1:]]
    yaw_theta = [ref.yaw_multiple * p for p in phi]
    yaw_theta[0] = yaw_theta[0] + ref.yaw_phase
    yaw_sines = _sine_derivatives(yaw_theta)
    yaw = [ref.yaw_center + ref.yaw_amplitude * yaw_sines[0]] + [ref.yaw_amplitude * d for d in yaw_sines[1:3]]
    return pos, yaw


def reference_pose(ref: ReferenceParams, t):
    """Position ``(n_quads, 3)`` and yaw ``(n_quads,)`` at time ``t`` (a scalar)."""
    phi = 2.0 * jnp.pi * time_warp(t, ref.ramp)[0] / ref.period
    pos = ref.center + ref.amplitude * jnp.sin(ref.multiple * phi[:, None] + ref.phase)
    yaw = ref.yaw_center + ref.yaw_amplitude * jnp.sin(ref.yaw_multiple * phi + ref.yaw_phase)
    return pos, yaw


def reference(ref: ReferenceParams, t) -> Reference:
    """Position, velocity, acceleration, yaw and yaw rate at time ``t`` (a scalar)."""
    pos, yaw = reference_derivatives(ref, t)
    return Reference(pos=pos[0], vel=pos[1], acc=pos[2], yaw=yaw[0], yaw_rate=yaw[1])
