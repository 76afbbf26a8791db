"""Static contact structure (part of :class:`~mysim_jax.core.types.Scene`) and contact
parameters (part of :class:`~mysim_jax.core.types.Params`).

Spheres are numbered in one table: first the spheres on point masses, then those on
rigid bodies (each centred on the body's centre of mass). Pairs and ground contacts are
static index tuples into that table; all of them are evaluated every step and the ones
not touching contribute exactly zero (sharp model) — no data-dependent shapes.

Capsules (rope and spring segments with a radius) are numbered in a second table, in the
order of the scene's springs; ``capsule_names`` are the springs' names in
``Scene.spring_names``, whose node tables give the capsules' end nodes. Sphere–capsule
pairs are index tuples into the two tables. A scene without capsules has empty capsule
tuples and ``ContactParams.capsule_radius = None``.

With ``contact.broad_phase`` the contact stage evaluates, in each step's sub-steps, only
the sphere–capsule pairs the broad phase chose at the step's start
(:mod:`mysim_jax.contact.broad_phase`); its settings are :class:`BroadPhaseScene`, its
memory ``State.contact``.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
from flax import struct


@dataclass(frozen=True)
class BroadPhaseScene:
    """The contact broad phase's settings (``contact.broad_phase``). Hashable."""

    capsules: int        # K, sphere–capsule pairs kept per sphere
    margin: float        # m, surface gap below which a pair must be kept


@dataclass(frozen=True)
class ContactScene:
    """Static contact structure of one scene. Hashable."""

    sphere_names: tuple[str, ...]          # (n_spheres,) point names, then body names
    sphere_point: tuple[int, ...]          # (n_point_spheres,) point index of each
    sphere_body: tuple[int, ...]           # (n_body_spheres,) body index of each
    pair_a: tuple[int, ...] = ()           # (n_pairs,) sphere index
    pair_b: tuple[int, ...] = ()           # (n_pairs,) sphere index (force on b along a -> b)
    ground_sphere: tuple[int, ...] = ()    # (n_ground,) spheres that touch the plane z = 0
    capsule_names: tuple[str, ...] = ()    # (n_capsules,) spring names (Scene.spring_names)
    capsule_end_names: tuple[tuple[str, str], ...] = ()   # (n_capsules, 2) end node names at s = 0, 1
    capsule_end_object_a: tuple[int, ...] = ()   # (n_capsules,) mass moving end a: point index,
    capsule_end_object_b: tuple[int, ...] = ()   # n_points + body index (body/marker), −1 anchor
    capsule_pair_sphere: tuple[int, ...] = ()    # (n_capsule_pairs,) sphere index
    capsule_pair_capsule: tuple[int, ...] = ()   # (n_capsule_pairs,) capsule index
    model: str = "sharp"                   # "sharp" | "smooth"
    friction: bool = False
    broad_phase: BroadPhaseScene | None = None   # None: every sphere–capsule pair in every sub-step

    @property
    def n_spheres(self) -> int:
        return len(self.sphere_point) + len(self.sphere_body)

    @property
    def n_pairs(self) -> int:
        return len(self.pair_a)

    @property
    def n_ground(self) -> int:
        return len(self.ground_sphere)

    def pair_names(self) -> list[str]:
        return [f"{self.sphere_names[a]}|{self.sphere_names[b]}" for a, b in zip(self.pair_a, self.pair_b)]

    @property
    def n_capsules(self) -> int:
        return len(self.capsule_names)

    @property
    def n_capsule_pairs(self) -> int:
        return len(self.capsule_pair_sphere)

    @property
    def culls_capsules(self) -> bool:
        """Does the broad phase choose the sphere–capsule pairs (it has some to choose from)?"""
        return self.broad_phase is not None and self.n_capsule_pairs > 0

    def capsule_pair_names(self) -> list[str]:
        return [f"{self.sphere_names[a]}|{self.capsule_names[c]}"
                for a, c in zip(self.capsule_pair_sphere, self.capsule_pair_capsule)]


@struct.dataclass
class ContactParams:
    """Traced contact constants (differentiable; vmap for sweeps)."""

    radius: jnp.ndarray            # (n_spheres,) m
    stiffness: jnp.ndarray         # () k, N/m^n
    exponent: jnp.ndarray          # () n
    damping: jnp.ndarray           # () c, N s/m
    damping_depth: jnp.ndarray     # () p, m
    mu_static: jnp.ndarray         # ()
    mu_dynamic: jnp.ndarray        # ()
    v_static: jnp.ndarray          # () m/s
    v_dynamic: jnp.ndarray         # () m/s
    smooth_depth: jnp.ndarray      # () m, width of the smooth model
    smooth_velocity: jnp.ndarray   # () m/s, slip regularisation of the smooth model
    capsule_radius: jnp.ndarray | None = None   # (n_capsules,) m; None without capsules
