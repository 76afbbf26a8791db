"""Contact laws (mysim_jax/contact/law.py): Hermite step, normal force, C¹ friction law,
smooth variants, and safe gradients at zero penetration / zero slip."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.contact import law

K, N_EXP, C, P = 1e8, 1.0, 1e4, 1e-4            # Table collision_module
MU_S, MU_D, V_S, V_D = 0.04, 0.03, 0.01, 0.1


def _mu(v):
    return law.friction_coefficient(v, MU_S, MU_D, V_S, V_D)


@pytest.mark.float64
def test_hermite_step_is_c1_with_the_end_values():
    x = jnp.linspace(-1.0, 3.0, 4001)
    h = law.hermite_step(x, 0.0, 2.0, 2.0, 5.0)
    assert float(h[0]) == 2.0 and float(h[-1]) == 5.0
    assert float(law.hermite_step(1.0, 0.0, 2.0, 2.0, 5.0)) == pytest.approx(3.5)   # midpoint
    slope = jax.jit(jax.vmap(jax.grad(lambda t: law.hermite_step(t, 0.0, 2.0, 2.0, 5.0))))
    # zero slope at both ends (C¹ against the constant pieces), monotone in between
    np.testing.assert_allclose(slope(jnp.array([0.0, 2.0, -0.5, 2.5])), 0.0, atol=1e-12)
    assert np.all(np.diff(np.asarray(h)) >= 0.0)


@pytest.mark.float64
def test_friction_law_is_continuous_c1_and_keeps_the_paper_values():
    assert float(_mu(0.0)) == 0.0
    assert float(_mu(V_S)) == pytest.approx(MU_S, rel=1e-12)      # peaks at mu_s at v_s
    assert float(_mu(V_D)) == pytest.approx(MU_D, rel=1e-12)      # settles to mu_d at v_d
    assert float(_mu(5.0)) == pytest.approx(MU_D, rel=1e-12)
    dmu = jax.jit(jax.grad(_mu))
    for v in (V_S, V_D):        # value and slope continuous across both branch points
        for eps in (1e-9,):
            assert abs(float(_mu(v + eps) - _mu(v - eps))) < 1e-9
            assert abs(float(dmu(v + eps) - dmu(v - eps))) < 1e-5
        assert abs(float(dmu(v))) < 1e-6
    # slope at zero slip: the linear (viscous-like) regularisation 1.5 mu_s / v_s
    assert float(dmu(0.0)) == pytest.approx(1.5 * MU_S / V_S, rel=1e-12)
    v = jnp.linspace(0.0, 0.3, 30001)
    mu = np.asarray(jax.vmap(_mu)(v))
    grad = np.asarray(jax.vmap(dmu)(v))
    dv = float(v[1] - v[0])
    # no jumps anywhere: steps bounded by the largest slope (3 mu_s / 2 v_s, at 0) and the
    # slope's steps by the largest curvature (3 mu_s / v_s², just below v_s)
    assert np.max(np.abs(np.diff(mu))) <= 1.001 * 1.5 * MU_S / V_S * dv
    assert np.max(np.abs(np.diff(grad))) <= 1.001 * 3.0 * MU_S / V_S ** 2 * dv
    assert mu.max() == pytest.approx(MU_S, rel=1e-6)


def _paper_printed_mu(v):
    """Eq. collsion miu-v exactly as printed in the paper (for the record: discontinuous)."""
    a = abs(v)
    if a > V_D:
        return MU_D * np.sign(v)
    if a >= V_S:
        s = (a - V_S) / (V_D - V_S)
        return -(MU_D + (MU_S - MU_D) * s * s * (3 - 2 * s)) * np.sign(v)
    u = (v + V_D) / (2 * V_D)
    return 2 * MU_D * (3 * u * u - 2 * u ** 3 - 0.5)


def test_the_printed_friction_formula_jumps_and_ours_does_not():
    eps = 1e-12
    jumps_printed = [abs(_paper_printed_mu(v + eps) - _paper_printed_mu(v - eps)) for v in (V_S, V_D)]
    assert min(jumps_printed) > 1e-2                       # both branch points jump
    with jax.enable_x64(True):
        jumps_ours = [abs(float(_mu(v + eps) - _mu(v - eps))) for v in (V_S, V_D)]
    assert max(jumps_ours) < 1e-9
    # where the printed law is well defined and continuous (fast slip) it agrees
    with jax.enable_x64(True):
        assert float(_mu(0.5)) == pytest.approx(_paper_printed_mu(0.5))


def test_friction_per_speed_is_mu_over_v_and_finite_at_zero_slip():
    with jax.enable_x64(True):
        speeds = jnp.array([1e-6, 0.005, V_S, 0.05, V_D, 1.0])
        g = law.friction_per_speed(speeds ** 2, MU_S, MU_D, V_S, V_D)
        np.testing.assert_allclose(g * speeds, _mu(speeds), rtol=1e-12)
        val, grad = jax.value_and_grad(lambda s2: law.friction_per_speed(s2, MU_S, MU_D, V_S, V_D))(0.0)
        assert float(val) == pytest.approx(1.5 * MU_S / V_S) and np.isfinite(float(grad))


@pytest.mark.float64
def test_normal_force_sharp_is_the_paper_law_with_a_dissipative_damper():
    f = lambda d, r: float(law.normal_force_sharp(d, r, K, N_EXP, C, P))  # noqa: E731
    assert f(-1e-3, -5.0) == 0.0 and f(0.0, 3.0) == 0.0              # no contact, no force
    assert f(1e-5, 0.0) == pytest.approx(K * 1e-5)                    # elastic k·δ^n
    ramp = C * 0.1 ** 2 * (3 - 0.2)                                   # STEP at δ = p/10
    assert f(1e-5, 2.0) == pytest.approx(K * 1e-5 + ramp * 2.0)       # approaching: more force
    assert f(1e-5, -2.0) == pytest.approx(K * 1e-5 - ramp * 2.0)      # separating: less
    assert f(2e-4, 1.0) == pytest.approx(K * 2e-4 + C)                # full damping beyond p
    assert f(1e-5, -1e3) == 0.0                                       # clipped: never pulls
    # continuous at first touch for any approach speed (the damper ramps from zero)
    assert f(1e-12, 10.0) < 1e-3
    # the damper never feeds energy in: (k δ^n - f) · dδ/dt <= 0
    rng = np.random.default_rng(0)
    d = rng.uniform(-1e-4, 5e-4, 2000)
    r = rng.uniform(-20.0, 20.0, 2000)
    fs = np.asarray(law.normal_force_sharp(d, r, K, N_EXP, C, P))
    elastic = K * np.maximum(d, 0.0)
    assert np.all((elastic - fs) * r <= 1e-9) and np.all(fs >= 0.0)


@pytest.mark.float64
def test_smooth_normal_force_converges_to_sharp_and_vanishes_apart():
    d = jnp.array([5e-5, 1e-4, 3e-4])
    r = jnp.array([1.0, -0.5, 2.0])
    sharp = law.normal_force_sharp(d, r, K, N_EXP, C, P)
    for width, rtol in ((1e-6, 2e-2), (1e-8, 2e-4)):
        smooth = law.normal_force_smooth(d, r, K, N_EXP, C, P, width)
        np.testing.assert_allclose(smooth, sharp, rtol=rtol)
    far = law.normal_force_smooth(jnp.array([-1e-4, -1e-3]), jnp.array([1.0, 1.0]), K, N_EXP, C, P, 1e-6)
    assert float(jnp.max(far)) < 1e-30
    # smooth (C^1 and beyond) through first touch: no slope jump at δ = 0
    df = jax.jit(jax.grad(lambda x: law.normal_force_smooth(x, 0.0, K, N_EXP, C, P, 1e-6)))
    assert abs(float(df(1e-12)) - float(df(-1e-12))) < 1e-3 * K


@pytest.mark.parametrize("precision", ["float32", "float64"])
@pytest.mark.parametrize("model", ["sharp", "smooth"])
def test_gradients_are_finite_at_touch_and_apart(precision, model):
    with jax.enable_x64(precision == "float64"):
        def f(depth, rate, k, n, c, p):
            if model == "smooth":
                return law.normal_force_smooth(depth, rate, k, n, c, p, 1e-6)
            return law.normal_force_sharp(depth, rate, k, n, c, p)
        grad = jax.jit(jax.grad(f, argnums=(0, 1, 2, 3, 4, 5)))
        for depth in (0.0, -1e-3, 1e-5, -1.0):
            for exponent in (1.0, 1.5):
                g = grad(depth, 1.0, K, exponent, C, P)
                assert all(np.isfinite(float(x)) for x in g), (depth, exponent, g)
        g = jax.grad(lambda s2: law.friction_per_speed(s2, MU_S, MU_D, V_S, V_D))(0.0)
        assert np.isfinite(float(g))
