"""The catch-point prediction (mysim_jax/tasks/intercept.py) against independent references:
the ballistic crossing time in closed form without drag, and SciPy's adaptive RK45 with an
event at the net's height with quadratic drag (float64, tolerances 1e-10)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from mysim_jax.tasks.intercept import predict_catch

G = np.array([0.0, 0.0, -9.81])


def reference(pos, vel, z_catch, k_over_m):
    """Crossing point, time and velocity from SciPy (RK45, rtol 1e-10, an event at z_catch)."""
    def rhs(t, y):
        v = y[3:]
        return np.concatenate([v, G - k_over_m * np.linalg.norm(v) * v])

    def crossing(t, y):
        return y[2] - z_catch
    crossing.terminal, crossing.direction = True, -1
    sol = solve_ivp(rhs, (0.0, 10.0), np.concatenate([pos, vel]), events=crossing, rtol=1e-10, atol=1e-12)
    t = sol.t_events[0][0]
    y = sol.y_events[0][0]
    return y[:3], t, y[3:]


@pytest.mark.float64
@pytest.mark.parametrize("pos, vel", [
    ((0.3, -1.2, 6.5), (0.2, -0.1, 0.4)),     # thrown up a little
    ((-1.5, 1.5, 7.0), (-0.3, 0.3, 0.0)),     # the spawn range's corner
    ((0.0, 0.0, 4.0), (1.5, 0.0, -3.0)),      # already falling fast
])
def test_without_drag_the_parabola_in_closed_form(pos, vel):
    pos, vel = np.array(pos), np.array(vel)
    z_net = 2.6
    cp = predict_catch(jnp.asarray(pos), jnp.asarray(vel), z_net, jnp.asarray(G), 0.0)
    g = 9.81
    t = (vel[2] + math.sqrt(vel[2] ** 2 + 2.0 * g * (pos[2] - z_net))) / g
    # the midpoint rule integrates a constant acceleration exactly; the interpolation
    # between 0.1 s samples is linear in z, so the time carries its error (~ g dt² / 8 v_z;
    # measured 0.7-1.3 ms, and 0.2-1.0 mm horizontally)
    assert bool(cp.crossed)
    assert float(cp.time) == pytest.approx(t, abs=3e-3)
    np.testing.assert_allclose(np.asarray(cp.point[:2]), pos[:2] + vel[:2] * t, atol=3e-3)
    assert float(cp.point[2]) == pytest.approx(z_net, abs=1e-12)


@pytest.mark.float64
@pytest.mark.parametrize("mass", [0.08, 0.15])
def test_with_quadratic_drag_against_scipy(mass):
    k = 0.5 * 1.225 * 0.47 * math.pi * 0.2 ** 2           # the env target's drag constant
    pos, vel = np.array([1.2, -0.4, 6.8]), np.array([-0.3, 0.25, 0.5])
    z_net = 2.5
    point, t, v = reference(pos, vel, z_net, k / mass)
    cp = predict_catch(jnp.asarray(pos), jnp.asarray(vel), z_net, jnp.asarray(G), k / mass)
    # 0.1 s midpoint steps and linear interpolation between them: measured 1.9-2.0 ms,
    # 0.03-0.16 mm and 6-17 mm/s, against a drag effect of 0.17-0.32 s on the fall time
    assert float(cp.time) == pytest.approx(t, abs=3e-3)
    np.testing.assert_allclose(np.asarray(cp.point), point, atol=2e-3)
    np.testing.assert_allclose(np.asarray(cp.velocity), v, atol=5e-2)
    no_drag = reference(pos, vel, z_net, 0.0)[1]
    assert t - no_drag > 0.15                     # drag matters at these masses


@pytest.mark.float64
def test_below_the_net_and_out_of_the_horizon():
    at = predict_catch(jnp.asarray([0.1, 0.2, 2.0]), jnp.asarray([1.0, 0.0, 1.0]), 2.5, jnp.asarray(G), 0.0)
    assert float(at.time) == 0.0 and bool(at.crossed)
    np.testing.assert_array_equal(np.asarray(at.point), [0.1, 0.2, 2.0])
    # a target rising fast does not come down within the 3 s horizon
    up = predict_catch(jnp.asarray([0.0, 0.0, 6.0]), jnp.asarray([0.0, 0.0, 20.0]), 2.5, jnp.asarray(G), 0.0)
    assert not bool(up.crossed) and float(up.time) == pytest.approx(3.0)


@pytest.mark.float64
def test_gradients_are_finite():
    def f(pos):
        cp = predict_catch(pos, jnp.asarray([0.2, 0.0, 0.0]), 2.5, jnp.asarray(G), 0.3)
        return jnp.sum(cp.point) + cp.time
    g = jax.grad(f)(jnp.asarray([0.3, 0.1, 6.0]))
    assert np.all(np.isfinite(np.asarray(g)))
    # d(point_x)/d(pos_x) = 1: the horizontal offset carries through
    gx = jax.grad(lambda p: predict_catch(p, jnp.zeros(3), 2.5, jnp.asarray(G), 0.3).point[0])(
        jnp.asarray([0.3, 0.1, 6.0]))
    np.testing.assert_allclose(np.asarray(gx), [1.0, 0.0, 0.0], atol=1e-12)
