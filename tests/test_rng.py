"""Draws computed as one (mysim_jax/core/rng.py) are ``jax.random``'s draws, bit for bit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mysim_jax.core import rng

SHAPES = [(), (3,), (4, 3), (2, 2, 5), (1,)]
LOWS = [-1.0, np.array([0.0, -2.0, 5.0]), 0.5, np.full((2, 2, 5), -3.0), 2.0]
HIGHS = [1.0, np.array([1.0, 2.0, 5.5]), 0.75, np.full((2, 2, 5), 4.0), 2.0]   # the last: an empty range


def _separately(key, dtype):
    keys = jax.random.split(key, len(SHAPES))
    uniform = [jax.random.uniform(k, s, dtype, lo, hi) for k, s, lo, hi in zip(keys, SHAPES, LOWS, HIGHS)]
    normal = [jax.random.normal(k, s, dtype) for k, s in zip(keys, SHAPES)]
    return uniform, normal


def _together(key, dtype):
    keys = jax.random.split(key, len(SHAPES))
    return rng.uniform_each(keys, SHAPES, dtype, LOWS, HIGHS), rng.normal_each(keys, SHAPES, dtype)


@pytest.mark.parametrize("how", ["eager", "jit", "jit of vmap"])
def test_the_same_bits_as_jax_random(how):
    keys = jax.random.split(jax.random.PRNGKey(20261128), 16)
    if how == "eager":
        runs = [(_separately(k, jnp.float32), _together(k, jnp.float32)) for k in keys[:3]]
    elif how == "jit":
        sep, tog = jax.jit(_separately, static_argnums=1), jax.jit(_together, static_argnums=1)
        runs = [(sep(k, jnp.float32), tog(k, jnp.float32)) for k in keys[:3]]
    else:
        sep = jax.jit(jax.vmap(lambda k: _separately(k, jnp.float32)))
        tog = jax.jit(jax.vmap(lambda k: _together(k, jnp.float32)))
        runs = [(sep(keys), tog(keys))]
    for separately, together in runs:
        for a, b, shape in zip(jax.tree.leaves(separately), jax.tree.leaves(together), SHAPES * 2):
            a, b = np.asarray(a), np.asarray(b)
            assert a.shape == b.shape and a.shape[a.ndim - len(shape):] == shape
            np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))


def test_one_key_per_shape_and_the_partitionable_layout_are_required():
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    with pytest.raises(ValueError, match="3 shapes for 2 keys"):
        rng.normal_each(keys, [(1,), (2,), (3,)])
    with jax.threefry_partitionable(False):
        with pytest.raises(RuntimeError, match="jax_threefry_partitionable"):
            rng.uniform_each(keys, [(1,), (2,)])


@pytest.mark.parametrize("name, init", [("he_normal", jax.nn.initializers.he_normal()),
                                        ("lecun_normal", jax.nn.initializers.lecun_normal()),
                                        ("normal", jax.nn.initializers.normal(1e-3))])
def test_kernels_drawn_as_matrices_equal_the_initialisers_own(name, init):
    """The detector's convolution kernels (mysim_jax/perception/detect) use rng.as_matrix."""
    for i, shape in enumerate([(3, 3, 16, 32), (1, 1, 48, 4), (3, 3, 3, 24), (5, 7)]):
        key = jax.random.PRNGKey(100 + i)
        a, b = np.asarray(init(key, shape)), np.asarray(rng.as_matrix(init)(key, shape))
        assert a.shape == b.shape == shape
        np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32), err_msg=f"{name} {shape}")
