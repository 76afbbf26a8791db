"""``sim.smooth_backward``: the tension-only line law exact in the forward pass, smoothed
in the backward pass only (mysim_jax/dynamics/forces.py; its effect on the capture's
gradients is measured in docs/gradients.md)."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import load_config
from mysim_jax.core.config_base import ConfigError
from mysim_jax.dynamics.forces import spring_tension
from mysim_jax.sim import step

SLACK_SCENE = Path(__file__).resolve().parents[1] / "configs" / "rope_net_slack.yaml"
WIDTHS = (0.5, 0.005)


def _springs(n=64, seed=0):
    rng = np.random.default_rng(seed)
    k = jnp.asarray(rng.uniform(10.0, 100.0, n), jnp.float32)
    c = jnp.asarray(rng.uniform(0.0, 0.1, n), jnp.float32)
    r = jnp.asarray(rng.uniform(0.2, 0.4, n), jnp.float32)
    length = r + jnp.asarray(rng.uniform(-0.02, 0.02, n), jnp.float32)     # slack and taut ones
    rate = jnp.asarray(rng.uniform(-1.0, 1.0, n), jnp.float32)
    return k, c, r, length, rate


def test_the_forward_pass_is_the_exact_law_and_the_backward_pass_the_smoothed_one():
    """Values equal the exact tension-only law bit for bit; the gradient with respect to
    length and rate is the smoothed law's ``w_T softplus(T_lin / w_T) sigmoid((l - l0) /
    w_l)``; without the option it is the exact law's (zero where slack)."""
    k, c, r, length, rate = _springs()
    mask = (True,) * length.shape[0]
    exact = spring_tension(k, c, r, length, rate, mask)
    smoothed = spring_tension(k, c, r, length, rate, mask, WIDTHS)
    np.testing.assert_array_equal(np.asarray(exact), np.asarray(smoothed))
    assert np.any(np.asarray(exact) == 0.0) and np.any(np.asarray(exact) > 0.0)

    def surrogate(l, v):
        linear = k * (l - r) + c * v
        return jnp.sum(WIDTHS[0] * jax.nn.softplus(linear / WIDTHS[0]) * jax.nn.sigmoid((l - r) / WIDTHS[1]))

    g_smooth = jax.grad(lambda l, v: jnp.sum(spring_tension(k, c, r, l, v, mask, WIDTHS)), argnums=(0, 1))(length, rate)
    g_want = jax.grad(surrogate, argnums=(0, 1))(length, rate)
    for got, want in zip(g_smooth, g_want):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-6, atol=1e-6)
    g_exact = jax.grad(lambda l: jnp.sum(spring_tension(k, c, r, l, rate, mask)))(length)
    slack = np.asarray(exact) == 0.0
    assert np.all(np.asarray(g_exact)[slack] == 0.0) and np.all(np.asarray(g_smooth[0])[slack] > 0.0)


def test_a_scene_steps_the_same_and_its_gradient_is_the_smoothed_one():
    """The slack rope-net scene (in float32, its rope masses' start positions stretched
    by 1.3 so that rope segments are taut): one step with ``sim.smooth_backward`` gives
    the same state bit for bit as without it, and the gradient of a weighted sum of the
    masses' x velocities after the step with respect to their start x positions differs
    (the option acts in reverse mode only)."""
    f32 = ["sim.precision=float32", "sim.integrator=semi_implicit_euler", "sim.rtol=1e-5", "sim.atol=1e-5"]
    plain = build(load_config(SLACK_SCENE, f32))
    smooth = build(load_config(SLACK_SCENE, f32 + ["sim.smooth_backward={tension: 0.5, slack: 0.005}"]))
    assert plain[0].smooth_backward is None and smooth[0].smooth_backward == WIDTHS

    def speed(scene, params, state, dz):
        pos = 1.3 * state.phys.point_pos                # the ropes stretched: some segments taut
        s = state.replace(phys=state.phys.replace(point_pos=pos.at[:, 0].add(dz)))
        v = step(scene, params, s).phys.point_vel[:, 0]
        return jnp.sum(v * jnp.arange(1, v.shape[0] + 1, dtype=v.dtype))     # weighted: the forces' sum is zero

    outs, grads = [], []
    for scene, params, state in (plain, smooth):
        dz = jnp.zeros(state.phys.point_pos.shape[0], state.phys.point_pos.dtype)
        f = jax.jit(jax.value_and_grad(lambda d: speed(scene, params, state, d)))
        value, g = f(dz)
        outs.append(float(value))
        grads.append(np.asarray(g))
    assert outs[0] == outs[1]
    assert np.all(np.isfinite(grads[1])) and not np.allclose(grads[0], grads[1])


def test_it_is_refused_with_the_implicit_integrator_and_needs_positive_widths():
    with pytest.raises(ConfigError, match="implicit_euler"):
        load_config(SLACK_SCENE, ["sim.integrator=implicit_euler", "sim.smooth_backward={tension: 0.5, slack: 0.005}"])
    with pytest.raises(ConfigError, match="slack"):
        load_config(SLACK_SCENE, ["sim.smooth_backward={tension: 0.5, slack: 0.0}"])
