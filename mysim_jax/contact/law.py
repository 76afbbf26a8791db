"""The contact laws: IMPACT-style normal force, Hermite step, C¹ Stribeck-like friction.

All functions are element-wise on arrays and safe under autodiff (finite values and
gradients at zero penetration and zero slip, also with respect to the exponent n).
The two models implement the small :class:`ContactLaw` interface (``SharpLaw``,
``SmoothLaw``), looked up from the static scene in :data:`CONTACT_LAWS`.

Normal force (paper Eq. compact_force)
--------------------------------------
In terms of the penetration ``δ = r_i + r_j − |x_j − x_i|`` (positive when the spheres
overlap) and its rate ``dδ/dt`` (positive while they approach)::

    f = max(0, k·δⁿ + STEP(δ; 0, 0, p, c)·dδ/dt)        for δ > 0,   0 otherwise

pushing the spheres apart along the line of centres. The damping coefficient ramps with
the cubic Hermite ``STEP`` from 0 at first touch to ``c`` at penetration ``p``, so the
force is continuous at first touch (no impulse from the damper). The paper writes the
same function in terms of the *gap* (MSC Adams' IMPACT), where the damping term carries
a minus sign because the gap shrinks while the bodies approach; read literally with δ as
penetration that minus sign would pull on approach and push on separation, i.e. feed
energy in. With the sign here the damper always takes energy out: the energy of the
contact (kinetic + k·δⁿ⁺¹/(n+1)) changes at the rate ``(k·δⁿ − f)·dδ/dt`` ≤ 0, both
while the damper acts (``−c·STEP·(dδ/dt)²``) and while ``max`` clips the force to zero
(which only happens when ``dδ/dt < 0``). The tests check that no bounce leaves with more
energy than it came in with.

Friction (paper Eq. collsion miu-v, made continuous)
----------------------------------------------------
The printed μ(v_t) has three branches that do not meet: the slow branch uses μ_d and v_d
where its neighbours use μ_s and v_s, and the middle branch has μ_s and μ_d swapped and a
stray minus sign, so μ jumps at |v_t| = v_s and at v_d. Its intent (the curve of the
paper's Fig. collsion miu-v, and MSC Adams' contact friction it follows) is kept here with
Hermite steps that meet with zero slope, which makes μ(v) odd and C¹::

    |v| < v_s:          μ = STEP(v; −v_s, −μ_s, v_s, μ_s) = μ_s·(3x − x³)/2,  x = v/v_s
    v_s ≤ |v| ≤ v_d:    μ = STEP(|v|; v_s, μ_s, v_d, μ_d)·sign(v)
    |v| > v_d:          μ = μ_d·sign(v)

The friction force on body j, opposing the tangential slip ``v_t`` of j's contact point
relative to i's, is ``−μ(|v_t|)·f·v_t/|v_t|``. Since μ is linear near zero this equals
``−f·g(|v_t|)·v_t`` with ``g(v) = μ(v)/v = μ_s(3 − x²)/(2 v_s)`` below v_s — a smooth
function of ``v_t`` through zero slip, with no direction to choose at ``v_t = 0``; it is
evaluated in that form (same values, exact derivatives).

Smooth variant (``model: smooth``)
----------------------------------
For gradients through contact events every kink is replaced by a softplus of width ε
(``smoothing.depth``): the penetration ``δ_ε = ε·softplus(δ/ε)``, and the outer max by
``σ(δ/ε)·w·softplus((k·δ_εⁿ + STEP(δ_ε)·dδ/dt)/w)`` with ``w = k·εⁿ`` (the elastic force at
depth ε). The logistic gate σ makes the force vanish (exponentially) out of contact and
is C^∞ at first touch. Deep in contact (δ ≫ ε) it equals the sharp law up to
``w·exp(−|·|/w)``. The slip speed is regularised to ``√(|v_t|² + v_ε²)``
(``smoothing.velocity``) before μ and g are evaluated.
"""

from __future__ import annotations

import abc

import jax
import jax.numpy as jnp

from mysim_jax.core.contact_types import ContactParams


def hermite_step(x, x0, h0, x1, h1):
    """Cubic Hermite step (MSC Adams' STEP): ``h0`` for x ≤ x0, ``h1`` for x ≥ x1, and
    ``h0 + (h1 − h0)·s²(3 − 2s)`` with ``s = (x − x0)/(x1 − x0)`` between. C¹ (zero slope at
    both ends)."""
    s = jnp.clip((x - x0) / (x1 - x0), 0.0, 1.0)
    return h0 + (h1 - h0) * s * s * (3.0 - 2.0 * s)


def _safe_pow(x, n):
    """``x**n`` for x ≥ 0 with finite gradients in x and n at x = 0 (value 0 there)."""
    positive = x > 0.0
    safe = jnp.where(positive, x, 1.0)
    return jnp.where(positive, safe ** n, 0.0)


def normal_force_sharp(depth, depth_rate, stiffness, exponent, damping, damping_depth):
    """The paper's law: ``max(0, k·δⁿ + STEP(δ; 0, 0, p, c)·dδ/dt)`` for δ > 0, else 0."""
    pen = jnp.maximum(depth, 0.0)
    elastic = stiffness * _safe_pow(pen, exponent)
    damper = hermite_step(pen, 0.0, 0.0, damping_depth, damping) * depth_rate
    return jnp.where(depth > 0.0, jnp.maximum(elastic + damper, 0.0), 0.0)


def normal_force_smooth(depth, depth_rate, stiffness, exponent, damping, damping_depth, width):
    """Softplus-smoothed law of width ``width`` [m] (module docstring); C^∞ in δ and dδ/dt."""
    pen = width * jax.nn.softplus(depth / width)
    elastic = stiffness * _safe_pow(pen, exponent)   # pen > 0 unless softplus underflows
    damper = hermite_step(pen, 0.0, 0.0, damping_depth, damping) * depth_rate
    force_width = stiffness * width ** exponent
    gate = jax.nn.sigmoid(depth / width)
    return gate * force_width * jax.nn.softplus((elastic + damper) / force_width)


def friction_coefficient(speed, mu_static, mu_dynamic, v_static, v_dynamic):
    """|μ| at slip speed ``speed`` ≥ 0 (the C¹ law of the module docstring)."""
    x = speed / v_static
    slow = 0.5 * mu_static * x * (3.0 - x * x)
    return jnp.where(speed < v_static, slow,
                     hermite_step(speed, v_static, mu_static, v_dynamic, mu_dynamic))


def friction_per_speed(speed_sq, mu_static, mu_dynamic, v_static, v_dynamic):
    """``g = μ(v)/v`` as a function of the squared slip speed ``v²`` (finite at v = 0).

    Below ``v_static`` it is the polynomial ``μ_s(3 − v²/v_s²)/(2 v_s)`` (no square root,
    exact gradients through zero slip); above, ``μ(v)/v`` with v ≥ v_s > 0.
    """
    slow_branch = speed_sq < v_static * v_static
    slow = 0.5 * mu_static * (3.0 - speed_sq / (v_static * v_static)) / v_static
    speed = jnp.sqrt(jnp.where(slow_branch, v_static * v_static, speed_sq))
    fast = hermite_step(speed, v_static, mu_static, v_dynamic, mu_dynamic) / speed
    return jnp.where(slow_branch, slow, fast)


class ContactLaw(abc.ABC):
    """One contact model: the normal force and the slip speed the friction law sees.

    Both methods are pure and element-wise over contacts; ``cp`` holds the traced
    constants. The model is chosen from the static ``ContactScene.model`` when the
    pipeline is traced (:data:`CONTACT_LAWS`), never by a traced branch.
    """

    @abc.abstractmethod
    def normal_force(self, depth, depth_rate, cp: ContactParams):
        """Normal force magnitude ``(k,)`` [N] from penetration and its rate."""

    @abc.abstractmethod
    def slip_speed_sq(self, slip_sq, cp: ContactParams):
        """Squared slip speed ``(k,)`` fed to the friction law, from ``|v_t|²``."""


class SharpLaw(ContactLaw):
    """The paper's law exactly (:func:`normal_force_sharp`), unregularised slip."""

    def normal_force(self, depth, depth_rate, cp):
        return normal_force_sharp(depth, depth_rate, cp.stiffness, cp.exponent, cp.damping, cp.damping_depth)

    def slip_speed_sq(self, slip_sq, cp):
        return slip_sq


class SmoothLaw(ContactLaw):
    """Softplus-smoothed law of width ``smooth_depth`` (:func:`normal_force_smooth`), slip
    speed regularised to ``√(|v_t|² + smooth_velocity²)``."""

    def normal_force(self, depth, depth_rate, cp):
        return normal_force_smooth(depth, depth_rate, cp.stiffness, cp.exponent, cp.damping, cp.damping_depth,
                                   cp.smooth_depth)

    def slip_speed_sq(self, slip_sq, cp):
        return slip_sq + cp.smooth_velocity * cp.smooth_velocity


CONTACT_LAWS: dict[str, ContactLaw] = {"sharp": SharpLaw(), "smooth": SmoothLaw()}
