"""Baumgarte stabilisation: a violated joint relaxes as ``C̈ + 2αĊ + β²C = 0``, row by row.

The constraint solve asks for ``G u̇ = −Ġu − 2αĊ − β²C``; since ``C̈ = G u̇ + Ġu`` along
the true motion, every constraint row ``C_i(t)`` of a joint obeys the linear ODE
``C̈ + 2αĊ + β²C = 0`` exactly (in continuous time), whatever the bodies do. Its closed
form with the initial ``C(0)``, ``Ċ(0)`` is written out below for the under-damped,
critically damped and over-damped cases. The scene starts both joints violated, in
position and angle rows, with the bodies spinning (so ``Ċ(0) ≠ 0`` and the ``Ġu`` term
matters) and under gravity: a fixed joint from a body to a world anchor, and a universal
joint between two free bodies. RK4 at 1e-4 s in float64 integrates it; ``C(t)`` is
evaluated from the states by a NumPy re-implementation of the joint rows
(paper Appendix A) and compared with the closed form.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.sim import rollout

pytestmark = pytest.mark.float64

DT, N_STEPS, EVERY = 1e-4, 1500, 25           # 0.15 s, C(t) checked every 2.5 ms

# body A hangs from anchor "pivot" by a fixed joint; bodies B, C joined by a universal joint
ANCHOR_POS, ANCHOR_ROT = np.array([0.1, -0.2, 1.0]), Rotation.from_rotvec([0.3, -0.5, 0.2])
A_MARKER_POS, A_MARKER_ROT = np.array([0.12, 0.05, 0.2]), Rotation.from_rotvec([-0.4, 0.1, 0.6])
B_MARKER_POS, B_MARKER_ROT = np.array([0.0, 0.15, -0.1]), Rotation.from_rotvec([0.2, 0.3, -0.1])
C_MARKER_POS, C_MARKER_ROT = np.array([-0.1, 0.0, 0.12]), Rotation.from_rotvec([0.5, -0.2, 0.3])
# z_I ⊥ z_J at a satisfied universal joint: C's marker frame is B's turned 90° about x, then
# by an angle about the two free axes
U_REL = Rotation.from_rotvec([0.0, 0.0, 0.4]) * Rotation.from_rotvec([np.pi / 2, 0.0, 0.0]) \
    * Rotation.from_rotvec([0.0, 0.0, -0.7])
BODIES = {  # name: mass, inertia, velocity (world), angular velocity (body)
    "A": (1.2, [0.02, 0.03, 0.04], [0.05, -0.1, 0.08], [1.5, -2.0, 0.7]),
    "B": (0.8, [0.01, 0.012, 0.015], [0.3, 0.1, -0.2], [-1.0, 0.6, 2.2]),
    "C": (0.5, [0.004, 0.006, 0.008], [-0.2, 0.25, 0.1], [0.9, 1.8, -1.2]),
}


def _initial_poses():
    """World poses (position, Rotation) of A, B, C: each joint violated by a few mm and a
    few tens of mrad."""
    rot_a = ANCHOR_ROT * Rotation.from_rotvec([0.03, -0.02, 0.025]) * A_MARKER_ROT.inv()
    pos_a = ANCHOR_POS + np.array([0.008, -0.006, 0.005]) - rot_a.apply(A_MARKER_POS)
    rot_b, pos_b = Rotation.from_rotvec([0.7, -0.3, 1.1]), np.array([1.0, 0.5, 2.0])
    frame_i = rot_b * B_MARKER_ROT
    rot_c = frame_i * U_REL * Rotation.from_rotvec([0.02, 0.035, -0.01]) * C_MARKER_ROT.inv()
    pos_c = pos_b + rot_b.apply(B_MARKER_POS) + np.array([-0.004, 0.007, 0.006]) - rot_c.apply(C_MARKER_POS)
    return {"A": (pos_a, rot_a), "B": (pos_b, rot_b), "C": (pos_c, rot_c)}


def _wxyz(rot):
    x, y, z, w = rot.as_quat()
    return [w, x, y, z]


def _scene():
    poses = _initial_poses()
    markers = {"A": ("m", A_MARKER_POS, A_MARKER_ROT), "B": ("m", B_MARKER_POS, B_MARKER_ROT),
               "C": ("m", C_MARKER_POS, C_MARKER_ROT)}
    raw = {
        "name": "baumgarte",
        "sim": {"t_end": N_STEPS * DT, "dt": DT, "output_dt": DT, "integrator": "rk4", "precision": "float64"},
        "gravity": [0.0, 0.0, -9.81],
        "anchors": [{"name": "pivot", "pos": ANCHOR_POS.tolist(), "quat": _wxyz(ANCHOR_ROT)}],
        "bodies": [{"name": n, "mass": m, "inertia": i, "pos": poses[n][0].tolist(), "quat": _wxyz(poses[n][1]),
                    "vel": v, "angvel": w,
                    "markers": [{"name": markers[n][0], "pos": markers[n][1].tolist(),
                                 "quat": _wxyz(markers[n][2])}]}
                   for n, (m, i, v, w) in BODIES.items()],
        "joints": [{"name": "weld", "type": "fixed", "marker_i": "A.m", "marker_j": "pivot"},
                   {"name": "cross", "type": "universal", "marker_i": "B.m", "marker_j": "C.m"}],
    }
    return build(config_from_dict(raw, "test"))


def _constraint_rows(pos, rot, omega_world=None, vel=None):
    """Joint rows ``C`` (10,) and, given velocities, ``Ċ`` (10,) from NumPy poses.

    ``pos[n]``, ``rot[n]`` (3x3), ``omega_world[n]``, ``vel[n]`` per body name."""
    def frame(n, r_m, rot_m):
        return pos[n] + rot[n] @ r_m, rot[n] @ rot_m.as_matrix()

    p_ai, f_ai = frame("A", A_MARKER_POS, A_MARKER_ROT)
    f_pj = ANCHOR_ROT.as_matrix()
    p_bi, f_bi = frame("B", B_MARKER_POS, B_MARKER_ROT)
    p_cj, f_cj = frame("C", C_MARKER_POS, C_MARKER_ROT)
    c = np.concatenate([p_ai - ANCHOR_POS, [f_ai[:, 0] @ f_pj[:, 1], f_ai[:, 0] @ f_pj[:, 2], f_ai[:, 1] @ f_pj[:, 2]],
                        p_bi - p_cj, [f_bi[:, 2] @ f_cj[:, 2]]])
    if omega_world is None:
        return c
    w = omega_world

    def point_vel(n, r_m):
        return vel[n] + np.cross(w[n], rot[n] @ r_m)

    def axis_rate(n, f, k):
        return np.cross(w[n], f[:, k])

    c_dot = np.concatenate([
        point_vel("A", A_MARKER_POS),
        [axis_rate("A", f_ai, 0) @ f_pj[:, 1], axis_rate("A", f_ai, 0) @ f_pj[:, 2], axis_rate("A", f_ai, 1) @ f_pj[:, 2]],
        point_vel("B", B_MARKER_POS) - point_vel("C", C_MARKER_POS),
        [axis_rate("B", f_bi, 2) @ f_cj[:, 2] + f_bi[:, 2] @ axis_rate("C", f_cj, 2)],
    ])
    return c, c_dot


def closed_form(t, c0, c_dot0, alpha, beta):
    """Solution of ``C̈ + 2αĊ + β²C = 0`` with ``C(0) = c0``, ``Ċ(0) = c_dot0`` (per row)."""
    t = t[:, None]
    if alpha == beta:                                  # critical: repeated root −α
        return np.exp(-alpha * t) * (c0 + (c_dot0 + alpha * c0) * t)
    disc = np.sqrt(complex(alpha * alpha - beta * beta))
    lam1, lam2 = -alpha + disc, -alpha - disc
    a = (c_dot0 - lam2 * c0) / (lam1 - lam2)
    return np.real(a * np.exp(lam1 * t) + (c0 - a) * np.exp(lam2 * t))


@functools.lru_cache(maxsize=1)
def _simulator():
    """Built and compiled once for all cases (α, β are Params: no recompilation). Called
    from inside the float64 tests."""
    scene, params, state = _scene()
    run = jax.jit(lambda p: rollout(scene, p, state, N_STEPS, EVERY)[1].phys)

    def constraint_history(alpha, beta):
        p = params.replace(baumgarte_alpha=jnp.asarray(alpha), baumgarte_beta=jnp.asarray(beta))
        traj = jax.tree.map(np.asarray, run(p))
        out = []
        for k in range(traj.body_pos.shape[0]):
            rot = {n: Rotation.from_quat(np.roll(traj.body_quat[k, i], -1)).as_matrix() for i, n in enumerate("ABC")}
            out.append(_constraint_rows({n: traj.body_pos[k, i] for i, n in enumerate("ABC")}, rot))
        return np.array(out)

    return state, constraint_history


@pytest.mark.parametrize("alpha, beta", [(10.0, 40.0), (50.0, 50.0), (60.0, 30.0)],
                         ids=["under-damped", "critical", "over-damped"])
def test_violated_joints_relax_as_the_closed_form(alpha, beta):
    state, constraint_history = _simulator()
    phys = jax.tree.map(np.asarray, state.phys)
    rot = {n: Rotation.from_quat(np.roll(phys.body_quat[i], -1)).as_matrix() for i, n in enumerate("ABC")}
    c0, c_dot0 = _constraint_rows({n: phys.body_pos[i] for i, n in enumerate("ABC")}, rot,
                                  {n: rot[n] @ phys.body_angvel[i] for i, n in enumerate("ABC")},
                                  {n: phys.body_vel[i] for i, n in enumerate("ABC")})
    # every row starts violated and moving (mm, tens of mrad; cm/s, rad/s scale rates)
    assert np.abs(c0).min() > 1e-3 and np.abs(c_dot0).min() > 1e-3, (c0, c_dot0)
    t = np.arange(1, N_STEPS // EVERY + 1) * EVERY * DT
    expected = closed_form(t, c0, c_dot0, alpha, beta)
    measured = constraint_history(alpha, beta)
    # measured max error over all rows and times (|C| up to 0.06): 2.3e-13 (under-damped),
    # 6.3e-13 (critical), 1.3e-12 (over-damped)
    err = np.abs(measured - expected).max()
    assert err < 1e-11, err
