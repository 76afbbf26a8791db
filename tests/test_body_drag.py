"""Linear body drag of a tilted quadrotor: ``F = −R D Rᵀ v`` with ``D = diag(drag)`` in
body axes (the effect ``mysim_jax/effects/body_drag.py``).

The drag coefficients belong to the body axes (a quadrotor is draggier broadside than
edge-on), so the world velocity is taken into the body frame, scaled, and the force
taken back. The existing terminal-velocity test flies level with drag equal on x and y,
where the frames cannot be told apart; here the body is tilted ~50° about a skew axis
and the coefficients differ per axis. Reference: SciPy rotation matrices.
"""

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.effects.body_drag import BODY_DRAG

pytestmark = pytest.mark.float64

DRAG = np.array([0.15, 0.4, 0.9])                 # N s/m, body x, y, z
VEL = np.array([1.2, -0.7, 0.5])                  # m/s, world
ROT = Rotation.from_rotvec(0.9 * np.array([0.3, 0.8, -0.52]))


def test_drag_acts_in_body_axes_of_a_tilted_body():
    x, y, z, w = ROT.as_quat()
    raw = {
        "name": "drag",
        "sim": {"t_end": 1.0, "dt": 1e-3, "output_dt": 1e-3, "integrator": "rk4", "precision": "float64"},
        "bodies": [{"name": "uav0", "mass": 0.28, "inertia": [1.4e-4, 1.4e-4, 2.17e-4], "pos": [0.0, 0.0, 1.0],
                    "quat": [w, x, y, z], "vel": VEL.tolist()}],
        "quadrotors": [{"body": "uav0", "controller": None, "drag": DRAG.tolist()}],
    }
    scene, params, state = build(config_from_dict(raw, "test"))
    assert [name for name, _ in scene.effects] == ["body_drag"]
    (name, stage), = BODY_DRAG.stages(BODY_DRAG.static(scene))
    loads = jax.jit(lambda ph: stage(scene, params, ph, None, None))(state.phys)
    rot = ROT.as_matrix()
    expected = -rot @ np.diag(DRAG) @ rot.T @ VEL
    # measured max abs error: 1.1e-16 N on a force of ~1.2 N
    np.testing.assert_allclose(np.asarray(loads.body_force[0]), expected, rtol=0, atol=1e-15)
    # the body-axis reading matters here: world-axis drag would be off by 0.56 N
    assert np.abs(expected + DRAG * VEL).max() > 0.1
    np.testing.assert_array_equal(np.asarray(loads.body_torque[0]), 0.0)
