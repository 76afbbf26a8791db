"""Where and when a falling target meets the net: the catch point shared by the scripted
team, the observations and the reward's potential.

A falling sphere of mass ``m`` and drag constant ``k = ½ ρ C_d π r²`` obeys

    dv/dt = g − (k / m) |v| v,         dp/dt = v

(quadratic drag in still air, as :mod:`mysim_jax.effects.target` applies it). Quadratic drag
couples the axes through ``|v|``, so there is no closed form for the time at which the
target comes down to the height ``z_catch`` of the net; :func:`predict_catch` integrates
the two equations above with ``n_steps`` fixed midpoint (RK2) steps over ``horizon``
seconds (a fixed-length ``lax.scan``: differentiable, the same work in every environment)
and interpolates the first step that crosses ``z_catch``. With ``k = 0`` it is the
ballistic parabola, whose crossing time ``t* = (v_z + √(v_z² + 2 g Δz)) / g`` the tests
compare against.

A target already at or below ``z_catch`` is caught "now": ``t = 0`` and the point is its
current position. A target that does not come down within ``horizon`` gets the position
and time at the end of the horizon (``crossed`` False).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from mysim_jax.core import vecmath

HORIZON = 3.0     # s, how far ahead the fall is integrated
N_STEPS = 30      # midpoint steps over the horizon (0.1 s each)


@struct.dataclass
class CatchPoint:
    """The predicted meeting of a falling target with the net's height."""

    point: jnp.ndarray      # (3,) m, where the target reaches z_catch (world frame)
    time: jnp.ndarray       # () s from now (0 when it is already at or below z_catch)
    velocity: jnp.ndarray   # (3,) m/s, the target's velocity there
    crossed: jnp.ndarray    # () bool, the crossing lies within the horizon


def _acceleration(v, gravity, drag_per_mass):
    return gravity - drag_per_mass * vecmath.safe_norm(v)[..., None] * v


def predict_catch(pos, vel, z_catch, gravity, drag_per_mass, horizon: float = HORIZON,
                  n_steps: int = N_STEPS) -> CatchPoint:
    """The catch point of a target at ``pos`` (3,) m moving at ``vel`` (3,) m/s coming down
    to the height ``z_catch`` () m (module docstring). ``gravity`` (3,) m/s² (world, e.g.
    ``(0, 0, −9.81)``); ``drag_per_mass`` () 1/m, ``k / m`` (0: no drag). ``horizon`` s and
    ``n_steps`` are static."""
    dt = horizon / n_steps
    dtype = pos.dtype

    def midpoint(carry, _):
        p, v = carry
        a1 = _acceleration(v, gravity, drag_per_mass)
        v_half = v + 0.5 * dt * a1
        a2 = _acceleration(v_half, gravity, drag_per_mass)
        p2 = p + dt * v_half
        v2 = v + dt * a2
        return (p2, v2), (p2, v2)

    _, (ps, vs) = jax.lax.scan(midpoint, (pos, vel), None, length=n_steps)
    ps = jnp.concatenate([pos[None], ps])              # (n + 1, 3), at t = 0, dt, ...
    vs = jnp.concatenate([vel[None], vs])
    below = ps[:, 2] <= z_catch
    crossed = jnp.any(below)
    # the first sample at or below z_catch (the last one when none is)
    i = jnp.where(crossed, jnp.argmax(below), n_steps)
    j = jnp.maximum(i - 1, 0)
    # rows i and j as masked sums, not gathers: batch-last (mysim_jax.core.batching) has a rule
    # for every primitive of the step, and gathers with traced indices are not among them
    rows = jnp.arange(n_steps + 1)
    pick = lambda x, k: jnp.sum(jnp.where((rows == k)[:, None], x, 0.0), axis=0)   # noqa: E731
    p_i, p_j, v_i, v_j = pick(ps, i), pick(ps, j), pick(vs, i), pick(vs, j)
    z0, z1 = p_j[2], p_i[2]
    # linear interpolation between samples j and i (i == j == 0: already below, s = 0)
    denom = jnp.where(jnp.abs(z0 - z1) > 1e-9, z0 - z1, 1.0)
    s = jnp.where(i > 0, jnp.clip((z0 - z_catch) / denom, 0.0, 1.0), 0.0)
    s = jnp.where(crossed, s, 1.0)
    point = p_j + s * (p_i - p_j)
    velocity = v_j + s * (v_i - v_j)
    time = (j.astype(dtype) + jnp.where(i > 0, s, 0.0)) * dt
    return CatchPoint(point=point.astype(dtype), time=time.astype(dtype), velocity=velocity.astype(dtype),
                      crossed=crossed)
