"""A rigid body's inertia must be positive definite: a zero principal moment is rejected.

A zero principal moment (a point mass or an ideal rod about its axis) makes ``J``
singular: ``J⁻¹`` in the Newton-Euler equations is infinite. Such an inertia passes the
triangle inequality (``I₃ ≤ I₁ + I₂`` with ``I₁ = 0``, ``I₂ = I₃``), so the positive-definite
check is what stops it, also when the zero moment hides in a full matrix.
"""

import pytest

from mysim_jax.config.scene import ConfigError, config_from_dict


def _body(inertia):
    return {
        "name": "inertia",
        "sim": {"t_end": 1.0, "dt": 1e-3, "output_dt": 1e-3},
        "bodies": [{"name": "rod", "mass": 1.0, "inertia": inertia}],
    }


@pytest.mark.parametrize("inertia", [
    [0.0, 1.0, 1.0],                                        # zero moment on a diagonal
    [[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]],    # eigenvalues 0, 2, 2
])
def test_zero_principal_moment_is_rejected(inertia):
    with pytest.raises(ConfigError, match=r"bodies\.0\.inertia: .*positive definite"):
        config_from_dict(_body(inertia), "scene.yaml")


def test_a_thin_but_solid_inertia_is_accepted():
    config_from_dict(_body([1e-9, 1.0, 1.0]), "scene.yaml")
