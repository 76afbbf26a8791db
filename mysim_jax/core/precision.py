"""The float width a run asks for, switched on for the whole process.

JAX's 64-bit switch (``jax_enable_x64``) is process-wide and must be set before the
arrays it concerns are made, so a script turns it on once, after validating its scene
files and before building anything, when one of them asks for ``sim.precision: float64``.
"""

from __future__ import annotations

import jax


def use_precision(*precisions: str) -> bool:
    """Turn on JAX's 64-bit floats when any of ``precisions`` (``sim.precision`` values,
    ``"float32"`` or ``"float64"``) is ``"float64"``; returns whether it did. Never turns
    them off: a process that already runs in 64 bits stays there."""
    wide = "float64" in precisions
    if wide:
        jax.config.update("jax_enable_x64", True)
    return wide
