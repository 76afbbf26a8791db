"""The host-side joint check's closed-form Jacobian against the solver's autodiff one.

:mod:`mysim_jax.dynamics.joint_check` decides, before compiling, whether a scene's joints
can be solved, from a NumPy Jacobian written in closed form. The constraint solve
(:mod:`mysim_jax.dynamics.constraints`) differentiates the same rows with ``jax.jacfwd``.
The two derivations are independent; here they must agree on arbitrary (unassembled)
poses of two spinning bodies joined to each other and to an anchor by a fixed and a
universal joint, and the rank verdicts must follow.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, config_from_dict
from mysim_jax.dynamics.constraints import constraint_error
from mysim_jax.dynamics.joint_check import joint_jacobian, joint_problems
from mysim_jax.dynamics.quaternion import quat_from_rotvec, quat_mul

pytestmark = pytest.mark.float64


def _wxyz(rotvec):
    x, y, z, w = Rotation.from_rotvec(rotvec).as_quat()
    return [w, x, y, z]


def _raw(joints):
    rng = np.random.default_rng(3)
    bodies = []
    for name in ("A", "B"):
        bodies.append({
            "name": name, "mass": 1.0, "inertia": [0.02, 0.03, 0.04],
            "pos": rng.normal(size=3).tolist(), "quat": _wxyz(rng.normal(size=3)),
            "markers": [{"name": f"m{k}", "pos": rng.normal(scale=0.2, size=3).tolist(),
                         "quat": _wxyz(rng.normal(size=3))} for k in range(2)],
        })
    return {"name": "jac", "sim": {"t_end": 1e-3, "dt": 1e-3, "output_dt": 1e-3, "integrator": "rk4",
                                   "precision": "float64"},
            "anchors": [{"name": "pivot", "pos": [0.3, -0.1, 0.8], "quat": _wxyz([0.2, 0.4, -0.3])}],
            "bodies": bodies, "joints": joints}


JOINTS = [{"name": "weld", "type": "fixed", "marker_i": "A.m0", "marker_j": "pivot"},
          {"name": "cross", "type": "universal", "marker_i": "A.m1", "marker_j": "B.m0"}]


def test_closed_form_jacobian_matches_the_solvers_autodiff():
    config = config_from_dict(_raw(JOINTS), "jac")
    scene, params, state = build(config)
    phys = state.phys

    def rows(delta):
        delta = delta.reshape(-1, 6)
        moved = phys.replace(body_pos=phys.body_pos + delta[:, :3],
                             body_quat=quat_mul(phys.body_quat, quat_from_rotvec(delta[:, 3:])))
        return constraint_error(scene, params, moved)

    auto = np.asarray(jax.jit(jax.jacfwd(rows))(jnp.zeros(6 * scene.n_bodies)))
    closed = np.concatenate([joint_jacobian(config, j) for j in config.joints], axis=0)
    assert auto.shape == closed.shape == (10, 12)
    # measured max abs difference 3.3e-16 (entries up to 1)
    np.testing.assert_allclose(closed, auto, rtol=0, atol=5e-15)
    assert joint_problems(config) == []


def test_a_third_joint_that_repeats_one_is_reported_as_redundant():
    repeated = JOINTS + [{"name": "again", "type": "universal", "marker_i": "A.m1", "marker_j": "B.m0"}]
    with pytest.raises(ConfigError, match="'cross'.*'again'.*more than once"):
        build(config_from_dict(_raw(repeated), "jac"))
