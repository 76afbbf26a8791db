"""A smooth capture objective on rollouts of the capture environment (lower is better).

For a horizon of ``n`` policy steps from a state ``s_0`` to ``s_n``::

    J = d_xy(s_n) + w_v * v_rel(s_n) + (1 / n) * sum_{k=1..n} [ w_T * excess(s_k) + w_e * effort(s_k) ]

* ``d_xy`` [m]: horizontal distance from the target's centre to the net's centre (the
  mean of its knots), smoothed as ``sqrt(|dx|^2 + eps^2) - eps`` (``eps`` = ``smooth_length``);
* ``v_rel`` [m/s]: the target's speed relative to the net's centre (the knots' mean
  velocity), smoothed alike with ``smooth_speed``; ``w_v`` [s] turns it into metres;
* ``excess`` [N]: summed over every tether segment, the tension above ``tension_limit``,
  smoothed as ``softplus(beta (T - T_max)) / beta`` (``beta`` = ``1 / tension_softness``);
  ``w_T`` [m/N];
* ``effort`` [1]: the mean over every rotor of ``(omega / omega_max)^2`` (the rotor
  speed's share of its maximum, squared; about thrust per maximum thrust); ``w_e`` [m].

* ``d_z`` [m] (optional, weight ``w_z`` = ``vertical``, 0 by default): the target's height
  above or below the net's centre at the horizon's end, smoothed like ``d_xy``, added to
  the end terms when ``w_z`` is not zero: a team that shadows the target far below it, or
  lets it fall past the net to the ground, pays the height between them;
* ``low`` [m] (optional, weight ``w_g`` = ``ground``, 0 by default): how far the target's
  centre is under ``ground_clearance`` at the horizon's end (a softplus over
  ``smooth_length``): a target on the ground fails the capture verdict wherever the net is.

So ``J`` is in metres. The two penalties are means over the horizon's steps, so a
horizon's length does not scale them. Everything here is for one environment and pure.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.dynamics.forces import spring_tension
from mysim_jax.dynamics.markers import node_states


@dataclass(frozen=True)
class ObjectiveWeights:
    """The objective's weights and smoothing constants (module docstring; hashable)."""

    speed: float = 0.2               # w_v, s: 1 m/s of relative speed costs 0.2 m
    tension: float = 0.05            # w_T, m/N per newton of tension above the limit
    effort: float = 0.2              # w_e, m per unit of mean squared rotor-speed fraction
    tension_limit: float = 2.0       # T_max, N, per tether segment
    tension_softness: float = 0.2    # N, 1 / beta of the softplus
    smooth_length: float = 0.01      # m, eps of the smoothed horizontal distance
    smooth_speed: float = 0.01       # m/s, eps of the smoothed relative speed
    vertical: float = 0.0            # w_z, m per m of the target's height off the net's centre (0: no term)
    ground: float = 0.0              # w_g, m per m of the target's centre under ground_clearance (0: no term)
    ground_clearance: float = 0.5    # m, the height above the ground (z = 0) the target should stay over

    def __post_init__(self):
        for name in ("speed", "tension", "effort", "tension_limit", "vertical", "ground", "ground_clearance"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"objective weight {name}: {getattr(self, name)!r}, expected >= 0")
        for name in ("tension_softness", "smooth_length", "smooth_speed"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"objective {name}: {getattr(self, name)!r}, expected > 0")


def tether_springs(env) -> tuple[int, ...]:
    """Spring indices of every tether segment of the environment's net (names ``P_t{n}[k]``
    with ``P`` the net's name, read from its first knot ``P_k0_0``)."""
    knot = env.scene.point_names[env.knot_points[0]]
    net = knot.rsplit("_k", 1)[0]
    pattern = re.compile(rf"{re.escape(net)}_t\d+\[\d+\]")
    found = tuple(i for i, n in enumerate(env.scene.spring_names) if pattern.fullmatch(n))
    if not found:
        raise ValueError(f"scene '{env.scene_name}': no tether springs named {net}_t<n>[<k>]")
    return found


def tether_state(env, sim_params, sim, springs):
    """``(tension, strain)`` ``(n_segments,)`` of the tether segments ``springs``: tension
    [N] by the scene's spring law (tension-only), strain [1] = length / rest length - 1
    (positive: taut)."""
    idx = np.asarray(springs, dtype=np.int32)
    a = np.asarray(env.scene.spring_node_a, dtype=np.int32)[idx]
    b = np.asarray(env.scene.spring_node_b, dtype=np.int32)[idx]
    pos, vel = node_states(env.scene, sim_params, sim.phys)
    dx = pos[b] - pos[a]
    length = jnp.sqrt(jnp.sum(dx * dx, axis=-1) + 1e-12)
    rate = jnp.sum((vel[b] - vel[a]) * dx, axis=-1) / length
    rest = sim_params.spring_rest_length[idx]
    tension = spring_tension(sim_params.spring_stiffness[idx], sim_params.spring_damping[idx], rest, length, rate,
                             tuple(env.scene.spring_tension_only[i] for i in springs))
    return tension, length / rest - 1.0


def _smooth_norm(x, eps):
    return jnp.sqrt(jnp.sum(x * x) + eps * eps) - eps


def end_terms(env, weights: ObjectiveWeights, state, params) -> dict:
    """The end-of-horizon terms of one state, unweighted: ``distance`` [m],
    ``relative_speed`` [m/s], ``height`` [m] (the target's centre above or below the
    net's centre, smoothed like ``distance``) and ``low`` [m] (how far the target's centre
    is under ``ground_clearance``, smoothed as a softplus over ``smooth_length``)."""
    phys = state.sim.phys
    knots = np.asarray(env.knot_points, dtype=np.int32)
    centre = jnp.mean(phys.point_pos[knots], axis=0)
    v_net = jnp.mean(phys.point_vel[knots], axis=0)
    p, v = phys.body_pos[env.target_body], phys.body_vel[env.target_body]
    return {"distance": _smooth_norm(p[:2] - centre[:2], weights.smooth_length),
            "relative_speed": _smooth_norm(v - v_net, weights.smooth_speed),
            "height": _smooth_norm(p[2:] - centre[2:], weights.smooth_length),
            "low": jax.nn.softplus((weights.ground_clearance - p[2]) / weights.smooth_length) * weights.smooth_length}


def running_terms(env, weights: ObjectiveWeights, state, params, springs) -> dict:
    """The per-step terms of one state, unweighted: ``tension_excess`` [N] (summed over the
    tether segments) and ``effort`` [1]."""
    sim_params = env.episode_params(params, state.episode)
    tension, _ = tether_state(env, sim_params, state.sim, springs)
    beta = 1.0 / weights.tension_softness
    excess = jnp.sum(jax.nn.softplus(beta * (tension - weights.tension_limit)) / beta)
    fraction = state.sim.controller.motor_speed / sim_params.quadrotor.omega_max[:, None]
    return {"tension_excess": excess, "effort": jnp.mean(fraction * fraction)}


def end_value(env, weights: ObjectiveWeights, state, params):
    """``d_xy + w_v v_rel (+ w_z d_z + w_g low)`` [m] of the horizon's last state; the
    optional terms only when their weights are not zero (so the objective without them is
    unchanged)."""
    t = end_terms(env, weights, state, params)
    value = t["distance"] + weights.speed * t["relative_speed"]
    if weights.vertical:
        value = value + weights.vertical * t["height"]
    return value + weights.ground * t["low"] if weights.ground else value


def running_value(env, weights: ObjectiveWeights, state, params, springs):
    """``w_T excess + w_e effort`` [m] of one step's state (averaged over the horizon in J)."""
    t = running_terms(env, weights, state, params, springs)
    return weights.tension * t["tension_excess"] + weights.effort * t["effort"]
