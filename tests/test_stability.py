"""The explicit stability check holds for the motion a scene will see.

The check bounds a spring network's top eigenvalue over every configuration the ropes can
take (``mysim_jax/dynamics/stability.py``) and accepts steps up to ``NETWORK_STEP_SAFETY``
of the resulting step. ``scripts/stability_margin.py`` measures where randomised runs blow
up against it (``docs/stability.md``); these tests check the same thing at the largest
accepted step on a smaller batch, with the same scenes and batches
(:mod:`mysim_jax.bench.stability_margin`), and that the check refuses a step where runs
blow up. A net carried by spinning bodies is among them: semi-implicit Euler takes the
gyroscopic term implicitly, and taken explicitly it blows that scene up at accepted steps.
"""

import dataclasses

import jax
import numpy as np
import pytest
import yaml

from mysim_jax.bench import stability_margin as SM
from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, config_from_dict
from mysim_jax.dynamics.constraints import constraint_error
from mysim_jax.dynamics.stability import (NETWORK_STEP_SAFETY, network_stable_step, spring_network_nodes, stable_step,
                                          stable_step_all_below)
from mysim_jax.sim import rollout


N_ENVS = 256
SPEED = 10.0      # m/s, largest initial speed of every mass (as in the measurements)
T_END = 2.0       # s




def _raw(name):
    return SM.scene_for(name, SM.DEFAULT_TARGET)


def _with(raw, integrator, dt, **sim):
    raw = yaml.safe_load(yaml.safe_dump(raw))
    t_end = round(sim.get("t_end", 1.0) / dt) * dt            # on the output grid
    raw["sim"] = {"t_end": t_end, "dt": dt, "output_dt": dt, "integrator": integrator,
                  "precision": sim.get("precision", "float32"), "substeps": sim.get("substeps", 1)}
    return config_from_dict(raw, raw["name"])


def _accepted_step(raw, integrator):
    """The largest step the check accepts on this scene (its spring network limit, from the
    float32 parameters: 1e-6 below the check's own float64 figure covers their rounding)."""
    scene, params, state = SM.built(raw, integrator)
    bound, _ = SM.limits(scene, params, state, integrator)
    return NETWORK_STEP_SAFETY * bound * (1.0 - 1e-6)


def _blow_ups(raw, integrator, h, key=0):
    """How many of N_ENVS randomised envs blow up within T_END at step ``h``."""
    scene, params, state = SM.built(raw, integrator)
    states = SM.random_states(scene, params, state, N_ENVS, SPEED, jax.random.PRNGKey(key))
    return SM.count_blow_ups(scene, params, states, h, T_END)


@pytest.mark.parametrize("name, integrator", [
    ("rope_net", "semi_implicit_euler"),
    ("random_1", "semi_implicit_euler"),    # a star of identical ropes
    ("random_5", "semi_implicit_euler"),    # a net held at its corners
    ("random_2", "semi_implicit_euler"),    # a net carried by four spinning bodies (gyroscopic term)
    ("rope_net", "rk4"),
])
def test_randomised_runs_at_the_largest_accepted_step_stay_finite(name, integrator):
    raw = _raw(name)
    h = _accepted_step(raw, integrator)
    build(_with(raw, integrator, h))                           # accepted ...
    with pytest.raises(ConfigError, match="sim.dt"):
        build(_with(raw, integrator, 1.001 * h))               # ... and the largest accepted
    assert _blow_ups(raw, integrator, h) == 0


def test_check_rejects_a_step_where_randomised_runs_blow_up():
    """2.0e-4 s on the rope net (semi-implicit Euler) passed the initial-geometry check,
    yet most randomised runs blow up there."""
    raw = _raw("rope_net")
    with pytest.raises(ConfigError, match="spring network"):
        build(_with(raw, "semi_implicit_euler", 2.0e-4))
    assert _blow_ups(raw, "semi_implicit_euler", 2.0e-4) > N_ENVS // 2


def test_auto_substeps_pass_the_check():
    for name in ("rope_net", "random_1", "random_2", "random_5"):
        raw = _raw(name)
        for integrator in ("semi_implicit_euler", "rk4"):
            scene, _, _ = build(_with(raw, integrator, 1e-3, substeps="auto"))
            build(_with(raw, integrator, 1e-3, substeps=scene.substeps))        # must not raise
            # and not finer than it needs to be: one sub-step fewer would be rejected
            assert scene.substeps == 1 or scene.dt / (scene.substeps - 1) > _accepted_step(raw, integrator)


def test_network_bound_holds_in_every_configuration():
    """With each spring's tangent stiffness ``k uuᵀ + (T/l)(I − uuᵀ)`` (0 <= T <= k l) at
    random directions, the mass-normalised stiffness never exceeds the scalar Laplacian's
    top eigenvalue; the directional estimate at the initial geometry does."""
    raw = _raw("rope_net")
    scene, params, state = SM.built(raw, "semi_implicit_euler")
    p = jax.tree.map(lambda x: np.asarray(x, float), params)
    a, b, inv, kept = spring_network_nodes(scene.n_points, scene.marker_body, scene.spring_node_a,
                                           scene.spring_node_b, p.point_mass, p.body_mass, p.body_inertia,
                                           p.marker_pos)
    k = p.spring_stiffness[kept]
    n = inv.shape[0]
    lap = np.zeros((n, n))
    for s in range(k.shape[0]):
        for i, j in ((a[s], b[s]), (b[s], a[s])):
            if i >= 0:
                lap[i, i] += k[s]
                if j >= 0:
                    lap[i, j] -= k[s]
    bound = np.linalg.eigvalsh(np.sqrt(inv)[:, None] * lap * np.sqrt(inv)[None, :])[-1]
    rng = np.random.default_rng(0)
    worst = 0.0
    for _ in range(200):
        u = rng.standard_normal((k.shape[0], 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        if _ % 2:                      # half the draws: all springs along one direction
            u[:] = u[0]
        tension_over_length = k * rng.uniform(0.0, 1.0, k.shape[0])
        big = np.zeros((n, 3, n, 3))
        for s in range(k.shape[0]):
            blk = k[s] * np.outer(u[s], u[s]) + tension_over_length[s] * (np.eye(3) - np.outer(u[s], u[s]))
            for i, j in ((a[s], b[s]), (b[s], a[s])):
                if i >= 0:
                    big[i, :, i, :] += blk * inv[i]
                    if j >= 0:
                        big[i, :, j, :] -= blk * np.sqrt(inv[i] * inv[j])
        worst = max(worst, np.linalg.eigvalsh(big.reshape(3 * n, 3 * n))[-1])
    assert worst <= bound * (1 + 1e-9)
    assert worst == pytest.approx(bound, rel=1e-9)      # reached with every spring aligned
    # the linearisation at the initial geometry misses that (four ropes meet at the payload)
    initial = (2.0 / SM.limits(scene, params.replace(spring_damping=0 * params.spring_damping), state,
                               "semi_implicit_euler")[1]) ** 2
    assert initial < 0.9 * bound


def _exact_top_with_body(point_mass, body, springs):
    """Top eigenvalue of the linearised network with a full 6-DOF rigid body (isotropic springs)."""
    mass, inertia, markers = body
    n = 3 * len(point_mass) + 6
    m = np.zeros((n, n))
    for i, pm in enumerate(point_mass):
        m[3 * i:3 * i + 3, 3 * i:3 * i + 3] = pm * np.eye(3)
    o = 3 * len(point_mass)
    m[o:o + 3, o:o + 3] = mass * np.eye(3)
    m[o + 3:, o + 3:] = inertia

    def jac(end):
        j = np.zeros((3, n))
        if end[0] == "p":
            j[:, 3 * end[1]:3 * end[1] + 3] = np.eye(3)
        else:
            r = markers[end[1]]
            skew = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
            j[:, o:o + 3] = np.eye(3)
            j[:, o + 3:] = -skew
        return j

    kmat = sum(k * (jac(e1) - jac(e0)).T @ (jac(e1) - jac(e0)) for e0, e1, k in springs)
    chol_inv = np.linalg.inv(np.linalg.cholesky(m))
    return np.linalg.eigvalsh(chol_inv @ kmat @ chol_inv.T)[-1]


def test_body_markers_bound_the_rigid_body_modes():
    """Two point masses, each on a spring to one end of a rigid bar, and joined to each other:
    the bar's rotation mode beats a model that lumps the bar into one node, not the bound."""
    r, inertia, pm = 0.3, np.diag([0.01, 0.01, 0.01]), [0.1, 0.1]
    markers = [np.array([r, 0.0, 0.0]), np.array([-r, 0.0, 0.0])]
    springs = [(("m", 0), ("p", 0), 1.0), (("m", 1), ("p", 1), 1.0), (("p", 0), ("p", 1), 1.0)]
    exact = _exact_top_with_body(pm, (1.0, inertia, markers), springs)

    def top(node_a, node_b, inv):     # undamped semi-implicit Euler: h = 2 / √λ
        return (2.0 / network_stable_step("semi_implicit_euler", node_a, node_b, [1.0] * 3, [0.0] * 3, inv)[0]) ** 2

    # scene numbering: points 0, 1; markers 2, 3 (both on body 0)
    node = {("p", 0): 0, ("p", 1): 1, ("m", 0): 2, ("m", 1): 3}
    a, b, inv, kept = spring_network_nodes(2, [0, 0], [node[s[0]] for s in springs], [node[s[1]] for s in springs],
                                           pm, [1.0], inertia[None], np.array(markers))
    assert kept.tolist() == [0, 1, 2]
    bound = top(a, b, inv)
    lumped = top([2, 2, 0], [0, 1, 1], [1 / pm[0], 1 / pm[1], 1.0 + r * r / 0.01])
    assert lumped < 0.9 * exact
    assert exact <= bound < 1.2 * exact


def _rk4_limits(omega, eta):
    """Stable RK4 steps of the oscillators ``(omega[i], eta[i])``: bisection on the spectral
    radius of the one-step matrix ``Σ (hA)^n / n!`` (n <= 4), all at once."""
    omega, eta = np.asarray(omega, float), np.asarray(eta, float)
    lo, hi = np.zeros_like(omega), 10.0 / np.maximum(omega, eta)
    for _ in range(60):
        h = 0.5 * (lo + hi)
        a = np.zeros(omega.shape + (2, 2))
        a[..., 0, 1] = h
        a[..., 1, 0] = -h * omega ** 2
        a[..., 1, 1] = -h * eta
        out, term = np.eye(2) + 0 * a, np.eye(2) + 0 * a
        for n in range(1, 5):
            term = term @ a / n
            out = out + term
        stable = np.abs(np.linalg.eigvals(out)).max(axis=-1) <= 1 + 1e-12
        lo, hi = np.where(stable, h, lo), np.where(stable, hi, h)
    return lo


def test_rk4_network_step_covers_every_mode_below_the_top_eigenvalues():
    """RK4's limit is not monotone in damping: the network step is the smallest over all
    oscillators with ω <= ω_max, η <= η_max (brute force on a grid), not the corner's."""
    for omega, eta in ((1.0, 0.3), (1.0, 1.7), (1.0, 3.0), (2.0, 0.5)):
        w, e = np.meshgrid(np.linspace(0.01, omega, 60), np.linspace(0.0, eta, 60))
        grid = _rk4_limits(w, e).min()
        box = stable_step_all_below("rk4", omega, eta)
        assert box == pytest.approx(grid, rel=1e-3)       # the grid's spacing
        assert box <= grid * (1 + 1e-9)
    assert stable_step_all_below("rk4", 1.0, 0.3) < 0.97 * stable_step("rk4", 1.0, 0.3)
    # semi-implicit Euler's limit falls with both: the corner is the minimum
    assert stable_step_all_below("semi_implicit_euler", 1.0, 0.3) == stable_step("semi_implicit_euler", 1.0, 0.3)


def _weld(dt, alpha=50.0, beta=50.0):
    """A bar welded (fixed joint) to a wall anchor, starting 5 cm off its joint."""
    return config_from_dict({
        "name": "weld",
        "sim": {"t_end": round(4.0 / dt) * dt, "dt": dt, "output_dt": dt, "integrator": "semi_implicit_euler",
                "precision": "float64"},
        "baumgarte": {"alpha": alpha, "beta": beta},
        "anchors": [{"name": "wall", "pos": [0, 0, 0]}],
        "bodies": [{"name": "bar", "mass": 1.0, "inertia": [0.01, 0.02, 0.02], "pos": [0.25, 0.0, -0.01],
                    "markers": [{"name": "root", "pos": [-0.2, 0, 0]}]}],
        "joints": [{"name": "weld", "type": "fixed", "marker_i": "wall", "marker_j": "bar.root"}],
    }, "weld")


@pytest.mark.float64
def test_baumgarte_limit_uses_the_damping_2_alpha():
    """``C̈ + 2αĊ + β²C = 0`` is the oscillator ω = β, η = 2α. A step between its semi-implicit
    Euler limit and the (larger) one with η = α is rejected, and a run there diverges; just
    below the limit the constraint error decays. (For RK4 the limit with η = α is the
    smaller one, so only semi-implicit Euler separates the two.)"""
    limit = stable_step("semi_implicit_euler", 50.0, 100.0)
    wrong = stable_step("semi_implicit_euler", 50.0, 50.0)
    assert wrong > 1.4 * limit
    between = 0.5 * (limit + wrong)
    with pytest.raises(ConfigError, match="Baumgarte"):
        build(_weld(between))
    errors = {}
    for h in (0.98 * limit, between):
        scene, params, state = build(_weld(0.98 * limit))          # the check passes here ...
        scene = dataclasses.replace(scene, dt=h)      # ... then step at h
        n = int(4.0 / h)
        final, _ = jax.jit(lambda s: rollout(scene, params, s, n, n))(state)
        errors[h] = (float(np.abs(np.asarray(constraint_error(scene, params, state.phys))).max()),
                     float(np.nan_to_num(np.abs(np.asarray(constraint_error(scene, params, final.phys))),
                                         nan=np.inf).max()))
    start, end = errors[0.98 * limit]
    assert start > 0.04 and end < 1e-6 * start          # decays by over 6 orders in 4 s
    assert not errors[between][1] < 1.0                   # diverged (or not finite)


def test_large_networks_use_a_conservative_eigenvalue_bound(monkeypatch):
    """Above EXACT_EIG_MAX_NODES the top eigenvalue is a Gershgorin row-sum bound: never a
    larger step than the exact one."""
    import mysim_jax.dynamics.stability as stability

    raw = _raw("random_5")
    scene, params, state = SM.built(raw, "semi_implicit_euler")
    exact, _ = SM.limits(scene, params, state, "semi_implicit_euler")
    monkeypatch.setattr(stability, "EXACT_EIG_MAX_NODES", 0)
    gershgorin, _ = SM.limits(scene, params, state, "semi_implicit_euler")
    assert 0.5 * exact < gershgorin <= exact       # not far below either
