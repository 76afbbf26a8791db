"""The vehicle the controller assumes: a UAV carrying cameras (``mysim_jax/control/build.py``).

Mass ``M = m_uav + Σ m_c``; centre of mass ``r_c = Σ m_c d_c / M`` (UAV body frame); inertia
about the UAV body origin, cameras at their start attitude ``R_c``:
``J = J_uav + Σ (R_c J_c R_cᵀ + m_c (|d_c|² I − d_c d_cᵀ))`` (parallel-axis theorem). Two
fixed cameras, turned and offset along all three axes so that every entry of the
parallel-axis term is non-zero; reference written with SciPy rotations.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict

pytestmark = pytest.mark.float64

J_UAV = np.array([1.4e-4, 1.5e-4, 2.17e-4])
CAMERAS = [  # name, offset (UAV frame), rotation vector (camera -> UAV), mass, principal inertia
    ("front", np.array([0.03, 0.01, -0.03]), np.array([0.2, -0.4, 0.3]), 0.02, np.array([2.2e-6, 4.8e-6, 5.7e-6])),
    ("side", np.array([-0.01, 0.04, -0.02]), np.array([-0.5, 0.1, 0.9]), 0.035, np.array([3.0e-6, 6.0e-6, 8.0e-6])),
]


def test_controller_mass_centre_and_inertia_with_cameras():
    cams = []
    for name, offset, rotvec, mass, inertia in CAMERAS:
        x, y, z, w = Rotation.from_rotvec(rotvec).as_quat()
        cams.append({"name": name, "mount": "fixed", "offset": offset.tolist(), "quat": [w, x, y, z],
                     "mass": mass, "inertia": inertia.tolist()})
    raw = {
        "name": "vehicle",
        "sim": {"t_end": 1.0, "dt": 1e-3, "output_dt": 1e-3, "integrator": "rk4", "precision": "float64"},
        "bodies": [{"name": "uav0", "mass": 0.28, "inertia": J_UAV.tolist(), "pos": [0.0, 0.0, 1.0]}],
        "quadrotors": [{"body": "uav0", "reference": {"center": [0.0, 0.0, 1.0]}, "cameras": cams}],
    }
    _, params, _ = build(config_from_dict(raw, "test"))
    cp = params.controller
    total = 0.28 + sum(c[3] for c in CAMERAS)
    com = sum(c[3] * c[1] for c in CAMERAS) / total
    inertia = np.diag(J_UAV)
    for _, d, rotvec, m, j in CAMERAS:
        r = Rotation.from_rotvec(rotvec).as_matrix()
        inertia = inertia + r @ np.diag(j) @ r.T + m * (d @ d * np.eye(3) - np.outer(d, d))
    # measured max abs errors: 0 (same arithmetic); tolerances a few ulp of each quantity
    np.testing.assert_allclose(float(cp.mass[0]), total, rtol=1e-15)
    np.testing.assert_allclose(np.asarray(cp.com_offset[0]), com, rtol=0, atol=1e-17)
    np.testing.assert_allclose(np.asarray(cp.inertia[0]), inertia, rtol=0, atol=1e-18)
    # the cameras' parallel-axis terms are a sizeable part of the vehicle inertia (products too)
    assert np.abs(inertia - np.diag(J_UAV)).max() > 1e-5 and abs(inertia[0, 2]) > 1e-5
