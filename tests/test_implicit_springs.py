"""``integrator: implicit_euler``: linearly implicit springs between point masses.

* stability: on the paper's rope net at 10x the explicit step limit of semi-implicit Euler
  (the limit the builder's check reports), randomised runs stay finite and lose energy,
  while semi-implicit Euler at that step is rejected by the check and blows up if forced;
* accuracy: first-order convergence to the independent reference of
  tests/reference_models.py (NumPy rope equations, SciPy DOP853 at rtol 1e-10), and
  O(h) agreement with semi-implicit Euler;
* the linear solve: the assembled stiffness and damping equal the exact Jacobians of the
  spring forces where the positive semi-definite approximation is exact, the CG residual
  after the configured iterations is small on the rope net and the capture nets, and a step
  with a dense ``np.linalg.solve`` agrees with the CG step;
* gradients through a rollout against central finite differences;
* bad input: ``sim.implicit_iterations`` bounds, and the explicit limits that still apply.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.core import batching
from mysim_jax.bench import stability_margin as SM
from mysim_jax.build import IMPLICIT_AUTO_FACTOR, build
from mysim_jax.config.scene import IMPLICIT_ITERATIONS, ConfigError, config_from_dict, load_config
from mysim_jax.dynamics import implicit_springs as IS
from mysim_jax.dynamics.forces import spring_forces
from mysim_jax.dynamics.markers import node_states
from mysim_jax.dynamics.stability import NETWORK_STEP_SAFETY
from mysim_jax.sim import accelerations, rollout

from conftest import CONFIGS, ROOT
from reference_models import RopeNetReference

ROPE_NET = CONFIGS / "rope_net.yaml"


def _explicit_limit():
    """The largest step the builder's check accepts for semi-implicit Euler on the rope net
    (its spring-network limit; 1e-6 below covers float32 rounding of the parameters)."""
    raw = SM.rope_net_raw()
    scene, params, state = SM.built(raw, "semi_implicit_euler")
    bound, _ = SM.limits(scene, params, state, "semi_implicit_euler")
    return NETWORK_STEP_SAFETY * bound * (1.0 - 1e-6)


def _rope_config(integrator, dt, precision="float64", t_end=None, extra=()):
    t_end = dt if t_end is None else t_end
    return load_config(ROPE_NET, [f"sim.integrator={integrator}", f"sim.dt={dt!r}", f"sim.output_dt={dt!r}",
                                  f"sim.t_end={t_end!r}", f"sim.precision={precision}", *extra])


def _energy(scene, params, phys):
    """Kinetic + gravitational + elastic energy ``(n_envs,)`` of batched rope-net states."""
    m = np.asarray(params.point_mass, float)
    g = np.asarray(params.gravity, float)
    x = np.asarray(phys.point_pos, float)
    v = np.asarray(phys.point_vel, float)
    kinetic = 0.5 * np.einsum("p,epi,epi->e", m, v, v)
    potential = -np.einsum("p,epi,i->e", m, x, g)
    nodes = np.concatenate([x, np.broadcast_to(np.asarray(params.anchor_pos, float), (x.shape[0],) + params.anchor_pos.shape)], 1)
    a = [n if n < scene.n_points else n - scene.n_markers for n in scene.spring_node_a]
    b = [n if n < scene.n_points else n - scene.n_markers for n in scene.spring_node_b]
    length = np.linalg.norm(nodes[:, b] - nodes[:, a], axis=-1)
    k = np.asarray(params.spring_stiffness, float)
    rest = np.asarray(params.spring_rest_length, float)
    return kinetic + potential + 0.5 * ((length - rest) ** 2 * k).sum(axis=1)


# --- stability --------------------------------------------------------------------------------


def test_rope_net_stable_at_ten_times_the_explicit_limit():
    h = 10.0 * _explicit_limit()
    with pytest.raises(ConfigError, match=r"sim\.dt.*semi_implicit_euler.*spring network"):
        build(_rope_config("semi_implicit_euler", h, "float32"))
    scene, params, state = build(_rope_config("implicit_euler", h, "float32"))     # accepted
    assert scene.implicit_iterations == IMPLICIT_ITERATIONS
    n_envs, t_end = 64, 2.0
    states = SM.random_states(scene, params, state, n_envs, 10.0, jax.random.PRNGKey(0))
    n_steps = int(np.ceil(t_end / h))
    final = jax.jit(jax.vmap(lambda s: rollout(scene, params, s, n_steps, n_steps)[0]))(states)
    assert not SM.blown_up(final).any()
    assert np.abs(np.asarray(final.phys.point_pos)).max() < 3.0           # ropes of 1 m from the origin
    e0, e1 = _energy(scene, params, states.phys), _energy(scene, params, final.phys)
    # backward Euler and the rope dampers only take energy out (10 m/s: e0 ~ 100 J per env)
    assert (e1 <= e0 + 1e-3 * np.abs(e0)).all(), (e0, e1)
    # semi-implicit Euler forced to the same step blows up
    sie_scene, sie_params, _ = SM.built(SM.rope_net_raw(), "semi_implicit_euler")
    assert SM.count_blow_ups(sie_scene, sie_params, states, h, 0.2) == n_envs


def test_auto_takes_a_multiple_of_the_explicit_step_without_explicit_parts():
    """No contact, joints or springs on markers: ``substeps: auto`` takes
    IMPLICIT_AUTO_FACTOR times semi-implicit Euler's accepted step."""
    config = load_config(ROPE_NET, ["sim.integrator=implicit_euler", "sim.dt=0.01", "sim.output_dt=0.01",
                                    "sim.substeps=auto", "sim.precision=float32"])
    scene, _, _ = build(config)
    assert scene.substeps == int(np.ceil(0.01 / (IMPLICIT_AUTO_FACTOR * _explicit_limit()) - 1e-6))


# --- accuracy ---------------------------------------------------------------------------------

T_ACC = 0.5


@pytest.fixture(scope="module")
def reference():
    ref = RopeNetReference(load_config(ROPE_NET))
    return ref.solve(T_ACC, np.array([0.0, T_ACC]))[-1]


def _final_pos(integrator, dt):
    scene, params, state = build(_rope_config(integrator, dt))
    n = int(round(T_ACC / dt))
    final = jax.jit(lambda s: rollout(scene, params, s, n, n)[0])(state)
    return np.asarray(final.phys.point_pos)


@pytest.mark.float64
def test_first_order_convergence_to_the_reference(reference):
    steps = (1e-4, 5e-5, 2.5e-5)
    imp = [_final_pos("implicit_euler", h) for h in steps]
    sie = [_final_pos("semi_implicit_euler", h) for h in steps]
    err = [np.abs(x - reference).max() for x in imp]
    gap = [np.abs(x - y).max() for x, y in zip(imp, sie)]
    print("implicit_euler errors", err, "distance to semi-implicit Euler", gap)
    # measured: 1.44e-3, 7.3e-4, 3.6e-4 m (payload sag ~5 cm): each halving halves the error
    for coarse, fine in zip(err, err[1:]):
        assert 1.8 < coarse / fine < 2.2
    assert err[0] < 3e-3
    # and the gap to semi-implicit Euler (itself ~100x closer to the reference) is O(h) too
    for coarse, fine in zip(gap, gap[1:]):
        assert 1.8 < coarse / fine < 2.2


# --- the linear solve -------------------------------------------------------------------------


def _dense(springs, lin, mass, h):
    """``A = M + h D + h² S`` assembled as a dense (3n x 3n) NumPy matrix."""
    n = springs.n_points
    a_mat = np.kron(np.diag(np.asarray(mass, float)), np.eye(3))
    u = np.asarray(lin.unit, float)
    for s in range(springs.n_springs):
        uu = np.outer(u[s], u[s])
        blk = ((h * float(lin.damping[s]) + h * h * float(lin.axial[s])) * uu
               + h * h * float(lin.transverse[s]) * (np.eye(3) - uu))
        ends = [e for e in (springs.end_a[s], springs.end_b[s]) if e < n]
        for i in ends:
            a_mat[3 * i:3 * i + 3, 3 * i:3 * i + 3] += blk
        if len(ends) == 2:
            i, j = ends
            a_mat[3 * i:3 * i + 3, 3 * j:3 * j + 3] -= blk
            a_mat[3 * j:3 * j + 3, 3 * i:3 * i + 3] -= blk
    return a_mat


def _random_state(state, speed, seed):
    rng = np.random.default_rng(seed)
    vel = rng.normal(scale=speed, size=state.phys.point_vel.shape)
    return state.replace(phys=state.phys.replace(point_vel=jnp.asarray(vel, state.phys.point_vel.dtype)))


@pytest.mark.float64
def test_linearisation_is_the_exact_jacobian_where_the_approximation_is_exact():
    """At rest with every spring stretched (no damping-geometric or non-symmetric term,
    no compression), S = −∂f/∂x and D = −∂f/∂v exactly."""
    scene, params, state = build(_rope_config("implicit_euler", 1e-3))
    params = params.replace(spring_rest_length=0.98 * params.spring_rest_length)
    springs = IS.implicit_springs(scene)
    assert springs.n_springs == scene.n_springs
    x = state.phys.point_pos + 3e-4 * jnp.asarray(np.random.default_rng(1).normal(size=state.phys.point_pos.shape))
    v = jnp.zeros_like(x)
    nodes = node_states(scene, params, state.phys.replace(point_pos=x))[0]
    lengths = np.linalg.norm(np.asarray(nodes)[list(scene.spring_node_b)] - np.asarray(nodes)[list(scene.spring_node_a)],
                             axis=1)
    assert (lengths > np.asarray(params.spring_rest_length)).all()

    def force(xp, vp):
        phys = state.phys.replace(point_pos=xp, point_vel=vp)
        return spring_forces(scene, params, *node_states(scene, params, phys))[:scene.n_points]

    n3 = 3 * scene.n_points
    k_exact = -np.asarray(jax.jacfwd(force, 0)(x, v)).reshape(n3, n3)
    c_exact = -np.asarray(jax.jacfwd(force, 1)(x, v)).reshape(n3, n3)
    lin = IS.linearise(springs, params, x, v)
    zero_mass = jnp.zeros(scene.n_points)
    s_dense = _dense(springs, lin.replace(damping=0.0 * lin.damping), zero_mass, 1.0)
    d_dense = _dense(springs, lin.replace(axial=0.0 * lin.axial, transverse=0.0 * lin.transverse), zero_mass, 1.0)
    np.testing.assert_allclose(s_dense, k_exact, atol=1e-9 * np.abs(k_exact).max())
    np.testing.assert_allclose(d_dense, c_exact, atol=1e-12 * np.abs(c_exact).max())


def _solve_case(built, h, speed, seed=0, rest_scale=1.0):
    """``(springs, system, CG solution, dense solution, dense matrix)`` for the built scene
    at a random-velocity state, with rest lengths scaled by ``rest_scale``."""
    scene, params, state = built
    params = params.replace(spring_rest_length=rest_scale * params.spring_rest_length)
    state = _random_state(state, speed, seed)
    springs = IS.implicit_springs(scene)

    @jax.jit
    def solve(params, phys):
        # springs and gravity (rotors and contact would need the controller; not what is tested)
        force = spring_forces(scene, params, *node_states(scene, params, phys))[:scene.n_points]
        point_acc = force / params.point_mass[:, None] + params.gravity
        system = IS.velocity_system(springs, params, phys, point_acc, jnp.asarray(h))
        return point_acc, system, IS.solve_velocity_change(springs, system, h * point_acc, scene.implicit_iterations)

    point_acc, system, dv = solve(params, state.phys)
    if scene.quadrotor is None:
        np.testing.assert_allclose(point_acc, accelerations(scene, params, state.phys).point_acc, rtol=1e-12,
                                   atol=1e-9)
    a_mat = _dense(springs, system.lin, params.point_mass, h)
    exact = np.linalg.solve(a_mat, np.asarray(system.rhs, float).reshape(-1)).reshape(-1, 3)
    return springs, system, np.asarray(dv), exact, a_mat


def _relative_residual(a_mat, system, dv):
    b = np.asarray(system.rhs, float).reshape(-1)
    return np.linalg.norm(b - a_mat @ dv.reshape(-1)) / np.linalg.norm(b)


@pytest.mark.float64
def test_cg_on_the_rope_net_matches_a_dense_solve():
    h = 10.0 * _explicit_limit()
    config = _rope_config("implicit_euler", h)
    springs, system, dv, exact, a_mat = _solve_case(build(config), h, speed=5.0)
    eig = np.linalg.eigvalsh(a_mat)
    assert np.allclose(a_mat, a_mat.T) and eig[0] > 0              # symmetric positive definite
    res = _relative_residual(a_mat, system, dv)
    print(f"rope net, h = {h:.3g} s, cond {eig[-1] / eig[0]:.3g}: residual {res:.2e}")
    assert res < 1e-8                                              # measured: ~1e-15
    np.testing.assert_allclose(dv, exact, atol=1e-9 * np.abs(exact).max())
    # the whole step: CG and dense solve agree
    scene, params, state = build(config)
    state = _random_state(state, 5.0, 0)
    after = jax.jit(lambda s: rollout(scene, params, s, 1, 1)[0])(state)
    v_dense = np.asarray(state.phys.point_vel) + exact
    np.testing.assert_allclose(np.asarray(after.phys.point_vel), v_dense, atol=1e-9 * np.abs(v_dense).max())
    np.testing.assert_allclose(np.asarray(after.phys.point_pos),
                               np.asarray(state.phys.point_pos) + h * v_dense, atol=1e-12)


@pytest.mark.float64
@pytest.mark.parametrize("name", ["capture_env_falling", "capture_falling"])
def test_cg_residual_on_the_capture_nets(name):
    """At the scene's own step (``substeps: auto``: contact limits it) and at 10x it, from
    a state with 0.5 m/s random velocities and the net lines pulled taut (rest lengths
    scaled by 0.75: the net starts with its knots 0.8 of a line apart, and tension-only
    lines that do not pull would leave only the diagonal)."""
    base = load_config(CONFIGS / f"{name}.yaml", ["sim.integrator=implicit_euler", "sim.substeps=auto",
                                                  "sim.precision=float64"])
    built = build(base)
    scene = built[0]
    # measured (default 20 iterations): ~1e-15 at the scene's step; 1.2e-3 (180 points, cond 129)
    # and 7.5e-3 (353 points, cond 177) at 10x it, where 20 iterations no longer converge fully
    for h, bound in ((scene.substep, 1e-8), (10 * scene.substep, 2e-2)):
        springs, system, dv, exact, a_mat = _solve_case(built, h, speed=0.5, rest_scale=0.75)
        assert (np.asarray(system.lin.axial) > 0).mean() > 0.9
        res = _relative_residual(a_mat, system, dv)
        print(f"{name}: {springs.n_springs} implicit springs, {scene.n_points} points, h = {h:.3g} s: "
              f"residual {res:.2e}")
        assert res < bound


def test_batch_last_step_needs_no_fallback():
    """The CG solve (gathers, segment_sum, a fixed-length loop, closed-form 3 x 3 inverses)
    has a batch-last rule for every primitive."""
    scene, params, state = build(_rope_config("implicit_euler", 1e-3, "float32"))
    states = jax.tree.map(lambda x: jnp.broadcast_to(x, (2,) + x.shape), state)
    batching.FALLBACK_COUNTS.clear()
    jax.eval_shape(batching.vmap(lambda s: rollout(scene, params, s, 2, 1)), states)
    assert batching.FALLBACK_COUNTS == {}


# --- gradients --------------------------------------------------------------------------------


@pytest.mark.float64
def test_gradient_through_a_rollout_matches_finite_differences():
    h = 10.0 * _explicit_limit()
    scene, params, state = build(_rope_config("implicit_euler", h))
    state = _random_state(state, 1.0, 3)
    n = 40

    def loss(scale, v_payload):
        p = params.replace(spring_stiffness=scale * params.spring_stiffness,
                           spring_damping=scale * params.spring_damping)
        s = state.replace(phys=state.phys.replace(point_vel=state.phys.point_vel.at[0, 0].set(v_payload)))
        final, _ = rollout(scene, p, s, n, n)
        return final.phys.point_pos[0, 2] + 0.5 * final.phys.point_pos[3, 0]

    f = jax.jit(loss)
    grad = jax.jit(jax.grad(loss, argnums=(0, 1)))(1.0, 0.5)
    eps = 1e-6
    fd = ((f(1.0 + eps, 0.5) - f(1.0 - eps, 0.5)) / (2 * eps), (f(1.0, 0.5 + eps) - f(1.0, 0.5 - eps)) / (2 * eps))
    # measured: (3.888e-3, 1.248e-5) both ways, to 3e-6 relative
    for g, d in zip(grad, fd):
        assert np.isfinite(float(g)) and abs(float(d)) > 1e-6
        np.testing.assert_allclose(float(g), float(d), rtol=1e-5)


# --- bad input --------------------------------------------------------------------------------


@pytest.mark.parametrize("value", ["0", "-3", "10001", "2.5", "true"])
def test_implicit_iterations_bounds(value):
    with pytest.raises(ConfigError, match="sim.implicit_iterations"):
        load_config(ROPE_NET, ["sim.integrator=implicit_euler", f"sim.implicit_iterations={value}"])


def test_implicit_iterations_with_another_integrator_is_an_error():
    with pytest.raises(ConfigError, match="implicit_iterations.*implicit_euler"):
        load_config(ROPE_NET, ["sim.integrator=rk4", "sim.implicit_iterations=10"])


def test_config_with_implicit_euler_validates_without_jax():
    code = ("import sys; from mysim_jax.config.scene import load_config; "
            f"c = load_config({str(ROPE_NET)!r}, ['sim.integrator=implicit_euler', 'sim.implicit_iterations=7']); "
            "assert c.sim.cg_iterations == 7; assert 'jax' not in sys.modules, 'jax imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_explicit_parts_keep_their_limits():
    """Contact (capture scene) and springs on body markers still limit the step, and the
    error says that implicit_euler cannot take them."""
    config = load_config(CONFIGS / "capture_falling.yaml", ["sim.integrator=implicit_euler", "sim.substeps=10"])
    with pytest.raises(ConfigError, match=r"sim\.dt.*implicit_euler takes only.*springs on body markers.*contact"):
        build(config)
    raw = {
        "name": "marker_spring",
        "sim": {"t_end": 0.01, "dt": 1e-3, "output_dt": 1e-3, "integrator": "implicit_euler"},
        "bodies": [{"name": "b", "mass": 1.0, "inertia": [0.01, 0.01, 0.01], "pos": [0, 0, 0],
                    "markers": [{"name": "m", "pos": [0.1, 0, 0]}]}],
        "points": [{"name": "p", "mass": 0.01, "pos": [0.2, 0, 0]}],
        "anchors": [{"name": "a", "pos": [0.4, 0, 0]}],
        "springs": [{"name": "s_marker", "start": "b.m", "end": "p", "stiffness": 1e5},
                    {"name": "s_anchor", "start": "p", "end": "a", "stiffness": 1e6}],
    }
    with pytest.raises(ConfigError, match=r"springs on body markers.*'s_marker'"):
        build(config_from_dict(raw, "marker_spring"))
    # the stiffer spring to the anchor alone would allow only ~1e-4 s: implicit, it does not limit
    raw["springs"] = raw["springs"][1:]
    scene, _, _ = build(config_from_dict(raw, "marker_spring"))
    assert IS.implicit_springs(scene).n_springs == 1 and scene.substeps == 1
