"""Several independent random draws computed as one: ``jax.random``'s values, bit for bit.

A program that draws ``n`` arrays from ``n`` keys (``jax.random.uniform(keys[i], shape_i)``)
contains ``n`` copies of the Threefry hash, each a loop that XLA compiles separately on
the CPU, and under ``jax.vmap`` each adds noticeably to the program's compile time. The
functions here draw them in one call, ``jax.vmap`` over the keys of a flat draw as long
as the largest shape, and cut each array out of its row. The values are
``jax.random``'s own: with JAX's partitionable Threefry (``jax_threefry_partitionable``,
the default since JAX 0.5) element ``j`` of a draw depends only on its key and ``j``, so
a shape's draw is the first ``size`` elements of any longer flat draw from the same key
(``tests/test_rng.py`` checks the draws against ``jax.random``'s, eagerly, jitted and
vmapped; the functions refuse to run when the setting is off). Arithmetic on the draws
inside a larger program may still round differently after the change, as after any
change that makes XLA fuse a program differently.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp


def _check_partitionable() -> None:
    if not jax.config.jax_threefry_partitionable:
        raise RuntimeError("mysim_jax.core.rng needs jax_threefry_partitionable=True (JAX's default): with the "
                           "older Threefry layout a short draw is not the start of a longer one")


def _rows(kind, keys, shapes, dtype):
    _check_partitionable()
    shapes = [tuple(s) for s in shapes]
    if len(shapes) != keys.shape[0]:
        raise ValueError(f"{len(shapes)} shapes for {keys.shape[0]} keys")
    longest = max([1] + [math.prod(s) for s in shapes])
    rows = jax.vmap(lambda k: kind(k, (longest,), dtype))(keys)
    return [rows[i, :math.prod(s)].reshape(s) for i, s in enumerate(shapes)]


def uniform_each(keys, shapes, dtype=float, minvals=None, maxvals=None) -> list:
    """``[jax.random.uniform(keys[i], shapes[i], dtype, minvals[i], maxvals[i]) for i]`` as one
    draw. ``keys`` ``(n, 2)`` (raw ``uint32`` keys, e.g. ``jax.random.split(key, n)``);
    ``minvals``/``maxvals`` sequences of ``n`` values broadcastable to their shapes
    (default 0 and 1)."""
    dtype = jax.dtypes.canonicalize_dtype(dtype)
    unit = _rows(jax.random.uniform, keys, shapes, dtype)
    n = len(unit)
    minvals = [0.0] * n if minvals is None else list(minvals)
    maxvals = [1.0] * n if maxvals is None else list(maxvals)
    return [_scale(u, jnp.asarray(lo, dtype), jnp.asarray(hi, dtype)) for u, lo, hi in zip(unit, minvals, maxvals)]


@jax.jit
def _scale(unit, low, high):
    # jax.random.uniform's own arithmetic on its [0, 1) floats, compiled as it compiles it
    # (eagerly, the product and the sum would round separately)
    return jax.lax.max(jnp.broadcast_to(low, unit.shape), unit * (high - low) + low)


def normal_each(keys, shapes, dtype=float) -> list:
    """``[jax.random.normal(keys[i], shapes[i], dtype) for i]`` as one draw (``keys`` as in
    :func:`uniform_each`)."""
    return _rows(jax.random.normal, keys, shapes, jax.dtypes.canonicalize_dtype(dtype))


def as_matrix(init):
    """A convolution kernel initialiser that draws the kernel ``(..., in, out)`` as the
    ``(fan_in, out)`` matrix it multiplies with: the same values as ``init`` on the full
    shape (a draw in C order, and the same fan-in) for fan-in scaled and fixed-scale
    initialisers (``he_normal``, ``lecun_normal``, ``normal``), not for fan-out or fan-avg
    ones. A rank-2 draw compiles faster than a rank-4 one on the CPU."""
    def matrix_init(key, shape, dtype=jnp.float32):
        shape = tuple(shape)
        return init(key, (math.prod(shape[:-1]), shape[-1]), dtype).reshape(shape)
    return matrix_init
