"""Rope module: a lumped-mass spring-damper rope (paper Sec. 2.1, Fig. rope_model).

A rope of total length ``L`` is ``N`` point masses ``m_i`` joined by ``N + 1`` segments:

* interior rest length ``s̄_i = L / N``; the two end segments ``s̄_0 = s̄_N = L / (2N)``,
  so the rest lengths sum to ``L`` and the ends can attach to other modules;
* segment stiffness ``k_i = EA / s̄_i`` and damping ``d_i = d / s̄_i``
  (``EA`` the axial stiffness [N], ``d`` the linear tensile damping [N·s]);
* segment force ``k_i (s − s̄_i) + d_i ds/dt`` along the segment
  (:func:`mysim_jax.dynamics.forces.spring_tension`), tension-only or linear.

The builder here is host-side NumPy: it turns one rope description into point masses,
initial positions and segment constants. The segments themselves are ordinary springs in
the scene's spring table (index arrays), so all ropes and springs are evaluated by one
gather and one scatter, never by a Python loop over segments.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def rope_rest_lengths(length: float, n_masses: int) -> np.ndarray:
    """Rest lengths ``(N + 1,)``: ``[L/2N, L/N, ..., L/N, L/2N]`` (sum = L); ``[L]`` for
    N = 0 (one segment between the rope's ends)."""
    if n_masses == 0:
        return np.array([float(length)])
    interior = length / n_masses
    rest = np.full(n_masses + 1, interior)
    rest[0] = rest[-1] = 0.5 * interior
    return rest


@dataclass(frozen=True)
class RopeSegments:
    """Host-side description of one rope's masses and segments."""

    point_pos: np.ndarray      # (N, 3) initial positions of the masses
    point_mass: np.ndarray     # (N,)
    rest_length: np.ndarray    # (N + 1,)
    stiffness: np.ndarray      # (N + 1,) EA / s̄_i
    damping: np.ndarray        # (N + 1,) d / s̄_i


def build_rope(length, n_masses, mass, ea, damping, start_pos, end_pos) -> RopeSegments:
    """Masses on the straight line from ``start_pos`` to ``end_pos``, at rest.

    The masses sit at the cumulative rest lengths, scaled by ``|end − start| / L`` so that
    every segment starts with the same strain (no strain at all when the ends are exactly
    ``L`` apart, as in the paper's rope net).
    """
    rest = rope_rest_lengths(length, n_masses)
    start = np.asarray(start_pos, dtype=float)
    end = np.asarray(end_pos, dtype=float)
    frac = np.cumsum(rest)[:-1] / length          # (N,) in (0, 1)
    pos = start[None, :] + frac[:, None] * (end - start)[None, :]
    return RopeSegments(
        point_pos=pos,
        point_mass=np.full(n_masses, float(mass)),
        rest_length=rest,
        stiffness=ea / rest,
        damping=damping / rest,
    )
