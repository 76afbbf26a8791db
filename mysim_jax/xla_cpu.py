"""How JAX's random-number hash is lowered for XLA's CPU back end.

Every ``jax.random`` draw (``split``, ``fold_in``, ``uniform``, ``normal``, flax's
initialisers) evaluates the Threefry-2x32 hash: 20 rounds of add, rotate and xor. On the
GPU JAX emits the 20 rounds as straight-line code; on the CPU it emits them as a loop of
5 iterations of 4 rounds, which XLA compiles as a separate while loop for every draw. A
capture-environment step holds dozens of draws (the episode's randomisation, the
observation noise, the spawn), and on this project's programs the loops cost compile time
without saving run time: BENCHMARKS.md, section (k), compiles and times both lowerings
side by side.

:func:`install` makes the CPU use the straight-line lowering, JAX's own (the one it uses on
the GPU). The hash computes the same bits either way (``tests/test_xla_cpu.py`` checks the
published Threefry test vectors and ``jax.random`` draws against the loop lowering); only
the code XLA generates changes. It is installed when a module that builds compiled
programs is imported (:mod:`mysim_jax.types`, :mod:`mysim_jax.mappo.trainer`,
:mod:`mysim_jax.perception.detect.model`) and holds for the whole process, including the
user's own ``jax.random`` calls. ``MYSIM_JAX_THREEFRY_CPU=rolled`` in the environment keeps
JAX's default.

The straight-line rule is a private name of JAX (``jax._src.random.threefry2x32``); the
project pins JAX below 0.11. If a JAX version lacks it, :func:`install` leaves JAX's
default in place and returns False (programs compile more slowly, values are unchanged);
``tests/test_xla_cpu.py`` fails on such a version so that it is noticed.
"""

from __future__ import annotations

import os

ENV_VAR = "MYSIM_JAX_THREEFRY_CPU"
CHOICES = ("unrolled", "rolled")

_installed: bool | None = None


def requested() -> str:
    """The lowering asked for by :data:`ENV_VAR` (``unrolled`` when unset)."""
    value = os.environ.get(ENV_VAR, "unrolled").strip().lower() or "unrolled"
    if value not in CHOICES:
        raise ValueError(f"{ENV_VAR}={value!r}: use one of {', '.join(CHOICES)}")
    return value


def install() -> bool:
    """Lower Threefry-2x32 unrolled on the CPU (module docstring), once per process.
    Returns whether the unrolled lowering is in place."""
    global _installed
    if _installed is not None:
        return _installed
    _installed = False
    if requested() == "rolled":
        return False
    try:
        from jax._src.random import threefry2x32 as _threefry
        from jax.interpreters import mlir

        rule = _threefry._threefry2x32_lowering_rule
        primitive = _threefry.threefry2x32_p
    except (ImportError, AttributeError):  # pragma: no cover - another JAX: its default stays
        return False
    mlir.register_lowering(primitive, rule, platform="cpu")
    _installed = True
    return True


def installed() -> bool:
    """Whether :func:`install` put the unrolled lowering in place in this process."""
    return bool(_installed)
