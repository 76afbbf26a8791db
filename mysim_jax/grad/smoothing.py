"""Zeroth-order gradient estimates by Gaussian smoothing, with antithetic samples.

The Gaussian smoothing of ``f`` at scale ``sigma`` is ``f_sigma(x) = E[f(x + sigma e)]``,
``e ~ N(0, I)``; its gradient is estimated from ``N`` antithetic pairs as

    g = 1 / (2 N sigma) * sum_i (f(x + sigma e_i) - f(x - sigma e_i)) e_i

(unbiased for ``grad f_sigma``; for a quadratic ``f``, ``grad f_sigma = grad f`` and
the estimate converges to it as ``N`` grows). It needs values only, so it is defined
through contact and switches where a first-order gradient may be biased (Suh et al.,
ICML 2022) and is the reference the gradient map compares autodiff against.

:func:`smoothed_gradient` is the estimator for any ``f``; :func:`directions` and
:func:`antithetic_estimate` are its two halves for callers that evaluate the perturbed
points themselves (batched rollouts). :func:`linear_reference` is what the same samples
give for an exactly linear function of gradient ``g``: the cosine an estimate can reach
with ``N`` samples in ``d`` dimensions (about ``1 / sqrt(1 + (d + 1) / N)``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def check_smoothing(sigma: float, n_pairs: int) -> None:
    """ValueError unless ``sigma > 0`` and ``n_pairs >= 1``."""
    if not sigma > 0.0:
        raise ValueError(f"smoothing sigma: {sigma!r}, expected > 0")
    if not (isinstance(n_pairs, int) and n_pairs >= 1):
        raise ValueError(f"smoothing pairs: {n_pairs!r}, expected an int >= 1")


def directions(key, n_pairs: int, shape, dtype=jnp.float32):
    """``(n_pairs, *shape)`` standard normal directions ``e_i``."""
    return jax.random.normal(key, (n_pairs, *tuple(shape)), dtype)


def antithetic_estimate(f_plus, f_minus, eps, sigma: float):
    """The estimate from the values ``f(x + sigma e_i)`` and ``f(x - sigma e_i)``
    ``(n_pairs,)`` and the directions ``eps`` ``(n_pairs, *shape)``: shape ``shape``."""
    diff = (f_plus - f_minus) / (2.0 * sigma)
    return jnp.tensordot(diff, eps, axes=(0, 0)) / eps.shape[0]


def smoothed_gradient(f, x, key, sigma: float, n_pairs: int):
    """The antithetic Gaussian-smoothing estimate of ``grad f(x)`` (module docstring) from
    ``n_pairs`` pairs drawn from ``key``; ``f`` maps an array shaped like ``x`` to a
    scalar and is evaluated with ``jax.vmap``."""
    check_smoothing(sigma, n_pairs)
    x = jnp.asarray(x)
    eps = directions(key, n_pairs, x.shape, x.dtype)
    values = jax.vmap(f)(jnp.concatenate([x + sigma * eps, x - sigma * eps]))
    return antithetic_estimate(values[:n_pairs], values[n_pairs:], eps, sigma)


def linear_reference(g, eps):
    """The estimate the directions ``eps`` ``(n_pairs, *shape)`` give for the linear
    function ``x -> g . x``: ``mean_i (g . e_i) e_i``."""
    proj = jnp.tensordot(eps, g, axes=g.ndim)
    return jnp.tensordot(proj, eps, axes=(0, 0)) / eps.shape[0]


def cosine(a, b, tiny: float = 1e-30):
    """Cosine of the angle between two arrays of one shape (0 when either is zero)."""
    a, b = jnp.ravel(a), jnp.ravel(b)
    return jnp.sum(a * b) / jnp.maximum(jnp.linalg.norm(a) * jnp.linalg.norm(b), tiny)
