"""Explicit stability limit of a nonlinear contact (exponent n ≠ 1) against the closed form.

A contact in the ramp region behaves like a spring-damper along the line of centres with
the linearised stiffness ``d(k δⁿ)/dδ = n k δⁿ⁻¹``, taken at the damping depth p (the
check's documented choice), and damping c, joining the two masses (the ground: infinite
mass). For semi-implicit Euler the oscillator ``ẍ = −ω²x − ηẋ`` with
``ω² = n k pⁿ⁻¹ (1/m_a + 1/m_b)``, ``η = c (1/m_a + 1/m_b)`` is stable for
``h < 2(√(1 + ζ²) − ζ)/ω``, ``ζ = η/(2ω)`` (eigenvalues of its amplification matrix on
the unit circle). The paper's scenes use n = 1, where a missing factor n is invisible.
"""

import math

import numpy as np
import pytest

from mysim_jax.build import build
from mysim_jax.config.scene import config_from_dict
from mysim_jax.contact.build import contact_stable_step

pytestmark = pytest.mark.float64

K, N, C, P = 1e9, 1.5, 800.0, 1e-4
MASSES = {"a": 0.2, "b": 0.5, "c": 0.05}


def _sie_limit(inv_mass):
    omega = math.sqrt(N * K * P ** (N - 1.0) * inv_mass)
    zeta = C * inv_mass / (2.0 * omega)
    return 2.0 * (math.sqrt(1.0 + zeta * zeta) - zeta) / omega


def test_nonlinear_contact_limit_is_the_closed_form():
    raw = {
        "name": "contact_limit",
        "sim": {"t_end": 0.01, "dt": 1e-4, "output_dt": 1e-4, "integrator": "tsit5", "precision": "float64"},
        "points": [{"name": n, "mass": m, "pos": [i * 1.0, 0.0, 0.5]} for i, (n, m) in enumerate(MASSES.items())],
        "contact": {"stiffness": K, "exponent": N, "damping": C, "damping_depth": P,
                    "groups": [{"name": "pair", "members": ["a", "b"], "radius": 0.03},
                               {"name": "dust", "members": ["c"], "radius": 0.01}],
                    "pairs": [["pair", "pair"], ["dust", "ground"]]},
    }
    config = config_from_dict(raw, "test")
    scene, params, _ = build(config)
    limit, what = contact_stable_step("semi_implicit_euler", config.contact, scene.contact,
                                      np.asarray(params.point_mass), np.asarray(params.body_mass))
    pair = _sie_limit(1 / MASSES["a"] + 1 / MASSES["b"])       # 1.49e-4 s
    ground = _sie_limit(1 / MASSES["c"])                        # 7.39e-5 s: the light sphere on the ground
    assert ground < pair
    # measured relative error: 2.1e-13 (the bisection accepts a spectral radius up to 1 + 1e-12)
    assert limit == pytest.approx(ground, rel=2e-12), (limit, ground)
    assert "c|ground" in what
    # the damping matters at these constants (ζ = 0.46): without it the limit would be
    # 2/ω = 1.16e-4 s, 1.56x larger
    assert 2.0 / math.sqrt(N * K * P ** (N - 1.0) / MASSES["c"]) > 1.5 * ground
