"""The three kinds of data a simulation is made of: what is fixed, what is tuned, what evolves.

* :class:`Scene` — static structure: counts, names, index arrays (as tuples), which effects
  exist, integrator settings. Frozen and hashable; changing it recompiles; never traced.
  What a run saves (its length, output interval, plots) is not here but in
  :class:`mysim_jax.config.scene.RunSettings`, so changing it never recompiles.
* :class:`Params` — a pytree of float arrays: masses, inertias, marker offsets, spring
  constants, gravity, Baumgarte constants. Traced, differentiable, vmappable.
* :class:`State` — a pytree: the multibody state :class:`PhysState`, the time, (with
  quadrotors) the controller memory, the memory of registered effects (docs/effects.md;
  the target's PRNG key lives there) and (with a contact broad phase) the contact stage's.
* :class:`Trajectory` — what a whole run returns on the host (:func:`mysim_jax.driver.simulate`):
  the states and accelerations on its output grid, as NumPy arrays.

Attachment points ("nodes") are numbered in one table so that springs and rope segments
can join anything with plain index arrays::

    node index:  [0, n_points)                    point masses
                 [n_points, n_points + n_markers)  markers on rigid bodies
                 [n_points + n_markers, n_nodes)   fixed anchors
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np
from flax import struct

from mysim_jax.core.contact_types import ContactParams, ContactScene


@dataclass(frozen=True)
class JointBucket:
    """Joint groups that share one structure, solved together with ``vmap``.

    A *group* is a connected set of rigid bodies joined by joints (anchors connect to
    nothing). Groups with the same signature (number of bodies, joint types, and which
    side of each joint is a body marker vs an anchor) are stacked into one bucket.
    """

    joint_types: tuple[str, ...]          # (n_joints,) "fixed" | "universal"
    side_i_is_anchor: tuple[bool, ...]    # (n_joints,)
    side_j_is_anchor: tuple[bool, ...]    # (n_joints,)
    side_i_local_body: tuple[int, ...]    # (n_joints,) position of the body in the group (-1 for anchors)
    side_j_local_body: tuple[int, ...]    # (n_joints,)
    group_bodies: tuple[tuple[int, ...], ...]  # (n_groups, n_bodies) global body indices
    group_frame_i: tuple[tuple[int, ...], ...]  # (n_groups, n_joints) marker or anchor index
    group_frame_j: tuple[tuple[int, ...], ...]  # (n_groups, n_joints)

    @property
    def n_rows(self) -> int:
        return sum(6 if t == "fixed" else 4 for t in self.joint_types)


@dataclass(frozen=True)
class Scene:
    """Static description of one environment. Hashable: usable as a ``jit`` static arg."""

    # --- entities ---------------------------------------------------------------------
    point_names: tuple[str, ...]
    body_names: tuple[str, ...]
    marker_names: tuple[str, ...]           # "body.marker"
    marker_body: tuple[int, ...]            # (n_markers,) body index of each marker
    anchor_names: tuple[str, ...]
    rope_names: tuple[str, ...] = ()
    rope_point_index: tuple[tuple[int, ...], ...] = ()   # (n_ropes, n_masses_r) point indices
    # --- springs (rope segments and free springs), joining node indices ----------------
    spring_names: tuple[str, ...] = ()
    spring_node_a: tuple[int, ...] = ()
    spring_node_b: tuple[int, ...] = ()
    spring_tension_only: tuple[bool, ...] = ()
    # --- effects ----------------------------------------------------------------------
    has_gravity: bool = True
    has_loads: bool = False
    joint_buckets: tuple[JointBucket, ...] = ()
    # --- integration ------------------------------------------------------------------
    integrator: str = "semi_implicit_euler"
    dt: float = 1e-3
    substeps: int = 1
    precision: str = "float32"
    rtol: float = 1e-8
    atol: float = 1e-10
    solver_max_steps: int = 10_000_000      # the adaptive solver's step limit (sim.max_steps)
    implicit_iterations: int = 0            # CG iterations per step of implicit_euler (0 otherwise)
    # how node forces are summed (sim.accumulate): "segment_sum" (a scatter-add, the
    # default) or "matmul" (a dense one-hot incidence product)
    accumulate: str = "segment_sum"
    # how spring ends are gathered (sim.gather): "slices" (static contiguous slices where
    # the index has few runs, markers.take_rows; the default) or "index" (x[index_array])
    gather: str = "slices"
    # (tension [N], slack [m]) widths of the tension-only law's backward-pass smoothing
    # (sim.smooth_backward); None: the exact law's gradients
    smooth_backward: tuple[float, float] | None = None
    # --- contact (mysim_jax/contact): None when the scene has no contact ---------------
    contact: ContactScene | None = None
    # --- quadrotors, their controller and cameras (mysim_jax/dynamics/quadrotor.py) ----
    quadrotor: object | None = None   # mysim_jax.dynamics.quadrotor.QuadrotorScene
    # --- registered effects (docs/effects.md): ((name, static part), ...) ---------------------
    effects: tuple[tuple[str, object], ...] = ()

    @property
    def n_points(self) -> int:
        return len(self.point_names)

    @property
    def n_bodies(self) -> int:
        return len(self.body_names)

    @property
    def n_markers(self) -> int:
        return len(self.marker_names)

    @property
    def n_anchors(self) -> int:
        return len(self.anchor_names)

    @property
    def n_nodes(self) -> int:
        return self.n_points + self.n_markers + self.n_anchors

    @property
    def n_springs(self) -> int:
        return len(self.spring_node_a)

    @property
    def substep(self) -> float:
        """The integrator's (initial, for adaptive solvers) step ``dt / substeps``."""
        return self.dt / self.substeps

    @property
    def dtype(self):
        return jnp.float64 if self.precision == "float64" else jnp.float32


@struct.dataclass
class Params:
    """Traced physical parameters of one environment (vmap over them for sweeps)."""

    point_mass: jnp.ndarray          # (n_points,) kg
    body_mass: jnp.ndarray           # (n_bodies,) kg
    body_inertia: jnp.ndarray        # (n_bodies, 3, 3) kg m^2, body frame, about the CoM
    marker_pos: jnp.ndarray          # (n_markers, 3) m, body frame
    marker_quat: jnp.ndarray         # (n_markers, 4) marker -> body rotation
    anchor_pos: jnp.ndarray          # (n_anchors, 3) m, world
    anchor_quat: jnp.ndarray         # (n_anchors, 4)
    spring_stiffness: jnp.ndarray    # (n_springs,) N/m
    spring_damping: jnp.ndarray      # (n_springs,) N s/m
    spring_rest_length: jnp.ndarray  # (n_springs,) m
    gravity: jnp.ndarray             # (3,) m/s^2
    load_node_force: jnp.ndarray     # (n_nodes, 3) N, world frame, constant applied forces
    load_body_torque: jnp.ndarray    # (n_bodies, 3) N m, body frame
    baumgarte_alpha: jnp.ndarray     # () 1/s
    baumgarte_beta: jnp.ndarray      # () 1/s
    contact: ContactParams | None = None   # contact constants and sphere radii (None: no contact)
    quadrotor: object | None = None   # mysim_jax.dynamics.quadrotor.QuadrotorParams; rotors, motors, aerodynamics, gimbal servos
    controller: object | None = None    # mysim_jax.control.pid.ControlParams; PID gains, controller model, references
    effects: dict = field(default_factory=dict)  # registered effect name -> its params pytree


@struct.dataclass
class PhysState:
    """Multibody state: what the integrators advance."""

    point_pos: jnp.ndarray    # (n_points, 3) m, world
    point_vel: jnp.ndarray    # (n_points, 3) m/s, world
    body_pos: jnp.ndarray     # (n_bodies, 3) m, world (centre of mass)
    body_quat: jnp.ndarray    # (n_bodies, 4) body -> world, scalar first
    body_vel: jnp.ndarray     # (n_bodies, 3) m/s, world
    body_angvel: jnp.ndarray  # (n_bodies, 3) rad/s, body frame


@struct.dataclass
class Accelerations:
    """Second derivatives of one :class:`PhysState`."""

    point_acc: jnp.ndarray       # (n_points, 3) m/s^2, world
    body_acc: jnp.ndarray        # (n_bodies, 3) m/s^2, world
    body_angacc: jnp.ndarray     # (n_bodies, 3) rad/s^2, body frame


@struct.dataclass
class State:
    """Full state of one environment."""

    phys: PhysState
    time: jnp.ndarray         # () s
    controller: object | None = None   # mysim_jax.control.pid.ControlState; PID integrators, motor speeds (quadrotor scenes)
    effects: dict = field(default_factory=dict)  # registered effect name -> its memory (e.g. PRNG key)
    contact: object | None = None      # mysim_jax.contact.broad_phase.BroadPhaseMemory (scenes with contact.broad_phase)


@dataclass
class Trajectory:
    """Host-side result of :func:`mysim_jax.driver.simulate`: states and accelerations on
    the output grid.

    ``failure`` is None when the run reached ``t_end``. Otherwise it says why the run
    stopped early (a state or acceleration turned non-finite, or the adaptive solver gave
    up), when, and in which points or bodies; the arrays then hold the finite part of the
    run only, up to the last finite saved state.
    """

    time: np.ndarray          # (n_out,)
    phys: PhysState           # leaves (n_out, ...) as NumPy arrays
    acc: Accelerations        # leaves (n_out, ...) as NumPy arrays
    controller: object = None  # ControlState leaves (n_out, ...) (quadrotor scenes), else None
    failure: str | None = None
    effects: dict | None = None  # effect name -> its memory, leaves (n_out, ...) (stepped runs), else None

    @property
    def ok(self) -> bool:
        return self.failure is None
