"""Sphere-against-capsule contact (rope and spring segments with a radius).

* the contact stage against an independent NumPy re-derivation (closest point, depth,
  normal and friction laws, split of the reaction onto the end nodes), float64, on random
  configurations with points, a rigid body (spinning, with a rope tied to its marker) and
  anchors;
* momentum: forces balance, and moments too without friction;
* the headline: a ball smaller than the spacing of the net's masses falls through a net
  whose masses carry spheres, and is caught and held by the same net with capsules;
* finite gradients at a zero-length segment, at a sphere centred on a segment end and on
  the segment's axis;
* bad input: every misuse of ``segments`` is an error naming the field.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, config_from_dict
from mysim_jax.contact.forces import contact_forces
from mysim_jax.dynamics.markers import node_states
from mysim_jax.sim import rollout

BALL_R, BOX_R, ROPE_R = 0.04, 0.05, 0.01
MARKER = np.array([0.0, 0.02, 0.03])
FRICTION = {"mu_static": 0.4, "mu_dynamic": 0.3, "v_static": 0.05, "v_dynamic": 0.2}


def _small_scene(model="sharp", friction=True, precision="float64", box_sphere=True):
    """A ball (point), a box (body, sphere at its centre), a rope w -> r_0 -> r_1 -> box.m
    and a spring p -> q, all segments capsules of radius ROPE_R."""
    contact = {"model": model, "stiffness": 2.0e4, "exponent": 1.5, "damping": 30.0, "damping_depth": 2e-3,
               "smoothing": {"depth": 1e-3, "velocity": 1e-2},
               "groups": [{"name": "balls", "members": ["ball"], "radius": BALL_R},
                          {"name": "lines", "segments": ["r", "sp"], "radius": ROPE_R}],
               "pairs": [["lines", "balls"]]}
    if box_sphere:
        contact["groups"].append({"name": "boxes", "members": ["box"], "radius": BOX_R})
        contact["pairs"].append(["boxes", "lines"])
    if friction:
        contact["friction"] = FRICTION
    raw = {
        "name": "capsules",
        "sim": {"t_end": 0.01, "dt": 1e-3, "output_dt": 1e-3, "integrator": "tsit5", "precision": precision},
        "points": [{"name": n, "mass": m, "pos": pos} for n, m, pos in
                   [("ball", 0.3, [0, 0, 0.1]), ("p", 0.05, [0, 0.1, 0]), ("q", 0.07, [0.1, 0.1, 0])]],
        "anchors": [{"name": "w", "pos": [-0.1, 0.0, 0.0]}],
        "bodies": [{"name": "box", "mass": 0.8, "inertia": [1e-3, 2e-3, 3e-3], "pos": [0.1, 0, 0],
                    "markers": [{"name": "m", "pos": MARKER.tolist()}]}],
        "ropes": [{"name": "r", "start": "w", "end": "box.m", "length": 0.2, "n_masses": 2, "mass": 0.04,
                   "EA": 100.0}],
        "springs": [{"name": "sp", "start": "p", "end": "q", "stiffness": 10.0}],
        "contact": contact,
    }
    return config_from_dict(raw)


def _rotate(q, v):
    w, u = q[0], q[1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _step(x, x0, h0, x1, h1):
    s = np.clip((x - x0) / (x1 - x0), 0.0, 1.0)
    return h0 + (h1 - h0) * s * s * (3.0 - 2.0 * s)


def _softplus(x):
    return np.logaddexp(0.0, x)


def _law(model, depth, rate, slip, c):
    """NumPy normal force and friction force (on the sphere) of one contact."""
    k, n, damping, p = c["stiffness"], c["exponent"], c["damping"], c["damping_depth"]
    if model == "sharp":
        pen = max(depth, 0.0)
        f = max(k * pen ** n + _step(pen, 0.0, 0.0, p, damping) * rate, 0.0) if depth > 0 else 0.0
        speed = np.linalg.norm(slip)
    else:
        w = c["smoothing"]["depth"]
        pen = w * _softplus(depth / w)
        width = k * w ** n
        gate = 1.0 / (1.0 + np.exp(-depth / w))
        f = gate * width * _softplus((k * pen ** n + _step(pen, 0.0, 0.0, p, damping) * rate) / width)
        speed = np.sqrt(slip @ slip + c["smoothing"]["velocity"] ** 2)
    fr = c.get("friction")
    if fr is None:
        return f, np.zeros(3)
    x = speed / fr["v_static"]
    mu = (0.5 * fr["mu_static"] * x * (3 - x * x) if speed < fr["v_static"]
          else _step(speed, fr["v_static"], fr["mu_static"], fr["v_dynamic"], fr["mu_dynamic"]))
    return f, -mu * f * slip / speed


def _reference_loads(raw_contact, model, pos, vel, body_pos, body_quat, body_vel, body_angvel, box_sphere):
    """Node forces (w, ball, p, q, r_0, r_1, box.m as named), box force and world torque."""
    omega = _rotate(body_quat, body_angvel)
    marker = body_pos + _rotate(body_quat, MARKER)
    nodes = {"ball": (pos[0], vel[0]), "p": (pos[1], vel[1]), "q": (pos[2], vel[2]),
             "r_0": (pos[3], vel[3]), "r_1": (pos[4], vel[4]),
             "w": (np.array([-0.1, 0.0, 0.0]), np.zeros(3)),
             "box.m": (marker, body_vel + np.cross(omega, marker - body_pos))}
    capsules = [("w", "r_0"), ("r_0", "r_1"), ("r_1", "box.m"), ("p", "q")]
    spheres = [("ball", pos[0], vel[0], np.zeros(3), BALL_R)]
    if box_sphere:
        spheres.append(("box", body_pos, body_vel, omega, BOX_R))
    force = {n: np.zeros(3) for n in nodes}
    box_force, box_torque = np.zeros(3), np.zeros(3)
    for name, x, v, w, r in spheres:
        for a, b in capsules:
            if name in (a, b) or (name == "box" and "box.m" in (a, b)):
                continue
            (xa, va), (xb, vb) = nodes[a], nodes[b]
            ab = xb - xa
            s = float(np.clip((x - xa) @ ab / (ab @ ab), 0.0, 1.0))
            gap = x - (xa + s * ab)
            dist = np.linalg.norm(gap)
            normal = gap / dist
            depth = r + ROPE_R - dist
            dv = v - ((1 - s) * va + s * vb)
            lever = -(r - 0.5 * depth) * normal
            v_rel = dv + np.cross(w, lever)
            slip = v_rel - (v_rel @ normal) * normal
            f, friction = _law(model, depth, -(dv @ normal), slip, raw_contact)
            total = f * normal + friction
            if name == "box":
                box_force += total
                box_torque += np.cross(lever, friction)
            else:
                force[name] += total
            force[a] -= (1 - s) * total
            force[b] -= s * total
    return force, box_force, box_torque


def _random_phys(rng, phys):
    """Every node inside a 0.12 m cube: most sphere-capsule pairs overlap."""
    q = rng.normal(size=4)
    return phys.replace(
        point_pos=jnp.asarray(rng.uniform(-0.06, 0.06, phys.point_pos.shape)),
        point_vel=jnp.asarray(rng.normal(scale=0.3, size=phys.point_vel.shape)),
        body_pos=jnp.asarray(rng.uniform(-0.06, 0.06, phys.body_pos.shape)),
        body_quat=jnp.asarray((q / np.linalg.norm(q))[None]),
        body_vel=jnp.asarray(rng.normal(scale=0.3, size=phys.body_vel.shape)),
        body_angvel=jnp.asarray(rng.normal(scale=5.0, size=phys.body_angvel.shape)))


@pytest.mark.float64
@pytest.mark.parametrize("model", ["sharp", "smooth"])
@pytest.mark.parametrize("friction", [True, False])
def test_capsule_forces_match_numpy(model, friction):
    config = _small_scene(model, friction)
    scene, params, state = build(config)
    assert scene.contact.capsule_names == ("r[0]", "r[1]", "r[2]", "sp")
    # the box never touches the segment tied to its own marker, nor a rope mass its own
    assert "box|r[2]" not in scene.contact.capsule_pair_names()
    assert "ball|r[0]" in scene.contact.capsule_pair_names()
    raw_contact = config.contact.model_dump()
    stage = jax.jit(lambda phys: contact_forces(scene, params, phys, node_states(scene, params, phys)))
    point_names = list(scene.point_names)
    node_names = point_names + list(scene.marker_names) + list(scene.anchor_names)
    rng = np.random.default_rng(7)
    touching = 0
    for _ in range(25):
        phys = _random_phys(rng, state.phys)
        loads = stage(phys)
        pos, vel = np.asarray(phys.point_pos), np.asarray(phys.point_vel)
        order = [point_names.index(n) for n in ("ball", "p", "q", "r_0", "r_1")]
        quat = np.asarray(phys.body_quat[0])
        force, box_force, box_torque = _reference_loads(
            raw_contact, model, pos[order], vel[order], np.asarray(phys.body_pos[0]), quat,
            np.asarray(phys.body_vel[0]), np.asarray(phys.body_angvel[0]), True)
        expected = np.stack([force[n] for n in node_names])
        scale = max(1.0, np.abs(expected).max())
        np.testing.assert_allclose(np.asarray(loads.node_force), expected, rtol=0, atol=2e-14 * scale)
        np.testing.assert_allclose(np.asarray(loads.body_force[0]), box_force, rtol=0, atol=2e-14 * scale)
        world_torque = _rotate(quat, np.asarray(loads.body_torque[0]))
        np.testing.assert_allclose(world_torque, box_torque, rtol=0, atol=2e-14 * scale)
        touching += np.abs(expected).max() > 0
    assert touching >= 20
    # round-off: the largest difference is 5.8e-13 N, between 1e-15 and 1e-13 of the force scale


@pytest.mark.float64
@pytest.mark.parametrize("friction", [True, False])
def test_capsule_forces_balance(friction):
    """The force on each sphere is minus the sum on the capsule's end nodes (anchors
    included in the stage's node forces); without friction, the moments balance too."""
    scene, params, state = build(_small_scene("sharp", friction, box_sphere=False))
    rng = np.random.default_rng(3)
    nodes_and_loads = jax.jit(lambda phys: (node_states(scene, params, phys),
                                            contact_forces(scene, params, phys, node_states(scene, params, phys))))
    for _ in range(20):
        phys = _random_phys(rng, state.phys)
        (node_pos, node_vel), loads = nodes_and_loads(phys)
        f = np.asarray(loads.node_force)
        scale = max(1.0, np.abs(f).max())
        np.testing.assert_allclose(f.sum(0), 0.0, atol=1e-10 * scale)
        moment = np.cross(np.asarray(node_pos), f).sum(0)
        if not friction:
            np.testing.assert_allclose(moment, 0.0, atol=1e-10 * scale)


# --- the headline: a ball smaller than the mass spacing, dropped on a net ------------------

DROP_R, LINE_R, LINE_SPACING, N_LINES, SPAN = 0.04, 0.005, 0.05, 13, 1.0


def _net(capsules: bool):
    """13 parallel tension-only ropes 1 m long, 0.05 m apart, each with 5 masses 0.2 m
    apart and anchored at both ends, tied across by tension-only rungs at every mass
    (cells 0.2 m x 0.05 m); a 0.1 kg ball of radius 0.04 m. With ``capsules`` every rope
    segment and rung is a capsule of radius 0.005 m, else every rope mass carries a sphere
    of that radius."""
    ys = (np.arange(N_LINES) - (N_LINES - 1) / 2) * LINE_SPACING
    anchors, ropes, springs = [], [], []
    for i, y in enumerate(ys):
        anchors += [{"name": f"w{i}", "pos": [-SPAN / 2, float(y), 0.0]},
                    {"name": f"e{i}", "pos": [SPAN / 2, float(y), 0.0]}]
        ropes.append({"name": f"line{i}", "start": f"w{i}", "end": f"e{i}", "length": SPAN, "n_masses": 5,
                      "mass": 0.01, "EA": 2000.0, "damping": 10.0, "model": "tension_only"})
        if i:
            springs += [{"name": f"rung{i}_{j}", "start": f"line{i - 1}_{j}", "end": f"line{i}_{j}",
                         "stiffness": 2000.0 / LINE_SPACING, "damping": 10.0, "model": "tension_only"}
                        for j in range(5)]
    net = ({"name": "net", "segments": ["line*", "rung*"], "radius": LINE_R} if capsules
           else {"name": "net", "members": ["line*_*"], "radius": LINE_R})
    return config_from_dict({
        "name": "net_drop",
        "sim": {"t_end": 2.0, "dt": 1e-3, "substeps": "auto", "output_dt": 1e-2,
                "integrator": "semi_implicit_euler", "precision": "float32"},
        "points": [{"name": "ball", "mass": 0.1, "pos": [0.0, 0.0, 0.3]}],
        "anchors": anchors, "ropes": ropes, "springs": springs,
        "contact": {"stiffness": 1e5, "damping": 50.0, "damping_depth": 1e-4,
                    "friction": {"mu_static": 0.3, "mu_dynamic": 0.2, "v_static": 0.01, "v_dynamic": 0.1},
                    "groups": [{"name": "ball", "members": ["ball"], "radius": DROP_R}, net],
                    "pairs": [["ball", "net"]]},
    })


def _drop(capsules: bool, seeds):
    """Ball and lowest net point z ``(n_drops, n_out)``, ball speed ``(n_drops, n_out)``."""
    scene, params, state = build(_net(capsules))
    # drop points inside the net, away from its free edges at y = ±0.3 m
    xy = np.stack([np.random.default_rng(seed).uniform(-0.2, 0.2, 2) * [1.0, 0.75] for seed in seeds])
    starts = jax.vmap(lambda p: state.replace(phys=state.phys.replace(
        point_pos=state.phys.point_pos.at[0, :2].set(p))))(jnp.asarray(xy, state.phys.point_pos.dtype))
    steps = round(2.0 / scene.dt)
    every = round(1e-2 / scene.dt)
    traj = jax.jit(jax.vmap(lambda s: rollout(scene, params, s, steps, every)[1]))(starts)
    z = np.asarray(traj.phys.point_pos[..., 2])
    return z[:, :, 0], z[:, :, 1:].min(-1), np.linalg.norm(np.asarray(traj.phys.point_vel[:, :, 0]), axis=-1)


SEEDS = range(8)


def test_a_ball_smaller_than_the_mass_spacing_falls_through_spheres_on_the_masses():
    ball, net_low, _ = _drop(False, SEEDS)
    through = ball[:, -1] < net_low[:, -1] - 10 * DROP_R
    assert through.sum() > len(SEEDS) // 2, ball[:, -1]


def test_capsules_catch_and_hold_the_ball_in_every_drop():
    ball, net_low, speed = _drop(True, SEEDS)
    # never below the net (the ball rests on it: centre about one radius above its lowest point)
    assert np.all(ball > net_low - 2 * DROP_R), (ball - net_low).min(1)
    # at rest in the net after 2 s: over the last 0.2 s the ball moves at under a tenth of
    # its 2.4 m/s impact speed (what is left is the net's slow swing, decaying)
    assert np.all(speed[:, -20:] < 0.24), speed[:, -20:].max(1)
    assert np.all(np.abs(ball[:, -1] - net_low[:, -1]) < 3 * DROP_R)


# --- gradients --------------------------------------------------------------------------


@pytest.mark.float64
@pytest.mark.parametrize("model", ["sharp", "smooth"])
@pytest.mark.parametrize("case", ["zero_length", "sphere_on_segment_end", "sphere_on_axis", "generic"])
def test_capsule_gradients_are_finite(model, case):
    scene, params, state = build(_small_scene(model, True, box_sphere=False))
    names = list(scene.point_names)
    pos = np.asarray(state.phys.point_pos).copy()
    ball, p, q, r0 = (names.index(n) for n in ("ball", "p", "q", "r_0"))
    pos[p] = [0.0, 0.1, 0.0]
    if case == "zero_length":          # the spring p -> q collapses onto p, the ball touches it
        pos[q] = pos[p]
        pos[ball] = pos[p] + [0.0, 0.0, 0.03]
    elif case == "sphere_on_segment_end":
        pos[ball] = pos[r0]
    elif case == "sphere_on_axis":
        pos[ball] = 0.5 * (pos[p] + pos[q])
    else:
        pos[ball] = 0.5 * (pos[p] + pos[q]) + [0.003, 0.01, 0.03]
    vel = np.random.default_rng(0).normal(scale=0.2, size=pos.shape)
    phys = state.phys.replace(point_pos=jnp.asarray(pos), point_vel=jnp.asarray(vel))
    weights = jnp.asarray(np.random.default_rng(1).normal(size=(scene.n_nodes, 3)))

    def loss(phys, cparams):
        p2 = params.replace(contact=cparams)
        return jnp.sum(weights * contact_forces(scene, p2, phys).node_force)

    value, (g_phys, g_params) = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))(phys, params.contact)
    assert np.isfinite(value)
    for leaf in jax.tree_util.tree_leaves((g_phys, g_params)):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert np.any(np.asarray(g_params.capsule_radius) != 0.0) or case == "sphere_on_segment_end"
    if model == "smooth" and case == "generic":
        # against central differences along a random direction of the ball's position
        direction = np.random.default_rng(2).normal(size=3)
        eps = 1e-7

        def moved(t):
            return loss(phys.replace(point_pos=phys.point_pos.at[ball].add(t * direction)), params.contact)

        fd = (moved(eps) - moved(-eps)) / (2 * eps)
        assert float(g_phys.point_pos[ball] @ direction) == pytest.approx(float(fd), rel=1e-5, abs=1e-6)


# --- bad input ------------------------------------------------------------------------------


def _raw_with(groups, pairs):
    return {
        "name": "bad", "sim": {"t_end": 0.01, "dt": 1e-3, "output_dt": 1e-3, "integrator": "rk4"},
        "points": [{"name": "ball", "mass": 0.1, "pos": [0, 0, 0.2]}],
        "anchors": [{"name": "a", "pos": [-0.5, 0, 0]}, {"name": "b", "pos": [0.5, 0, 0]}],
        "ropes": [{"name": "rope", "start": "a", "end": "b", "length": 1.0, "n_masses": 1, "mass": 0.1,
                   "EA": 100.0}],
        "contact": {"stiffness": 1e4, "damping_depth": 1e-3, "groups": groups, "pairs": pairs},
    }


BALL = {"name": "ball", "members": ["ball"], "radius": 0.03}
ROPE = {"name": "rope", "segments": ["rope"], "radius": 0.01}


@pytest.mark.parametrize("groups, pairs, expect", [
    ([BALL, {"name": "rope", "segments": ["ropes*"], "radius": 0.01}], [["ball", "rope"]],
     ("contact.groups.1.segments.0", "'ropes*' matches no rope or spring")),
    ([BALL, {"name": "rope", "segments": ["ball"], "radius": 0.01}], [["ball", "rope"]],
     ("contact.groups.1.segments.0", "spheres on objects go under members")),
    ([BALL, {"name": "rope", "members": ["rope_0"], "segments": ["rope"], "radius": 0.01}], [["ball", "rope"]],
     ("contact.groups.1", "exactly one of members", "has both")),
    ([BALL, {"name": "rope", "radius": 0.01}], [["ball", "rope"]], ("contact.groups.1", "has neither")),
    ([BALL, ROPE, {"name": "more", "segments": ["rope"], "radius": 0.01}], [["rope", "more"]],
     ("contact.pairs.0", "two segment groups", "members group")),
    ([BALL, ROPE], [["rope", "ground"]],
     ("contact.pairs.0", "segments do not touch the ground", "spheres on its masses")),
    ([{"name": "mass", "members": ["rope_0"], "radius": 0.03}, ROPE], [["mass", "rope"]],
     ("contact.pairs.0", "lists no (sphere, segment) pair", "never touches the segments it is an end of")),
    ([BALL, {"name": "rope", "segments": ["rope"], "radius": 0.01},
      {"name": "again", "segments": ["rope"], "radius": 0.02}], [["ball", "rope"], ["ball", "again"]],
     ("contact.groups.2.radius", "segment 'rope[0]' already has a capsule of radius 0.01")),
])
def test_bad_segment_input_names_the_field(groups, pairs, expect):
    with pytest.raises(ConfigError) as info:
        config_from_dict(_raw_with(groups, pairs))
    for text in expect:
        assert text in str(info.value), str(info.value)


def test_a_pair_in_either_order_lists_the_same_capsule_pairs():
    a = build(config_from_dict(_raw_with([BALL, ROPE], [["ball", "rope"]])))[0].contact
    b = build(config_from_dict(_raw_with([BALL, ROPE], [["rope", "ball"], ["ball", "rope"]])))[0].contact
    assert a == b and a.capsule_pair_names() == ["ball|rope[0]", "ball|rope[1]"]


def test_stability_limit_counts_capsule_pairs():
    """A capsule's side moves like its lighter end node (max of 1/m over the two ends), an
    anchor end like an infinite mass: a capsule between two anchors is the ground's limit."""
    from mysim_jax.contact.build import contact_stable_step
    from mysim_jax.dynamics.stability import spring_stable_steps

    raw = _raw_with([BALL, ROPE], [["ball", "rope"]])
    raw["ropes"][0]["mass"] = 0.4                       # rope_0: 0.4 kg, ball 0.1 kg
    raw["springs"] = [{"name": "bar", "start": "a", "end": "b", "stiffness": 1.0}]
    config = config_from_dict(raw)
    scene, params, _ = build(config)
    k, c = config.contact.stiffness, config.contact.damping
    limit, what = contact_stable_step("semi_implicit_euler", config.contact, scene.contact,
                                      params.point_mass, params.body_mass)
    assert limit == pytest.approx(spring_stable_steps("semi_implicit_euler", [k], [c], [10.0], [2.5])[0])
    assert "ball|rope[" in what
    raw["contact"]["groups"][1]["segments"] = ["bar"]
    config = config_from_dict(raw)
    scene, params, _ = build(config)
    limit, what = contact_stable_step("semi_implicit_euler", config.contact, scene.contact,
                                      params.point_mass, params.body_mass)
    assert limit == pytest.approx(spring_stable_steps("semi_implicit_euler", [k], [c], [10.0], [0.0])[0])
    assert "ball|bar" in what


@pytest.mark.float64
def test_capsule_force_is_minus_the_gradient_of_the_energy_it_counts():
    """Sharp law, no damper, no friction: the forces on the points are −∂U/∂x, with U the
    capsule part of :func:`mechanical_energy` (E minus E with the capsules shrunk away)."""
    from mysim_jax.contact.energy import mechanical_energy

    scene, params, state = build(_small_scene("sharp", False, box_sphere=False))
    cp = params.contact.replace(damping=jnp.zeros_like(params.contact.damping))
    far = cp.replace(capsule_radius=cp.capsule_radius - 1.0)

    def potential(point_pos, phys):
        phys = phys.replace(point_pos=point_pos)
        return (mechanical_energy(scene, params.replace(contact=cp), phys)
                - mechanical_energy(scene, params.replace(contact=far), phys))

    rng = np.random.default_rng(5)
    forces = jax.jit(lambda phys: contact_forces(scene, params.replace(contact=cp), phys).node_force[:scene.n_points])
    gradient = jax.jit(jax.grad(potential))
    for _ in range(10):
        phys = _random_phys(rng, state.phys)
        force = forces(phys)
        grad = gradient(phys.point_pos, phys)
        scale = max(1.0, float(jnp.abs(force).max()))
        np.testing.assert_allclose(np.asarray(grad), -np.asarray(force), rtol=0, atol=2e-14 * scale)
        assert potential(phys.point_pos, phys) >= 0.0
