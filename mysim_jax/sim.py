"""The simulation pipeline: accelerations, one environment step, rollouts.

``accelerations`` is composed at trace time from the effects the static Scene has, as a
chain of pure stages named after the physics (each under ``jax.named_scope`` so that a
profile reads like the paper)::

    marker_kinematics -> [force stages: spring_forces, applied_loads, ...]
      -> distribute_node_forces -> newton_euler (+ gravity) -> constraint_solve

``force_stages(scene)`` lists the force elements a scene has; a scene without springs
traces no spring code, without joints no constraint solve.

``step(scene, params, state, control=None)`` advances one environment by ``scene.dt``
(``scene.substeps`` sub-steps of a fixed-step integrator, or one adaptive diffrax solve).
It is pure and written for one environment: batch with ``jax.vmap``, jit once around the
whole rollout. The updates a step runs once at its start (the control stage, the contact
broad phase, the effects' updates) are :func:`step_updates`; what they hold over the
step's sub-steps is a :class:`Held`.

The host-side driver of whole runs (``simulate``: its chunks, progress bar and checks for
non-finite states) is :mod:`mysim_jax.driver`, the only place the library calls
``jax.jit`` on its own.
"""

from __future__ import annotations

from typing import NamedTuple

import diffrax
import jax
import jax.numpy as jnp

from mysim_jax.contact.broad_phase import broad_phase_update
from mysim_jax.contact.forces import contact_forces
from mysim_jax.control.actuation import actuate
from mysim_jax.dynamics import constraints as _constraints
from mysim_jax.dynamics.forces import ForceStage, Loads, spring_forces
from mysim_jax.dynamics.implicit_springs import ImplicitSpringSolve
from mysim_jax.dynamics.integrators import FIXED_STEP, state_derivative
from mysim_jax.dynamics.markers import distribute_node_forces, node_states
from mysim_jax.dynamics.quadrotor import rotor_forces
from mysim_jax.dynamics.quaternion import quat_normalize
from mysim_jax.dynamics.rigid_body import body_accelerations, inertia_inverse
from mysim_jax.effects.registry import scene_effects
from mysim_jax.core.types import Accelerations, Params, PhysState, Scene, State, Trajectory

# Trajectory, what the driver (mysim_jax.driver) returns, stays importable from here
__all__ = ["force_stages", "accelerations", "derivative", "adaptive_solution", "solve_adaptive", "held_inputs",
           "effect_updates", "Held", "has_step_updates", "step_updates", "held_accelerations", "step", "rollout",
           "Trajectory"]


class Held(NamedTuple):
    """What the updates of one step hold over its sub-steps (zero-order hold)."""

    inputs: object = None        # the control stage's ActuatorInputs (quadrotor scenes), else the caller's control
    effects: dict | None = None  # effect name -> what its update holds
    contact: object = None       # the contact broad phase's choice of pairs (contact.broad_phase), else None


def _spring_stage(scene, params, phys, nodes, held: Held) -> Loads:
    return Loads.of_nodes(spring_forces(scene, params, *nodes), scene.n_bodies)


def _load_stage(scene, params, phys, nodes, held: Held) -> Loads:
    return Loads(node_force=params.load_node_force,
                 body_force=jnp.zeros_like(phys.body_pos), body_torque=params.load_body_torque)


def _contact_stage(scene, params, phys, nodes, held: Held) -> Loads:
    return contact_forces(scene, params, phys, nodes, held.contact)


def _rotor_stage(scene, params, phys, nodes, held: Held) -> Loads:
    return rotor_forces(scene, params, phys, nodes, held.inputs)


def force_stages(scene: Scene) -> tuple[tuple[str, ForceStage], ...]:
    """The built-in force elements this scene has, in pipeline order, decided from the
    static Scene.

    Each stage is ``fn(scene, params, phys, nodes, held) -> Loads`` with ``nodes`` the
    ``(node_pos, node_vel)`` table and ``held`` the step's :class:`Held` (the actuator
    inputs, the contact broad phase's choice). Registered effects (docs/effects.md) add
    their stages after these, each called with what its own update holds; new effects
    register there, not here.
    """
    stages: list[tuple[str, ForceStage]] = []
    if scene.n_springs:
        stages.append(("spring_forces", _spring_stage))
    if scene.has_loads:
        stages.append(("applied_loads", _load_stage))
    if scene.contact is not None:
        stages.append(("contact_forces", _contact_stage))
    if scene.quadrotor is not None:
        stages.append(("rotor_forces", _rotor_stage))
    return tuple(stages)


def _all_stages(scene: Scene, held: Held):
    """``[(name, stage, what it holds), ...]``: the built-in stages, then the effects'."""
    stages = [(name, stage, held) for name, stage in force_stages(scene)]
    for effect, static in scene_effects(scene):
        stages += [(name, stage, (held.effects or {}).get(effect.name)) for name, stage in effect.stages(static)]
    return stages


def accelerations(scene: Scene, params: Params, phys: PhysState, inputs=None, held=None,
                  contact=None) -> Accelerations:
    """Accelerations of every point and body for one environment, under what the step's
    updates hold (:func:`step_updates`): ``inputs`` the actuator inputs, ``held`` a dict of
    what each effect's update holds (by effect name), ``contact`` the contact broad
    phase's choice of pairs (None: every pair)."""
    stages = _all_stages(scene, Held(inputs=inputs, effects=held, contact=contact))
    loads = None
    if stages:
        with jax.named_scope("marker_kinematics"):
            nodes = node_states(scene, params, phys)
        for name, stage, hold in stages:
            with jax.named_scope(name):
                part = stage(scene, params, phys, nodes, hold)
            loads = part if loads is None else loads + part
    with jax.named_scope("distribute_node_forces"):
        if loads is None:
            point_force = jnp.zeros_like(phys.point_pos)
            body_force = jnp.zeros_like(phys.body_pos)
            body_torque = jnp.zeros_like(phys.body_pos)
        else:
            point_force, body_force, body_torque = distribute_node_forces(scene, params, phys, loads.node_force)
            body_force = body_force + loads.body_force
            body_torque = body_torque + loads.body_torque
    with jax.named_scope("newton_euler"):
        point_acc = point_force / params.point_mass[:, None]
        if scene.has_gravity:
            point_acc = point_acc + params.gravity
        if scene.n_bodies:
            inertia_inv = inertia_inverse(params.body_inertia)
            body_acc, body_angacc = body_accelerations(
                params.body_mass, inertia_inv, params.body_inertia, phys.body_angvel, body_force, body_torque
            )
            if scene.has_gravity:
                body_acc = body_acc + params.gravity
        else:
            body_acc = jnp.zeros_like(phys.body_pos)
            body_angacc = jnp.zeros_like(phys.body_pos)
    if scene.joint_buckets:
        with jax.named_scope("constraint_solve"):
            body_acc, body_angacc = _constraints.solve_constraints(
                scene, params, phys, body_acc, body_angacc, inertia_inv
            )
    return Accelerations(point_acc=point_acc, body_acc=body_acc, body_angacc=body_angacc)


def derivative(scene: Scene, params: Params, phys: PhysState, inputs=None, held=None, contact=None) -> PhysState:
    """``d(phys)/dt`` as a PhysState-shaped pytree (quaternion rate ½ q ⊗ ω)."""
    return state_derivative(phys, accelerations(scene, params, phys, inputs, held, contact))


def _adaptive_solver(scene: Scene):
    return {"tsit5": diffrax.Tsit5, "kvaerno5": diffrax.Kvaerno5}[scene.integrator]()


def _vector_field(scene: Scene):
    def field(t, y, args):
        params, inputs, held, contact = args
        # quaternions drift off the unit sphere by O(tolerance); forces and the attitude
        # rate use the unit quaternion
        return derivative(scene, params, y.replace(body_quat=quat_normalize(y.body_quat)), inputs, held, contact)
    return field


# Solver steps between progress-bar refreshes: diffrax's default (20) redraws the bar
# thousands of times in a contact scene (~1e5 steps), flooding logs with carriage returns.
_PROGRESS_REFRESH_STEPS = 2000


def adaptive_solution(scene: Scene, params: Params, phys: PhysState, t0, t1, ts=None, progress=False, inputs=None,
                      held=None, contact=None):
    """The diffrax solve behind :func:`solve_adaptive`, returning diffrax's ``Solution``
    (states, ``result``, ``stats``). It never raises: a failed solve (``max_steps``
    reached, a non-finite state) is reported in ``result``, and saved times it did not
    reach hold ``inf``."""
    saveat = diffrax.SaveAt(ts=ts) if ts is not None else diffrax.SaveAt(t1=True)
    return diffrax.diffeqsolve(
        diffrax.ODETerm(_vector_field(scene)),
        _adaptive_solver(scene),
        t0=t0,
        t1=t1,
        dt0=scene.substep,
        y0=phys,
        args=(params, inputs, held, contact),
        saveat=saveat,
        stepsize_controller=diffrax.PIDController(rtol=scene.rtol, atol=scene.atol),
        max_steps=scene.solver_max_steps,
        throw=False,
        progress_meter=(diffrax.TqdmProgressMeter(refresh_steps=_PROGRESS_REFRESH_STEPS) if progress
                        else diffrax.NoProgressMeter()),
    )


def solve_adaptive(scene: Scene, params: Params, phys: PhysState, t0, t1, ts=None, progress=False, inputs=None,
                   held=None, stats: bool = False, contact=None):
    """Integrate with the scene's diffrax solver from ``t0`` to ``t1``.

    Returns the states at ``ts`` (stacked) if given, else the state at ``t1``; with
    ``stats=True``, ``(states, stats)`` where ``stats`` holds the solver's
    ``num_accepted_steps``, ``num_rejected_steps`` (int arrays) and ``successful`` (bool). A solve
    that fails (``max_steps`` reached, e.g. because the state turned non-finite and every
    step was rejected) does not raise inside jit: the states it did not reach are ``inf``
    (at ``ts``) or NaN (at ``t1``: diffrax would return the state where it stopped,
    which is not the state at ``t1``), so a caller checking for finite states sees it.
    """
    sol = adaptive_solution(scene, params, phys, t0, t1, ts, progress, inputs, held, contact)
    ys = sol.ys
    ys = ys.replace(body_quat=quat_normalize(ys.body_quat))
    ok = sol.result == diffrax.RESULTS.successful
    if ts is None:
        ys = jax.tree.map(lambda a: jnp.where(ok, a[0], jnp.nan), ys)
    if stats:
        return ys, {"num_accepted_steps": sol.stats["num_accepted_steps"],
                    "num_rejected_steps": sol.stats["num_rejected_steps"], "successful": ok}
    return ys


def held_inputs(scene: Scene, params: Params, state: State, control=None):
    """The actuator inputs held over the next step, and the updated controller memory.

    Scenes with quadrotors run their control stage here (controller, or the caller's
    motor commands ``control``, then the motor model; :mod:`mysim_jax.control.actuation`);
    other scenes pass ``control`` through unchanged.
    """
    if scene.quadrotor is None:
        return control, state.controller
    with jax.named_scope("control"):
        return actuate(scene, params, state, control)


def effect_updates(scene: Scene, params: Params, state: State):
    """Run the update of every effect the scene has (docs/effects.md), once per
    environment step. Returns ``(held, memory)``: what each effect's stages hold over the
    step, and the effects' new memory (both dicts by effect name)."""
    held, memory = {}, dict(state.effects)
    for effect, _ in scene_effects(scene):
        with jax.named_scope(f"{effect.name}_update"):
            held[effect.name], memory[effect.name] = effect.update(scene, params, state)
    return held, memory


def has_step_updates(scene: Scene) -> bool:
    """Does a step of this scene run updates at its start (:func:`step_updates`: a
    controller, an effect, a contact broad phase)? Such a scene is stepped one ``dt`` at
    a time even with an adaptive integrator."""
    return (scene.quadrotor is not None or bool(scene.effects)
            or (scene.contact is not None and scene.contact.broad_phase is not None))


def step_updates(scene: Scene, params: Params, state: State, control=None) -> tuple[Held, State]:
    """The updates a step runs once, at its start, from ``state``: the control stage
    (:func:`held_inputs`), the contact broad phase (``contact.broad_phase``,
    :func:`~mysim_jax.contact.broad_phase.broad_phase_update`) and every effect's update
    (:func:`effect_updates`). Returns what they hold over the step and ``state`` with
    their new memories (the controller's, the contact stage's, the effects'); the physics
    and the time are not advanced. :func:`step` and the driver's accelerations at saved
    states share it."""
    inputs, controller = held_inputs(scene, params, state, control)
    contact, contact_memory = None, state.contact
    if scene.contact is not None and scene.contact.broad_phase is not None:
        with jax.named_scope("broad_phase"):
            contact, contact_memory = broad_phase_update(scene, params, state)
    held, effect_memory = effect_updates(scene, params, state)
    return (Held(inputs=inputs, effects=held, contact=contact),
            state.replace(controller=controller, effects=effect_memory, contact=contact_memory))


def held_accelerations(scene: Scene, params: Params, phys: PhysState, held: Held) -> Accelerations:
    """:func:`accelerations` with what a step's updates hold (:func:`step_updates`)."""
    return accelerations(scene, params, phys, held.inputs, held.effects, held.contact)


def step(scene: Scene, params: Params, state: State, control=None) -> State:
    """Advance one environment by ``scene.dt``. Pure; vmap and jit at the call site.

    The updates (:func:`step_updates`: the control stage, the contact broad phase, the
    effects') run once at the start of the step; what they hold is held over the
    sub-steps (zero-order hold).
    """
    held, updated = step_updates(scene, params, state, control)
    if scene.integrator in FIXED_STEP:
        integrator = FIXED_STEP[scene.integrator]
        h = jnp.asarray(scene.substep, dtype=state.time.dtype)

        def accel(phys):
            return held_accelerations(scene, params, phys, held)

        implicit = (ImplicitSpringSolve(scene, params, scene.implicit_iterations)
                    if integrator.takes_implicit_springs else None)

        def substep(phys):
            return integrator.step(accel, phys, h, params.body_inertia, implicit)

        phys = state.phys
        if scene.substeps == 1:
            phys = substep(phys)
        else:
            phys = jax.lax.fori_loop(0, scene.substeps, lambda _, p: substep(p), phys)
    else:
        phys = solve_adaptive(scene, params, state.phys, state.time, state.time + scene.dt, inputs=held.inputs,
                              held=held.effects, contact=held.contact)
    return updated.replace(phys=phys, time=state.time + jnp.asarray(scene.dt, dtype=state.time.dtype))


def rollout(scene: Scene, params: Params, state: State, n_steps: int, every: int = 1, policy=None):
    """``lax.scan`` over ``n_steps`` steps; returns ``(final_state, states)`` where
    ``states`` stacks the state after every ``every``-th step (``n_steps // every`` rows).

    ``policy(scene, params, state) -> control``, if given, is asked for the control of
    every step (a :class:`~mysim_jax.control.setpoint.Setpoint` or motor commands, see
    :func:`step`); without it every step runs with ``control=None``.
    """
    if n_steps % every:
        raise ValueError(f"n_steps ({n_steps}) must be a multiple of every ({every})")

    def inner(s, _):
        return step(scene, params, s, None if policy is None else policy(scene, params, s)), None

    def outer(s, _):
        s, _ = jax.lax.scan(inner, s, None, length=every)
        return s, s

    return jax.lax.scan(outer, state, None, length=n_steps // every)
