"""Rotor geometry and the allocation matrix from configuration values, in NumPy.

Host-side only (config checks and scene assembly); the traced versions live in
:mod:`mysim_jax.dynamics.quadrotor`, whose docstring defines the layout and ``M``. This
module imports no JAX, so validating a scene file does not either.
"""

from __future__ import annotations

import numpy as np


def rotor_positions_np(arm_length, angle) -> np.ndarray:
    """``d_i = l_i [sin θ_i, cos θ_i, 0]`` as a ``(4, 3)`` NumPy array."""
    arm, ang = np.asarray(arm_length, float), np.asarray(angle, float)
    return np.stack([arm * np.sin(ang), arm * np.cos(ang), np.zeros_like(arm)], axis=-1)


def allocation_matrix_np(arm_length, angle, lift, torque_coefficient, spin) -> np.ndarray:
    """The allocation matrix ``M`` (4, 4) from config values."""
    d = rotor_positions_np(arm_length, angle)
    c, k, s = (np.asarray(x, float) for x in (lift, torque_coefficient, spin))
    return np.stack([c, c * d[:, 1], -c * d[:, 0], s * k])
