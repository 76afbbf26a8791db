"""The straight-line Threefry lowering on the CPU (mysim_jax/xla_cpu.py) computes JAX's bits.

Checked two ways: the published known-answer vectors of Threefry-2x32 with 20 rounds
(Salmon et al., "Parallel random numbers: as easy as 1, 2, 3", SC 2011; the Random123
distribution's kat_vectors, which JAX's own tests use too), and a set of ``jax.random``
draws compared bit for bit with a child process that keeps JAX's default loop lowering.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mysim_jax.types  # noqa: F401  (installs the lowering, as every simulator program does)
from mysim_jax import xla_cpu

# (key, counter) -> output of threefry2x32_20
KNOWN_ANSWERS = [
    ((0x00000000, 0x00000000), (0x00000000, 0x00000000), (0x6B200159, 0x99BA4EFE)),
    ((0xFFFFFFFF, 0xFFFFFFFF), (0xFFFFFFFF, 0xFFFFFFFF), (0x1CB996FC, 0xBB002BE7)),
    ((0x13198A2E, 0x03707344), (0x243F6A88, 0x85A308D3), (0xC4923A9C, 0x483DF7A0)),
]

# the draws compared across the two lowerings: printed as JSON lists of uint32 / float bits
DRAWS = r"""
import json, sys
import jax, jax.numpy as jnp, numpy as np
import mysim_jax.types
from mysim_jax import xla_cpu
key = jax.random.PRNGKey(20261128)
keys = jax.random.split(key, 5)
out = {
    "installed": xla_cpu.installed(),
    "split": jax.random.split(key, 7),
    "fold_in": jax.random.fold_in(key, 12345),
    "bits": jax.random.bits(keys[0], (4, 3, 5)),
    "uniform": jax.random.uniform(keys[1], (33,), minval=-2.0, maxval=3.0),
    "normal": jax.random.normal(keys[2], (6, 7)),
    "vmapped_normal": jax.jit(jax.vmap(lambda k: jax.random.normal(k, (4, 3))))(jax.random.split(keys[3], 9)),
    "permutation": jax.random.permutation(keys[4], 50),
}
def bits(x):
    x = np.asarray(x)
    return (x.view(np.uint32) if x.dtype == np.float32 else x.astype(np.int64)).ravel().tolist()
print(json.dumps({k: (v if isinstance(v, bool) else bits(v)) for k, v in out.items()}))
"""


def _draws(lowering: str) -> dict:
    env = dict(os.environ, **{xla_cpu.ENV_VAR: lowering}, JAX_PLATFORMS="cpu")
    res = subprocess.run([sys.executable, "-c", DRAWS], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_the_unrolled_lowering_is_installed_on_this_jax():
    """Fails on a JAX that lacks the private rule (the library then keeps the slower default)."""
    assert xla_cpu.installed()


@pytest.mark.parametrize("key, counter, expected", KNOWN_ANSWERS)
def test_known_answers(key, counter, expected):
    from jax.extend.random import threefry_2x32

    run = jax.jit(threefry_2x32)
    got = run(jnp.asarray(key, jnp.uint32), jnp.asarray(counter, jnp.uint32))
    assert [int(v) for v in np.asarray(got)] == list(expected)


def test_draws_equal_the_default_lowering_bit_for_bit():
    unrolled, rolled = _draws("unrolled"), _draws("rolled")
    assert unrolled.pop("installed") is True and rolled.pop("installed") is False
    assert unrolled.keys() == rolled.keys()
    for name in unrolled:
        assert unrolled[name] == rolled[name], name


def test_a_bad_setting_is_named():
    env = dict(os.environ, **{xla_cpu.ENV_VAR: "sideways"})
    res = subprocess.run([sys.executable, "-c", "import mysim_jax.types"], env=env, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode != 0
    assert f"{xla_cpu.ENV_VAR}='sideways': use one of unrolled, rolled" in res.stderr
