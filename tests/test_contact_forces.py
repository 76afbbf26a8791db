"""The contact_forces stage: against an independent NumPy implementation, Newton's third
law, rigid-body friction (rolling, angular momentum), dissipative bounces, coincident
centres. All float64."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict, load_config
from mysim_jax.contact.forces import contact_forces
from mysim_jax.dynamics.markers import node_states
from mysim_jax.dynamics.quaternion import quat_rotate
from mysim_jax.sim import accelerations, solve_adaptive

from conftest import CONFIGS
from contact_reference import CollisionNetReference

pytestmark = pytest.mark.float64


def _scene(points=(), bodies=(), groups=(), pairs=(), gravity=(0.0, 0.0, 0.0), **contact):
    law = dict(stiffness=1e8, damping=1e4, damping_depth=1e-4)
    law.update(contact)
    raw = {
        "name": "contact_test",
        "sim": {"t_end": 0.01, "dt": 1e-4, "output_dt": 1e-4, "precision": "float64", "integrator": "tsit5",
                "rtol": 1e-10, "atol": 1e-13},
        "gravity": list(gravity),
        "points": list(points),
        "bodies": list(bodies),
        "contact": {**law, "groups": list(groups), "pairs": [list(p) for p in pairs]},
    }
    return build(config_from_dict(raw, "contact_test"))


def test_collision_scene_forces_match_the_independent_reference():
    """Library accelerations == NumPy reference (tests/contact_reference.py) at states where
    the ball overlaps the payload and rope masses, with friction and random velocities."""
    cfg = load_config(CONFIGS / "collision_light.yaml")
    scene, params, state = build(cfg)
    ref = CollisionNetReference(cfg)               # friction on, as configured
    rng = np.random.default_rng(3)
    acc = jax.jit(lambda phys: accelerations(scene, params, phys).point_acc)
    x0 = np.asarray(state.phys.point_pos)
    checked = 0
    for target in ("payload", "r0_0", "r2_1"):
        for _ in range(4):
            x = x0 + rng.normal(scale=1e-3, size=x0.shape)
            j = scene.point_names.index(target)
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            x[1] = x[j] + (0.06 - rng.uniform(1e-6, 3e-4)) * direction      # overlapping
            v = rng.normal(scale=0.5, size=x0.shape)
            v[1] = v[j] + rng.normal(scale=0.02, size=3)                     # slow slip: static branch too
            ours = np.asarray(acc(state.phys.replace(point_pos=jnp.asarray(x), point_vel=jnp.asarray(v))))
            np.testing.assert_allclose(ours, ref.accelerations(x, v), rtol=1e-9, atol=1e-6)
            assert np.abs(ref.contact_forces(x, v)).max() > 1.0               # the contact is active
            checked += 1
    assert checked == 12


def test_pair_force_is_equal_and_opposite_along_the_line_of_centres():
    r = 0.03
    scene, params, state = _scene(
        points=[{"name": "a", "mass": 0.2, "pos": [0, 0, 0], "vel": [0.1, 0, 0]},
                {"name": "b", "mass": 0.5, "pos": [0.03, 0.04, 0.0], "vel": [0, -0.2, 0.05]}],
        groups=[{"name": "s", "members": ["a", "b"], "radius": r}], pairs=[("s", "s")],
    )
    loads = jax.jit(lambda phys: contact_forces(scene, params, phys, node_states(scene, params, phys)))(state.phys)
    fa, fb = np.asarray(loads.node_force[0]), np.asarray(loads.node_force[1])
    np.testing.assert_allclose(fa, -fb, rtol=1e-14)
    n = np.array([0.03, 0.04, 0.0]) / 0.05
    depth, rate = 2 * r - 0.05, -np.dot([-0.1, -0.2, 0.05], n)
    s = depth / 1e-4
    expected = 1e8 * depth + 1e4 * min(s, 1.0) ** 2 * (3 - 2 * min(s, 1.0)) * rate
    np.testing.assert_allclose(fb, expected * n, rtol=1e-12)           # frictionless: pure normal


def test_coincident_centres_push_apart_along_world_z_with_finite_gradients():
    scene, params, state = _scene(
        points=[{"name": "a", "mass": 0.2}, {"name": "b", "mass": 0.2}],
        groups=[{"name": "s", "members": ["a", "b"], "radius": 0.03}], pairs=[("s", "s")],
        friction={"mu_static": 0.04, "mu_dynamic": 0.03, "v_static": 0.01, "v_dynamic": 0.1},
    )
    f = jax.jit(lambda phys: contact_forces(scene, params, phys).node_force)(state.phys)
    np.testing.assert_allclose(np.asarray(f[1]), [0.0, 0.0, 1e8 * 0.06], rtol=1e-12)

    def loss(params, phys):
        return jnp.sum(contact_forces(scene, params, phys).node_force ** 2)
    grads = jax.jit(jax.grad(loss, argnums=(0, 1)))(params, state.phys)
    assert all(np.all(np.isfinite(np.asarray(g))) for g in jax.tree.leaves(grads))


def _run_adaptive(scene, params, phys, t1):
    return jax.jit(lambda p, y: solve_adaptive(scene, p, y, 0.0, t1))(params, phys)


def test_sliding_sphere_ends_up_rolling_at_five_sevenths():
    """A solid sphere launched sliding (no spin) on the ground: friction at the contact
    point slows it and spins it up until it rolls, at v = 5/7 v0 and ω = v/r (analytic;
    angular momentum about the contact line is conserved). Exercises the friction torque
    and the body angular velocity in the slip."""
    m, r, v0, k = 1.0, 0.05, 1.0, 1e6
    rest = r - m * 9.81 / k
    scene, params, state = _scene(
        bodies=[{"name": "ball", "mass": m, "inertia": [0.4 * m * r * r] * 3, "pos": [0, 0, rest],
                 "vel": [v0, 0, 0]}],
        groups=[{"name": "ball", "members": ["ball"], "radius": r}], pairs=[("ball", "ground")],
        gravity=(0, 0, -9.81), stiffness=k, damping=2e3,
        friction={"mu_static": 0.3, "mu_dynamic": 0.25, "v_static": 0.01, "v_dynamic": 0.1},
    )
    end = _run_adaptive(scene, params, state.phys, 0.4)      # rolling from ~0.12 s on
    v = float(end.body_vel[0, 0])
    omega_world = np.asarray(quat_rotate(end.body_quat[0], end.body_angvel[0]))
    assert v == pytest.approx(5.0 / 7.0 * v0, rel=1e-3)
    assert omega_world[1] == pytest.approx(v / r, rel=1e-3)
    assert abs(float(end.body_pos[0, 2]) - rest) < 1e-6           # still on the ground, not bouncing


def test_spinning_spheres_conserve_momentum_and_angular_momentum():
    """Oblique collision of two spinning rigid spheres with friction, no gravity: the
    contact force acts on both at the same point, so total linear and angular momentum
    are conserved while the spins change."""
    m, r, inertia = 1.0, 0.05, 0.001
    scene, params, state = _scene(
        bodies=[{"name": "a", "mass": m, "inertia": [inertia] * 3, "angvel": [0.0, 0.0, 20.0]},
                {"name": "b", "mass": 2 * m, "inertia": [2 * inertia] * 3, "pos": [-0.3, 0.04, 0.01],
                 "vel": [2.0, 0.0, 0.0], "angvel": [5.0, -3.0, 10.0]}],
        groups=[{"name": "s", "members": ["a", "b"], "radius": r}], pairs=[("s", "s")],
        stiffness=1e6, damping=100.0,
        friction={"mu_static": 0.3, "mu_dynamic": 0.25, "v_static": 0.01, "v_dynamic": 0.1},
    )

    def momenta(phys):
        p = np.asarray(params.body_mass)[:, None] * np.asarray(phys.body_vel)
        spin = np.asarray(quat_rotate(phys.body_quat, jnp.einsum("nij,nj->ni", params.body_inertia, phys.body_angvel)))
        return p.sum(0), (np.cross(np.asarray(phys.body_pos), p) + spin).sum(0)

    p0, l0 = momenta(state.phys)
    end = _run_adaptive(scene, params, state.phys, 0.25)
    p1, l1 = momenta(end)
    np.testing.assert_allclose(p1, p0, atol=1e-8)
    np.testing.assert_allclose(l1, l0, atol=1e-8)
    # the spheres did collide, and friction changed the spins
    assert float(end.body_vel[0, 0]) > 0.1
    assert np.abs(np.asarray(end.body_angvel) - np.asarray(state.phys.body_angvel)).max() > 0.1


@pytest.mark.parametrize("model", ["sharp", "smooth"])
def test_a_bounce_never_leaves_with_more_energy_than_it_came_in_with(model):
    """A 0.2 kg ball hits the ground (paper constants) at 0.1 to 10 m/s: the rebound speed
    is below the impact speed. With the damper's sign flipped (the paper's gap-form sign
    read with δ as penetration) it would leave faster: shown as a control."""
    r = 0.03
    scene, params, state = _scene(
        points=[{"name": "ball", "mass": 0.2, "pos": [0, 0, r + 1e-5]}],
        groups=[{"name": "ball", "members": ["ball"], "radius": r}], pairs=[("ball", "ground")],
        model=model,
    )
    speeds = jnp.array([0.1, 1.0, 3.0, 10.0])

    def rebound(params, speed):
        phys = state.phys.replace(point_vel=jnp.array([[0.0, 0.0, -1.0]]) * speed)
        return solve_adaptive(scene, params, phys, 0.0, 2e-3).point_vel[0, 2]

    run = jax.jit(jax.vmap(rebound, in_axes=(None, 0)))
    out = np.asarray(run(params, speeds))
    assert np.all(out > 0.0)                                   # it did bounce back
    assert np.all(out <= np.asarray(speeds) * (1.0 + 1e-9)), out
    assert out[-1] < 0.9 * 10.0                                # a hard hit loses energy in the damper
    flipped = params.replace(contact=params.contact.replace(damping=-params.contact.damping))
    assert np.all(np.asarray(run(flipped, speeds))[1:] > np.asarray(speeds)[1:])
