"""Rope module (paper Sec. 2.1), spring force law, loads at markers, gradients, vmap."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict, load_config
from mysim_jax.dynamics.quaternion import quat_rotate_inv
from mysim_jax.net.rope import build_rope, rope_rest_lengths
from mysim_jax.sim import accelerations, rollout

from conftest import CONFIGS

G = 9.81


def test_rope_discretisation_matches_paper():
    rest = rope_rest_lengths(1.0, 5)
    np.testing.assert_allclose(rest, [0.1, 0.2, 0.2, 0.2, 0.2, 0.1])
    assert rest.sum() == pytest.approx(1.0)
    seg = build_rope(2.0, 4, 0.3, 1e5, 50.0, [0, 0, 0], [2.0, 0, 0])
    np.testing.assert_allclose(seg.stiffness, 1e5 / seg.rest_length)
    np.testing.assert_allclose(seg.damping, 50.0 / seg.rest_length)
    np.testing.assert_allclose(seg.point_pos[:, 0], [0.25, 0.75, 1.25, 1.75])
    # ends closer than L: uniform strain, masses still evenly spread by rest length
    seg = build_rope(2.0, 4, 0.3, 1e5, 50.0, [0, 0, 0], [1.0, 0, 0])
    np.testing.assert_allclose(seg.point_pos[:, 0], [0.125, 0.375, 0.625, 0.875])


def test_rope_net_topology():
    scene, params, state = build(load_config(CONFIGS / "rope_net.yaml", ["sim.precision=float32"]))
    assert scene.n_points == 21 and scene.n_springs == 24 and scene.n_anchors == 4
    # every rope's rest lengths sum to L and every rope starts unstretched
    rest = np.asarray(params.spring_rest_length).reshape(4, 6)
    np.testing.assert_allclose(rest.sum(axis=1), 1.0, rtol=1e-6)
    pos = np.concatenate([np.asarray(state.phys.point_pos), np.asarray(params.anchor_pos)])
    lengths = np.linalg.norm(pos[list(scene.spring_node_b)] - pos[list(scene.spring_node_a)], axis=1)
    np.testing.assert_allclose(lengths, np.asarray(params.spring_rest_length), rtol=1e-6)


def _two_point_scene(model, start_gap, **spring):
    return {
        "name": "spring_test",
        "sim": {"t_end": 0.01, "dt": 1e-4, "output_dt": 1e-4, "precision": "float64"},
        "points": [{"name": "p", "mass": 0.5, "pos": [start_gap, 0.0, 0.0]}],
        "anchors": [{"name": "wall", "pos": [0.0, 0.0, 0.0]}],
        "springs": [{"name": "s", "start": "wall", "end": "p", "stiffness": 100.0, "damping": 2.0,
                     "rest_length": 1.0, "model": model, **spring}],
    }


@pytest.mark.float64
@pytest.mark.parametrize("model", ["tension_only", "linear"])
def test_tension_only_rope_does_not_push(model):
    # compressed (0.5 m < 1 m rest): a rope is slack, a linear spring pushes 50 N
    scene, params, state = build(config_from_dict(_two_point_scene(model, 0.5), "t"))
    acc = accelerations(scene, params, state.phys).point_acc[0]
    expected_x = 0.0 if model == "tension_only" else 100.0 * 0.5 / 0.5
    np.testing.assert_allclose(acc, [expected_x, 0, -G], atol=1e-12)
    # stretched (1.2 m): both pull back with k (s - s̄) = 20 N
    scene, params, state = build(config_from_dict(_two_point_scene(model, 1.2), "t"))
    acc = accelerations(scene, params, state.phys).point_acc[0]
    np.testing.assert_allclose(acc, [-40.0, 0, -G], atol=1e-12)


@pytest.mark.float64
def test_tension_only_damping_cannot_push_a_taut_rope():
    # taut but closing fast: k(s - s̄) + c ṡ = 100*0.01 + 2*(-5) < 0 -> rope force is 0, not a push
    raw = _two_point_scene("tension_only", 1.01)
    raw["points"][0]["vel"] = [-5.0, 0.0, 0.0]
    scene, params, state = build(config_from_dict(raw, "t"))
    np.testing.assert_allclose(accelerations(scene, params, state.phys).point_acc[0], [0, 0, -G], atol=1e-12)


@pytest.mark.float64
def test_zero_length_segment_is_finite_in_value_and_gradient():
    scene, params, state = build(config_from_dict(_two_point_scene("linear", 0.0), "t"))

    def f(pos):
        phys = state.phys.replace(point_pos=pos)
        return jnp.sum(accelerations(scene, params, phys).point_acc ** 2)

    assert np.isfinite(f(state.phys.point_pos))
    assert np.all(np.isfinite(jax.grad(f)(state.phys.point_pos)))


@pytest.mark.float64
def test_hanging_rope_settles_to_the_analytic_static_stretch():
    """Vertical rope (N masses m) from a ceiling anchor holding a payload M: segment j from
    the top carries the weight below it, T_j = g (M + m (N − j)), and stretches T_j s̄_j / EA."""
    n, m, big_m, ea, length = 6, 0.05, 0.4, 2e3, 1.2
    raw = {
        "name": "hanging",
        "sim": {"t_end": 4.0, "dt": 1e-4, "output_dt": 1e-2, "integrator": "semi_implicit_euler",
                "precision": "float64"},
        "points": [{"name": "payload", "mass": big_m, "pos": [0.0, 0.0, -length]}],
        "anchors": [{"name": "ceiling", "pos": [0.0, 0.0, 0.0]}],
        "ropes": [{"name": "r", "start": "ceiling", "end": "payload", "length": length, "n_masses": n,
                   "mass": m, "EA": ea, "damping": 20.0}],
    }
    scene, params, state = build(config_from_dict(raw, "t"))
    final, _ = jax.jit(lambda p, s: rollout(scene, p, s, 40000, 40000))(params, state)
    rest = rope_rest_lengths(length, n)
    tension = G * (big_m + m * (n - np.arange(n + 1)))
    expected = -(length + np.sum(tension * rest / ea))
    assert abs(float(final.phys.point_pos[0, 2]) - expected) < 1e-6
    assert np.abs(np.asarray(final.phys.point_vel)).max() < 1e-5


@pytest.mark.float64
def test_force_at_marker_gives_force_and_torque():
    raw = {
        "name": "lever",
        "sim": {"t_end": 0.01, "dt": 1e-3, "output_dt": 1e-3, "precision": "float64"},
        "gravity": [0, 0, 0],
        "bodies": [{"name": "b", "mass": 2.0, "inertia": [0.1, 0.2, 0.25],
                    "quat": [np.cos(0.3), 0.0, np.sin(0.3), 0.0],
                    "markers": [{"name": "tip", "pos": [0.5, 0.2, -0.1]}]}],
        "loads": [{"at": "b.tip", "force": [1.0, -2.0, 3.0]}, {"at": "b", "torque": [0.0, 0.0, 0.4]}],
    }
    scene, params, state = build(config_from_dict(raw, "t"))
    acc = accelerations(scene, params, state.phys)
    f = jnp.array([1.0, -2.0, 3.0])
    np.testing.assert_allclose(acc.body_acc[0], f / 2.0, atol=1e-14)
    torque_body = jnp.cross(jnp.array([0.5, 0.2, -0.1]), quat_rotate_inv(state.phys.body_quat[0], f)) + jnp.array([0, 0, 0.4])
    np.testing.assert_allclose(acc.body_angacc[0], torque_body / jnp.array([0.1, 0.2, 0.25]), atol=1e-13)


def _payload_z_after(scale, n_steps=1000):
    scene, params, state = build(load_config(CONFIGS / "rope_net.yaml", ["sim.integrator=semi_implicit_euler"]))
    params = params.replace(spring_stiffness=params.spring_stiffness * scale)
    final, _ = rollout(scene, params, state, n_steps, n_steps)
    return final.phys.point_pos[0, 2]


@pytest.mark.float64
def test_gradient_through_rope_net_matches_finite_differences():
    f = jax.jit(_payload_z_after)
    grad = jax.jit(jax.grad(_payload_z_after))(1.0)
    eps = 1e-5
    fd = (f(1.0 + eps) - f(1.0 - eps)) / (2 * eps)
    assert np.isfinite(grad) and abs(grad) > 1e-4
    assert abs(grad - fd) < 1e-6 * max(1.0, abs(fd)), (grad, fd)


@pytest.mark.float64
def test_vmap_over_params_matches_single_runs():
    scales = jnp.array([0.5, 1.0, 2.0])
    batched = jax.jit(jax.vmap(lambda s: _payload_z_after(s, 1000)))(scales)
    single = [jax.jit(lambda s: _payload_z_after(s, 1000))(s) for s in scales]
    np.testing.assert_allclose(batched, single, rtol=1e-12, atol=1e-15)
    assert np.min(np.abs(np.diff(np.asarray(batched)))) > 1e-5   # the samples really differ


def test_simulate_steps_a_short_run_in_one_chunk_of_the_next_power_of_two(monkeypatch):
    """simulate() runs a fixed-step scene in compiled chunks of ``chunk`` outputs; a run of
    fewer outputs steps one chunk of the next power of two (not a whole chunk), a longer
    one whole chunks, and both save the same states on the grid they share."""
    from mysim_jax import driver

    config = load_config(CONFIGS / "rope_net.yaml", ["sim.precision=float32", "sim.t_end=0.05",
                                                     "sim.output_dt=0.01"])
    scene, params, state = build(config)
    calls, advance = [], driver._advance

    def counted(scene, params, state, n_steps, every, policy=None):
        calls.append(n_steps // every)
        return advance(scene, params, state, n_steps, every, policy)

    monkeypatch.setattr(driver, "_advance", counted)
    short = driver.simulate(scene, params, state, config.run_settings(), progress=False)       # 5 outputs
    assert calls == [8] and len(short.time) == 6 and short.time[-1] == pytest.approx(0.05)
    calls.clear()
    long = driver.simulate(scene, params, state, config.run_settings(), progress=False, chunk=2)
    assert calls == [2, 2, 2] and len(long.time) == 6
    np.testing.assert_allclose(long.phys.point_pos, short.phys.point_pos, rtol=0, atol=1e-6)
