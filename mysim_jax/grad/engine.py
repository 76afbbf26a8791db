"""The compiled, batched passes of the gradient map for one environment
(:class:`GradientEngine`): the scripted episodes that place the windows, the forward
rollouts (nominal and perturbed), and the reverse-mode gradient of ``J`` at a horizon.

Every pass is :mod:`.rollout`'s per-environment function batched over episodes with the
library's :func:`mysim_jax.core.batching.vmap` (reverse-mode steps with ``jax.vmap``) and
jitted once per shape: the rollouts (closed and open loop alike) once per length and
batch size, the backward step once for every horizon and both kinds.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.core import batching
from mysim_jax.grad.objective import tether_springs
from mysim_jax.grad.rollout import Problem, backward_step, forward, seed_cotangent
from mysim_jax.grad.team import team_parameters


def take(tree, index):
    """Every leaf of ``tree`` indexed along its leading axis by ``index`` (host or device)."""
    return jax.tree.map(lambda a: a[index], tree)


def stack_start(first, rest):
    """``s_0 .. s_n`` ``(n + 1, batch, ...)`` from ``s_0`` ``(batch, ...)`` and ``s_1 .. s_n``
    ``(batch, n, ...)``."""
    return jax.tree.map(lambda a, b: jnp.concatenate([a[None], jnp.swapaxes(b, 0, 1)]), first, rest)


class GradientEngine:
    """The batched passes on one environment (module docstring)."""

    def __init__(self, env, params, weights):
        self.problem = Problem(env=env, params=params, weights=weights, team=team_parameters(env.scripted),
                               springs=tether_springs(env))
        self._cache = {}

    @property
    def env(self):
        return self.problem.env

    def _compiled(self, name, build):
        if name not in self._cache:
            self._cache[name] = jax.jit(build())
        return self._cache[name]

    def episodes(self, keys):
        """The scripted team's episodes from their keys ``(batch,)``: ``(rows, states)`` with
        ``states`` ``s_0 .. s_n`` ``(n + 1, batch, ...)`` and ``n`` the episode's steps."""
        pb, n = self.problem, self.env.max_steps

        def one(key):
            k_reset, k_run = jax.random.split(key)
            _, s0 = pb.env.reset(k_reset, pb.params)
            dtype = s0.sim.phys.body_pos.dtype
            u, actions = jnp.zeros(pb.team.size, dtype), jnp.zeros((n, *pb.env.action_shape), dtype)
            rows, _, states = forward(pb, s0, k_run, n, True, u, actions, keep_states=True)
            return rows, s0, states

        run = self._compiled(("episodes", n), lambda: batching.vmap(one))
        rows, s0, states = run(keys)
        return rows, stack_start(s0, states)

    def rollouts(self, states, keys, closed, u, actions, n: int, keep_states: bool = False):
        """Rollouts of ``n`` steps from ``states`` ``(batch, ...)``, each closed loop with
        the team's parameters ``u`` ``(batch, n_params)`` where ``closed`` ``(batch,)``, else
        open loop with ``actions`` ``(batch, n, n_agents, 3)``:
        :func:`~mysim_jax.grad.rollout.forward`'s ``(rows, actions, states)`` with a
        leading batch axis."""
        pb = self.problem
        run = self._compiled(("rollouts", n, keep_states), lambda: batching.vmap(
            lambda s, k, c, x, a: forward(pb, s, k, n, c, x, a, keep_states=keep_states)))
        return run(states, keys, jnp.asarray(closed), u, actions)

    def gradient(self, window, keys, u, actions, n: int, closed_loop: bool, truncate: int | None = None,
                 norms: list | None = None):
        """The gradient of ``J`` at the horizon of ``n`` steps for every episode of a
        window, by the backward pass of :mod:`.rollout`: with respect to the team's
        parameters ``u`` ``(batch, n_params)`` (closed loop), or to every step's
        ``actions`` ``(batch, >= n, n_agents, 3)`` (open loop; the actions the window was
        flown with). ``window``: ``s_0 .. s_n`` ``(>= n + 1, batch, ...)``; ``keys`` the
        windows' keys ``(batch,)``. Returns ``(batch, n_params)`` or ``(batch, n,
        n_agents, 3)``. ``norms``: a list that receives the norm ``(batch,)`` of the
        state's cotangent ``lam_k`` at every step, from ``lam_n`` back to ``lam_0`` (how
        fast the backward pass grows)."""
        pb = self.problem
        seed = self._compiled(("seed",), lambda: jax.vmap(lambda s, w: seed_cotangent(pb, s, w),
                                                          in_axes=(0, None)))
        back = self._compiled(("back",), lambda: jax.vmap(
            lambda s, c, x, a, k, lam, w, m: backward_step(pb, s, c, x, a, k, lam, w, m),
            in_axes=(0, None, 0, 0, 0, 0, None, None)))
        lam = seed(take(window, n), 1.0 / n)
        g_u, g_actions = None, []
        if norms is not None:
            norms.append(_norm(lam))
        for k in range(n - 1, -1, -1):
            step_keys = jax.vmap(lambda key: jax.random.fold_in(key, k))(keys)
            carry = 0.0 if (truncate and k > 0 and (n - k) % truncate == 0) else 1.0
            lam, gu, ga = back(take(window, k), closed_loop, u, actions[:, k], step_keys, lam,
                               1.0 / n if k > 0 else 0.0, carry)
            g_u = gu if g_u is None else g_u + gu
            g_actions.append(ga)
            if norms is not None:
                norms.append(_norm(lam))
        return g_u if closed_loop else jnp.stack(g_actions[::-1], axis=1)


def _norm(leaves):
    """Per episode, the norm of a list of batched arrays (leading batch axis)."""
    return np.sqrt(sum(np.sum(np.asarray(a, np.float64).reshape(a.shape[0], -1) ** 2, axis=1) for a in leaves))


def window_keys(keys, starts):
    """The keys ``(batch,)`` of windows starting at policy steps ``starts`` of the episodes
    drawn from ``keys`` (the episode's key folded with ``1 + start``). The environment
    draws only observation noise and estimation errors from them: without those, a
    window's states do not depend on its key."""
    return jax.vmap(lambda key, s: jax.random.fold_in(key, 1 + s))(keys, jnp.asarray(starts))


def to_numpy(tree):
    return jax.tree.map(np.asarray, tree)
