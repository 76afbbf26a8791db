"""Friction between spinning rigid spheres, and of a spinning sphere on the ground, against
a NumPy re-derivation of the contact model (``mysim_jax/contact/forces.py`` docstring).

The contact point sits mid-overlap, at lever ``(r_a − δ/2) n`` from a and
``−(r_b − δ/2) n`` from b. Friction opposes the tangential slip of b's contact point
relative to a's, ``v_b + ω_b × l_b − v_a − ω_a × l_a`` (``ω`` the world angular velocity,
``R ω_body``), with the C¹ Stribeck-like law μ(|v_t|), and turns each body by
``lever × friction``. Here the spins dominate the slip (ω r ≈ 1 m/s against a relative
centre velocity of 0.3 m/s), so a sign or frame slip in ``ω × lever`` reverses or turns the
friction force; total momentum conservation cannot see that (the pair forces stay equal
and opposite), a force-level comparison does.
"""

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.contact.forces import contact_forces

pytestmark = pytest.mark.float64

K, EXPONENT, DAMPING, DEPTH_P = 2e6, 1.5, 300.0, 1e-3
MU_S, MU_D, V_S, V_D = 0.5, 0.3, 0.01, 0.1
R_PAIR, R_GROUND = 0.05, 0.04
EPS_DEPTH, EPS_VEL = 5e-5, 3e-3       # smooth model: widths large enough to matter here

# name: position, velocity, attitude (rotation vector), body-frame angular velocity
SPHERES = {
    "a": ([0.0, 0.0, 1.0], [0.1, -0.05, 0.02], [0.4, -1.1, 0.7], [12.0, -7.0, 15.0]),
    "b": (None, [-0.15, 0.2, -0.1], [-1.3, 0.2, 0.5], [-9.0, 14.0, 6.0]),
    # rolling-ish on the ground: the spin cancels most of the centre velocity at the contact
    "g": ([2.0, 0.0, R_GROUND - 3e-4], [0.3, -0.02, -0.05], [0.9, 0.6, -0.4], None),
}
PAIR_NORMAL = np.array([0.6, -0.48, 0.64])            # unit vector a -> b
PAIR_DEPTH = 4e-4                                     # inside the damping ramp (p = 1e-3 m)


def _states():
    """Positions, velocities, rotation matrices and body-frame angular velocities."""
    out = {}
    for name, (pos, vel, rotvec, omega) in SPHERES.items():
        rot = Rotation.from_rotvec(rotvec).as_matrix()
        if name == "b":
            pos = np.array(SPHERES["a"][0]) + (2 * R_PAIR - PAIR_DEPTH) * PAIR_NORMAL
        if name == "g":   # world spin about -y (rolling towards +x) slightly faster than rolling
            omega = rot.T @ np.array([0.8, 6.5, -2.0])
        out[name] = (np.asarray(pos, float), np.asarray(vel, float), rot, np.asarray(omega, float))
    return out


def _scene(model):
    raw = {
        "name": "spin_friction",
        "sim": {"t_end": 0.01, "dt": 1e-4, "output_dt": 1e-4, "integrator": "tsit5", "precision": "float64"},
        "gravity": [0.0, 0.0, -9.81],
        "bodies": [],
        "contact": {"model": model, "smoothing": {"depth": EPS_DEPTH, "velocity": EPS_VEL},
                    "stiffness": K, "exponent": EXPONENT, "damping": DAMPING, "damping_depth": DEPTH_P,
                    "friction": {"mu_static": MU_S, "mu_dynamic": MU_D, "v_static": V_S, "v_dynamic": V_D},
                    "groups": [{"name": "pair", "members": ["a", "b"], "radius": R_PAIR},
                               {"name": "roller", "members": ["g"], "radius": R_GROUND}],
                    "pairs": [["pair", "pair"], ["roller", "ground"]]},
    }
    inertia = {"a": [2e-3, 3e-3, 4e-3], "b": [1e-3, 1.5e-3, 2e-3], "g": [6e-4, 6e-4, 6e-4]}
    for name, (pos, vel, rot, omega) in _states().items():
        x, y, z, w = Rotation.from_matrix(rot).as_quat()
        raw["bodies"].append({"name": name, "mass": 1.0, "inertia": inertia[name], "pos": pos.tolist(),
                              "vel": vel.tolist(), "quat": [w, x, y, z], "angvel": omega.tolist()})
    return build(config_from_dict(raw, "test"))


def _step(x, x0, h0, x1, h1):
    s = np.clip((x - x0) / (x1 - x0), 0.0, 1.0)
    return h0 + (h1 - h0) * s * s * (3.0 - 2.0 * s)


def _mu(speed):
    if speed < V_S:
        x = speed / V_S
        return 0.5 * MU_S * x * (3.0 - x * x)
    return _step(speed, V_S, MU_S, V_D, MU_D)


def _softplus(x):
    return np.logaddexp(0.0, x)


def _normal_force(depth, rate, model):
    if model == "sharp":
        return max(0.0, K * depth ** EXPONENT + _step(depth, 0.0, 0.0, DEPTH_P, DAMPING) * rate)
    pen = EPS_DEPTH * _softplus(depth / EPS_DEPTH)
    width = K * EPS_DEPTH ** EXPONENT
    inner = K * pen ** EXPONENT + _step(pen, 0.0, 0.0, DEPTH_P, DAMPING) * rate
    return width * _softplus(inner / width) / (1.0 + np.exp(-depth / EPS_DEPTH))


def _friction(fn, slip, model):
    speed = np.linalg.norm(slip)
    seen = speed if model == "sharp" else np.sqrt(speed ** 2 + EPS_VEL ** 2)
    return -_mu(seen) * fn * slip / seen, speed


def _reference(model):
    """Force (world) and torque (body frame) on each sphere, and the slip speeds."""
    s = _states()
    (xa, va, ra, wa), (xb, vb, rb, wb), (xg, vg, rg, wg) = s["a"], s["b"], s["g"]
    d = xb - xa
    n = d / np.linalg.norm(d)
    depth = 2 * R_PAIR - np.linalg.norm(d)
    fn = _normal_force(depth, -(vb - va) @ n, model)
    lever_a, lever_b = (R_PAIR - 0.5 * depth) * n, -(R_PAIR - 0.5 * depth) * n
    v_rel = vb + np.cross(rb @ wb, lever_b) - va - np.cross(ra @ wa, lever_a)
    fr, pair_speed = _friction(fn, v_rel - (v_rel @ n) * n, model)
    force = {"b": fn * n + fr, "a": -(fn * n + fr)}
    torque = {"b": rb.T @ np.cross(lever_b, fr), "a": ra.T @ np.cross(lever_a, -fr)}
    up = np.array([0.0, 0.0, 1.0])
    depth_g = R_GROUND - xg[2]
    fn_g = _normal_force(depth_g, -vg[2], model)
    lever_g = -(R_GROUND - 0.5 * depth_g) * up
    v_contact = vg + np.cross(rg @ wg, lever_g)
    fr_g, ground_speed = _friction(fn_g, v_contact - (v_contact @ up) * up, model)
    force["g"] = fn_g * up + fr_g
    torque["g"] = rg.T @ np.cross(lever_g, fr_g)
    return force, torque, pair_speed, ground_speed


@pytest.mark.parametrize("model", ["sharp", "smooth"])
def test_friction_of_spinning_spheres_matches_numpy(model):
    scene, params, state = _scene(model)
    loads = jax.jit(lambda ph: contact_forces(scene, params, ph))(state.phys)
    force, torque, pair_speed, ground_speed = _reference(model)
    # the cases are the ones meant: the pair slides fast (μ = μ_d), the ground contact slips
    # in the Stribeck transition between v_s and v_d
    assert pair_speed > V_D and V_S < ground_speed < V_D, (pair_speed, ground_speed)
    for i, name in enumerate(scene.body_names):
        # measured max abs error (both models): 2.3e-12 N on forces of 15-55 N, 4.3e-14 N m on torques of
        # 0.07-0.8 N m: round-off, amplified ~250x by the depth 2r − |d| (4e-4 m out of 0.1 m)
        np.testing.assert_allclose(np.asarray(loads.body_force[i]), force[name], rtol=0, atol=2e-11)
        np.testing.assert_allclose(np.asarray(loads.body_torque[i]), torque[name], rtol=0, atol=4e-13)
    # friction is a sizeable part of each force, not round-off
    for name in ("a", "g"):
        assert np.linalg.norm(np.cross(force[name], [0, 0, 1] if name == "g" else PAIR_NORMAL)) > 1.0
    if model == "smooth":   # and the smoothing changes the forces well beyond the tolerance
        sharp_force, sharp_torque, _, _ = _reference("sharp")
        assert np.abs(force["g"] - sharp_force["g"]).max() > 1e-2       # 0.029 N
        assert np.abs(force["a"] - sharp_force["a"]).max() > 5e-3       # 0.011 N
