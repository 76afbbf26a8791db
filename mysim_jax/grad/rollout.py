"""Rollouts of the capture environment for gradients: the scripted team in closed loop
with its parameters ``u`` (:mod:`.team`), or a fixed action sequence in open loop, the
objective's values along them (:mod:`.objective`), and the reverse-mode pass one policy
step at a time.

**Why one step at a time.** A policy step is hundreds of physics sub-steps; reverse mode
over a whole horizon as one program would store every sub-step's intermediates and
compile one program per horizon. Here the forward rollout keeps only the states between
policy steps, and the backward pass walks them in reverse, recomputing one step inside
its vector-Jacobian product (``jax.vjp``): the memory of a checkpoint per policy step, and
one compiled step for every horizon. The cotangent of step ``k``'s state is

    lam_k = vjp_k(lam_{k+1}) + (1 / n) grad r(s_k),   lam_n = grad e(s_n) + (1 / n) grad r(s_n)

with ``e`` the end terms and ``r`` the running terms of :mod:`.objective`; the parameter
gradient is the sum of each step's ``vjp`` with respect to ``u`` (closed loop) or that
step's action (open loop); one compiled step serves both (:func:`policy_step`). With ``truncate`` ``m``, the cotangent coming from later steps
is dropped at every ``m``-th state counted back from the horizon's end (a
``stop_gradient`` on the state there, as truncated backpropagation through time does):
gradients then cross at most ``m`` policy steps.

The state's integer and boolean leaves (step counters, flags) carry no gradient: the
passes differentiate with respect to its floating leaves only, and not to the
episode's draws (:func:`state_floats`).
Step ``k``'s environment key is ``fold_in(key, k)``, the same for every perturbation of
one episode (common random numbers).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from mysim_jax.grad.objective import end_value, running_value, tether_state
from mysim_jax.grad.team import team_actions


class Problem(NamedTuple):
    """What every rollout needs: the environment (static), its parameters (traced), the
    objective's weights, the team's parameter layout and the tether springs."""

    env: object
    params: object
    weights: object
    team: object            # TeamParameters of env.scripted
    springs: tuple          # tether spring indices


class Row(NamedTuple):
    """What a rollout records at every state it reaches ``s_1 .. s_n``."""

    end: jnp.ndarray        # () m, d_xy + w_v v_rel of the state
    running: jnp.ndarray    # () m, w_T excess + w_e effort of the state
    touching: jnp.ndarray   # () bool, the target touches a net line
    taut: jnp.ndarray       # (n_tether_segments,) bool, strain > 0


def float_leaves(tree):
    """``(floats, rebuild)``: the floating-point leaves of ``tree`` and a function that
    puts (new) floating leaves back with the other leaves unchanged."""
    leaves, treedef = jax.tree.flatten(tree)
    is_float = [jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating) for x in leaves]
    floats = [x for x, f in zip(leaves, is_float) if f]

    def rebuild(new):
        it = iter(new)
        return jax.tree.unflatten(treedef, [next(it) if f else x for x, f in zip(leaves, is_float)])

    return floats, rebuild


def state_floats(state):
    """:func:`float_leaves` of an environment state without its episode's draws (masses,
    wind, held constant over a rollout: they carry no gradient here)."""
    episode = state.episode
    floats, rebuild = float_leaves(state.replace(episode=None))
    return floats, lambda new: rebuild(new).replace(episode=episode)


def policy_step(pb: Problem, closed, u, action, state, key):
    """``(next_state, actions)``: one policy step with the scripted team's actions at its
    parameters ``u`` where ``closed`` (closed loop), else with ``action`` ``(n_agents, 3)``
    (open loop). ``closed`` is a traced bool: one compiled program serves both (the team's
    actions are computed either way; the unused input gets a zero gradient)."""
    team = team_actions(pb.env, pb.team.team(pb.env.scripted, u), state, pb.params)
    actions = jnp.where(closed, team, action)
    return pb.env.step_env(key, state, actions, pb.params)[1], actions


def record(pb: Problem, state) -> Row:
    """The :class:`Row` of one state."""
    sim_params = pb.env.episode_params(pb.params, state.episode)
    _, strain = tether_state(pb.env, sim_params, state.sim, pb.springs)
    touching = pb.env.flags(pb.env.snapshot(state.sim, sim_params)).touching
    return Row(end=end_value(pb.env, pb.weights, state, pb.params),
               running=running_value(pb.env, pb.weights, state, pb.params, pb.springs),
               touching=touching, taut=strain > 0.0)


def forward(pb: Problem, state, key, n: int, closed, u, actions, keep_states: bool = False):
    """``n`` policy steps of one environment from ``state`` (:func:`policy_step`): closed
    loop with the team's parameters ``u`` ``(n_params,)`` where ``closed``, else open loop
    with ``actions`` ``(n, n_agents, 3)``.

    Returns ``(rows, actions, states)``: the :class:`Row` of ``s_1 .. s_n`` (leading axis
    ``n``), the actions flown ``(n, n_agents, 3)``, and with ``keep_states`` the states
    ``s_1 .. s_n`` (leading axis ``n``; else None), which the backward pass walks."""
    def body(s, k):
        nxt, a = policy_step(pb, closed, u, actions[k], s, jax.random.fold_in(key, k))
        return nxt, (record(pb, nxt), a, nxt if keep_states else None)

    _, (rows, flown, states) = jax.lax.scan(body, state, jnp.arange(n))
    return rows, flown, states


def horizon_values(rows: Row, steps):
    """``J`` [m] at every horizon of ``steps`` (policy steps, each in ``1..n``): the end
    terms of ``s_h`` plus the mean running terms of ``s_1 .. s_h``; ``(len(steps),)``."""
    cumulative = jnp.cumsum(rows.running, axis=0)
    return jnp.stack([rows.end[h - 1] + cumulative[h - 1] / h for h in steps])


def seed_cotangent(pb: Problem, state, weight):
    """``lam_n``: the gradient of ``e(s_n) + weight * r(s_n)`` (``weight`` = ``1 / n``) with
    respect to the floating leaves of the horizon's last state."""
    floats, rebuild = state_floats(state)

    def value(fl):
        s = rebuild(fl)
        return end_value(pb.env, pb.weights, s, pb.params) + weight * running_value(pb.env, pb.weights, s, pb.params,
                                                                                   pb.springs)
    return jax.grad(value)(floats)


def backward_step(pb: Problem, state, closed, u, action, key, lam_next, weight, carry):
    """``(lam_k, g_u, g_action)`` of step ``k`` from ``s_k`` (module docstring): the
    cotangent of ``s_k``'s floating leaves, ``carry * vjp_k(lam_next) + weight * grad
    r(s_k)`` (``carry`` 1, or 0 where a truncation drops what comes from later steps), and
    the gradients with respect to the team's parameters ``u`` (nonzero in closed loop) and
    to the step's ``action`` (nonzero in open loop)."""
    floats, rebuild = state_floats(state)

    def step(fl, u, action):
        return state_floats(policy_step(pb, closed, u, action, rebuild(fl), key)[0])[0]

    _, vjp = jax.vjp(step, floats, u, action)
    lam, g_u, g_action = vjp(lam_next)
    local = jax.grad(lambda fl: running_value(pb.env, pb.weights, rebuild(fl), pb.params, pb.springs))(floats)
    return [carry * a + weight * b for a, b in zip(lam, local)], g_u, g_action
