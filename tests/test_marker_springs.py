"""Springs attached to offset markers of a rotated, spinning rigid body, against NumPy.

A marker at body-frame offset ``r`` on a body at ``p`` with attitude ``R`` and body-frame
angular velocity ``ω`` sits at ``p + R r`` and moves at ``v + (R ω) × (R r)`` (the world
angular velocity crossed with the world lever). A force ``F`` (world) at the marker
pushes the centre of mass with ``F`` and turns the body with the world torque
``(R r) × F``, i.e. ``Rᵀ((R r) × F)`` in the body frame. The reference below is written
with SciPy rotation matrices, independently of the library's quaternion helpers; the
attitude (about 100° about a skew axis) and the spin are chosen so that each of the
plausible frame slips (offset not rotated, ``R(ω × r)`` replaced by ``ω × (R r)``, the
torque taken from the world-frame force) changes the numbers at order one.
"""

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.dynamics.markers import node_states
from mysim_jax.sim import accelerations

pytestmark = pytest.mark.float64

MASS = 1.7
INERTIA = np.array([0.031, 0.052, 0.064])
POS = np.array([0.2, -0.1, 0.9])
VEL = np.array([0.3, -0.4, 0.25])
OMEGA = np.array([1.3, -2.1, 3.4])                 # body frame, rad/s
ROT = Rotation.from_rotvec(1.75 * np.array([0.48, -0.6, 0.64]))   # body -> world
MARKERS = {"hook": np.array([0.35, -0.22, 0.15]), "tail": np.array([-0.28, 0.05, -0.31])}
ANCHOR = np.array([1.1, 0.6, 2.2])
POINT_POS, POINT_VEL, POINT_MASS = np.array([-0.6, 0.4, 0.3]), np.array([0.5, 0.1, -0.2]), 0.4
SPRINGS = (                                  # name, start, end, k, c, rest length
    ("to_anchor", "body.hook", "ceiling", 240.0, 6.0, 0.8),
    ("to_point", "p", "body.tail", 150.0, 4.5, 0.5),
)


def _scene():
    q = ROT.as_quat()                       # SciPy is scalar-last
    raw = {
        "name": "marker_springs",
        "sim": {"t_end": 0.01, "dt": 1e-4, "output_dt": 1e-4, "integrator": "rk4", "precision": "float64"},
        "gravity": [0.0, 0.0, 0.0],
        "points": [{"name": "p", "mass": POINT_MASS, "pos": POINT_POS.tolist(), "vel": POINT_VEL.tolist()}],
        "anchors": [{"name": "ceiling", "pos": ANCHOR.tolist()}],
        "bodies": [{"name": "body", "mass": MASS, "inertia": INERTIA.tolist(), "pos": POS.tolist(),
                    "quat": [q[3], q[0], q[1], q[2]], "vel": VEL.tolist(), "angvel": OMEGA.tolist(),
                    "markers": [{"name": n, "pos": r.tolist()} for n, r in MARKERS.items()]}],
        "springs": [{"name": n, "start": a, "end": b, "stiffness": k, "damping": c, "rest_length": s0,
                     "model": "linear"} for n, a, b, k, c, s0 in SPRINGS],
    }
    return build(config_from_dict(raw, "test"))


def _reference(damped=True):
    """Marker kinematics, forces on the body (world) and body-frame torque, in NumPy."""
    rot = ROT.as_matrix()
    omega_world = rot @ OMEGA
    nodes = {"ceiling": (ANCHOR, np.zeros(3)), "p": (POINT_POS, POINT_VEL)}
    for name, r in MARKERS.items():
        lever = rot @ r
        nodes[f"body.{name}"] = (POS + lever, VEL + np.cross(omega_world, lever))
    force_on = {name: np.zeros(3) for name in nodes}
    for _, a, b, k, c, s0 in SPRINGS:
        d = nodes[b][0] - nodes[a][0]
        length = np.linalg.norm(d)
        unit = d / length
        tension = k * (length - s0) + (c if damped else 0.0) * (nodes[b][1] - nodes[a][1]) @ unit
        force_on[a] = force_on[a] + tension * unit
        force_on[b] = force_on[b] - tension * unit
    body_force = sum(force_on[f"body.{n}"] for n in MARKERS)
    torque_world = sum(np.cross(rot @ r, force_on[f"body.{n}"]) for n, r in MARKERS.items())
    return nodes, body_force, rot.T @ torque_world, force_on["p"]


def test_marker_kinematics_on_a_rotated_spinning_body():
    scene, params, state = _scene()
    pos, vel = jax.jit(lambda ph: node_states(scene, params, ph))(state.phys)
    nodes, *_ = _reference()
    for name in MARKERS:
        i = scene.n_points + scene.marker_names.index(f"body.{name}")
        # measured max abs error 2.8e-17 m, 4.4e-16 m/s (round-off); a frame slip is O(0.1-1)
        np.testing.assert_allclose(np.asarray(pos[i]), nodes[f"body.{name}"][0], rtol=0, atol=1e-15)
        np.testing.assert_allclose(np.asarray(vel[i]), nodes[f"body.{name}"][1], rtol=0, atol=5e-15)
    # the spin matters here: the lever velocity is comparable to the body's own velocity
    lever_speed = np.linalg.norm(nodes["body.hook"][1] - VEL)
    assert lever_speed > np.linalg.norm(VEL)


def test_marker_springs_force_and_body_torque():
    """Accelerations of the body and the point from two damped springs on markers:
    m a = ΣF, J ω̇ = τ − ω × Jω (τ in the body frame), against the NumPy reference."""
    scene, params, state = _scene()
    acc = jax.jit(lambda ph: accelerations(scene, params, ph))(state.phys)
    _, body_force, torque_body, point_force = _reference()
    angacc = (torque_body - np.cross(OMEGA, INERTIA * OMEGA)) / INERTIA
    # measured max abs error: 8.9e-15 m/s^2 (body, |a| ~ 60), 2.3e-13 rad/s^2 (|ω̇| ~ 1.2e3),
    # 0 (point, |a| ~ 140): tolerances ~10x the measured round-off
    np.testing.assert_allclose(np.asarray(acc.body_acc[0]), body_force / MASS, rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.asarray(acc.body_angacc[0]), angacc, rtol=0, atol=2e-12)
    np.testing.assert_allclose(np.asarray(acc.point_acc[0]), point_force / POINT_MASS, rtol=0, atol=2e-13)
    # the dampers (which see the marker velocities) contribute newtons, not round-off
    _, undamped_force, undamped_torque, _ = _reference(damped=False)
    assert np.abs(body_force - undamped_force).max() > 1.0            # 2.5 N
    assert np.abs(torque_body - undamped_torque).max() > 0.5          # 0.9 N m
