"""The simulation pipeline: accelerations, one environment step, rollouts, whole runs.

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
whole rollout. The library never calls ``jax.jit`` on its own except in ``simulate``, the
host-side driver that writes outputs.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import partial

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from mysim_jax.contact.forces import contact_forces
from mysim_jax.control.actuation import actuate
from mysim_jax.dynamics import constraints as _constraints
from mysim_jax.dynamics.forces import ForceStage, Loads, spring_forces
from mysim_jax.dynamics.gimbal import gimbal_servo_forces
from mysim_jax.dynamics.implicit_springs import ImplicitSpringSolve
from mysim_jax.dynamics.integrators import FIXED_STEP, state_derivative
from mysim_jax.dynamics.markers import distribute_node_forces, node_states
from mysim_jax.dynamics.quadrotor import aerodynamic_forces, rotor_forces
from mysim_jax.dynamics.quaternion import quat_normalize
from mysim_jax.dynamics.rigid_body import body_accelerations, inertia_inverse
from mysim_jax.effects.registry import scene_effects
from mysim_jax.core.types import Accelerations, Params, PhysState, Scene, State


def _spring_stage(scene, params, phys, nodes, inputs) -> Loads:
    return Loads.of_nodes(spring_forces(scene, params, *nodes), scene.n_bodies)


def _load_stage(scene, params, phys, nodes, inputs) -> Loads:
    return Loads(node_force=params.load_node_force,
                 body_force=jnp.zeros_like(phys.body_pos), body_torque=params.load_body_torque)


def force_stages(scene: Scene) -> tuple[tuple[str, ForceStage], ...]:
    """The force elements this scene has, in pipeline order, decided from the static Scene.

    Each stage is ``fn(scene, params, phys, nodes, inputs) -> Loads`` with ``nodes`` the
    ``(node_pos, node_vel)`` table and ``inputs`` the actuator commands held over the step
    (``None`` when the scene has no actuators). Registered effects (docs/effects.md)
    add their stages after these, each called with what its own update holds instead of
    ``inputs``; new effects register there, not here.
    """
    stages: list[tuple[str, ForceStage]] = []
    if scene.n_springs:
        stages.append(("spring_forces", _spring_stage))
    if scene.has_loads:
        stages.append(("applied_loads", _load_stage))
    if scene.contact is not None:
        stages.append(("contact_forces", contact_forces))
    if scene.quadrotor is not None:
        stages.append(("rotor_forces", rotor_forces))
        if scene.quadrotor.has_drag or scene.quadrotor.has_wind:
            stages.append(("aerodynamic_forces", aerodynamic_forces))
        if scene.quadrotor.n_gimbals:
            stages.append(("gimbal_servo", gimbal_servo_forces))
    return tuple(stages)


def _all_stages(scene: Scene, inputs, held):
    """``[(name, stage, what it holds), ...]``: the built-in stages, then the effects'."""
    stages = [(name, stage, inputs) for name, stage in force_stages(scene)]
    for effect, static in scene_effects(scene):
        stages += [(name, stage, (held or {}).get(effect.name)) for name, stage in effect.stages(static)]
    return stages


def accelerations(scene: Scene, params: Params, phys: PhysState, inputs=None, held=None) -> Accelerations:
    """Accelerations of every point and body for one environment. ``held`` maps effect
    names to what their updates hold over the step (:func:`effect_updates`)."""
    stages = _all_stages(scene, inputs, held)
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


def derivative(scene: Scene, params: Params, phys: PhysState, inputs=None, held=None) -> PhysState:
    """``d(phys)/dt`` as a PhysState-shaped pytree (quaternion rate ½ q ⊗ ω)."""
    return state_derivative(phys, accelerations(scene, params, phys, inputs, held))


def _adaptive_solver(scene: Scene):
    return {"tsit5": diffrax.Tsit5, "kvaerno5": diffrax.Kvaerno5}[scene.integrator]()


def _vector_field(scene: Scene):
    def field(t, y, args):
        params, inputs, held = args
        # quaternions drift off the unit sphere by O(tolerance); forces and the attitude
        # rate use the unit quaternion
        return derivative(scene, params, y.replace(body_quat=quat_normalize(y.body_quat)), inputs, held)
    return field


# Solver steps between progress-bar refreshes: diffrax's default (20) redraws the bar
# thousands of times in a contact scene (~1e5 steps), flooding logs with carriage returns.
_PROGRESS_REFRESH_STEPS = 2000


def _diffeqsolve(scene: Scene, params: Params, phys: PhysState, t0, t1, ts=None, progress=False, inputs=None,
                 held=None):
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
        args=(params, inputs, held),
        saveat=saveat,
        stepsize_controller=diffrax.PIDController(rtol=scene.rtol, atol=scene.atol),
        max_steps=scene.max_steps,
        throw=False,
        progress_meter=(diffrax.TqdmProgressMeter(refresh_steps=_PROGRESS_REFRESH_STEPS) if progress
                        else diffrax.NoProgressMeter()),
    )


def solve_adaptive(scene: Scene, params: Params, phys: PhysState, t0, t1, ts=None, progress=False, inputs=None,
                   held=None, stats: bool = False):
    """Integrate with the scene's diffrax solver from ``t0`` to ``t1``.

    Returns the states at ``ts`` (stacked) if given, else the state at ``t1``; with
    ``stats=True``, ``(states, stats)`` where ``stats`` holds the solver's
    ``num_accepted_steps``, ``num_rejected_steps`` (int arrays) and ``successful`` (bool). A solve
    that fails (``max_steps`` reached, e.g. because the state turned non-finite and every
    step was rejected) does not raise inside jit: the states it did not reach are ``inf``
    (at ``ts``) or NaN (at ``t1``: diffrax would return the state where it stopped,
    which is not the state at ``t1``), so a caller checking for finite states sees it.
    """
    sol = _diffeqsolve(scene, params, phys, t0, t1, ts, progress, inputs, held)
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


def step(scene: Scene, params: Params, state: State, control=None) -> State:
    """Advance one environment by ``scene.dt``. Pure; vmap and jit at the call site.

    The control stage (:func:`held_inputs`) and the effects' updates
    (:func:`effect_updates`) run once at the start of the step; their outputs are held
    over the sub-steps (zero-order hold).
    """
    control, memory = held_inputs(scene, params, state, control)
    held, effect_memory = effect_updates(scene, params, state)
    if scene.integrator in FIXED_STEP:
        integrator = FIXED_STEP[scene.integrator]
        h = jnp.asarray(scene.substep, dtype=state.time.dtype)

        def accel(phys):
            return accelerations(scene, params, phys, control, held)

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
        phys = solve_adaptive(scene, params, state.phys, state.time, state.time + scene.dt, inputs=control,
                              held=held)
    return state.replace(phys=phys, time=state.time + jnp.asarray(scene.dt, dtype=state.time.dtype),
                         controller=memory, effects=effect_memory)


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


@dataclass
class Trajectory:
    """Host-side result of :func:`simulate`: states and accelerations on the output grid.

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


def output_times(run) -> np.ndarray:
    """The output grid ``0, output_dt, ..., t_end`` of a :class:`~mysim_jax.config.scene.RunSettings`
    (whose ``t_end`` lies on it)."""
    n = int(round(run.t_end / run.output_dt))
    return np.arange(n + 1) * run.output_dt


def steps_per_output(scene: Scene, run) -> int:
    """Environment steps between saved states; the run's ``output_dt`` must be a whole
    multiple of the scene's step ``dt`` (a ValueError says so otherwise)."""
    every = int(round(run.output_dt / scene.dt))
    if every < 1 or abs(every * scene.dt - run.output_dt) > 1e-9 * run.output_dt:
        raise ValueError(f"run '{run.name}': output_dt = {run.output_dt:g} s is not a whole multiple of the "
                         f"scene's step dt = {scene.dt:g} s")
    return every


@partial(jax.jit, static_argnums=(0, 3, 4, 5))
def _advance(scene: Scene, params: Params, state: State, n_steps: int, every: int, policy=None):
    return rollout(scene, params, state, n_steps, every, policy)


@partial(jax.jit, static_argnums=(0, 4))
def _solve_on_grid(scene: Scene, params: Params, phys: PhysState, ts, progress: bool):
    sol = _diffeqsolve(scene, params, phys, ts[0], ts[-1], ts, progress)
    return sol.ys.replace(body_quat=quat_normalize(sol.ys.body_quat)), sol.result, sol.stats["num_steps"]


@partial(jax.jit, static_argnums=(0, 3))
def _accelerations_on_grid(scene: Scene, params: Params, states: State, policy=None):
    """Accelerations at stacked states, with the inputs the controller and the effects
    hold from there."""
    def at(s):
        inputs = None
        if scene.quadrotor is not None:
            inputs = held_inputs(scene, params, s, None if policy is None else policy(scene, params, s))[0]
        held = effect_updates(scene, params, s)[0] if scene.effects else None
        return accelerations(scene, params, s.phys, inputs, held)
    return jax.vmap(at)(states)


def single_env_scene(scene: Scene) -> Scene:
    """The scene as ``simulate`` runs it: one environment, ``segment_sum`` accumulation.

    Built scenes already use ``segment_sum``; a scene switched to the dense ``matmul``
    accumulation by hand is switched back, since for a single environment the scatter is
    faster (BENCHMARKS.md, section b). The physics is the same up to the order of
    floating-point additions.
    """
    return dataclasses.replace(scene, accumulate="segment_sum")


def _stepped_run(scene: Scene, params: Params, state: State, run, times, progress, chunk: int, policy):
    """Fixed steps in jitted chunks of ``chunk`` outputs, checked after each chunk. Returns
    the saved states (host arrays, the finite rows) and ``(row, reason)`` or None."""
    every = steps_per_output(scene, run)
    n_out = len(times) - 1
    if 0 < n_out < chunk:          # one chunk: the next power of two, not a whole chunk
        chunk = 1 << (n_out - 1).bit_length()
    pieces = [jax.tree.map(lambda a: np.asarray(a)[None], state)]
    failure = _non_finite(scene, pieces[0], times, 0)
    done = 0
    bar = _progress(n_out, progress, scene, run.name)
    while done < n_out and failure is None:
        state, traj = _advance(scene, params, state, chunk * every, every, policy)
        take = min(chunk, n_out - done)
        piece = jax.tree.map(lambda a: np.asarray(a)[:take], traj)
        failure = _non_finite(scene, piece, times, done + 1)
        if failure is not None:
            take = failure[0] - (done + 1)
        pieces.append(jax.tree.map(lambda a: a[:take], piece))
        done += take
        if bar is not None:
            bar.update(take)
    if bar is not None:
        bar.close()
    return jax.tree.map(lambda *xs: np.concatenate(xs, axis=0), *pieces), failure


def _adaptive_run(scene: Scene, params: Params, state: State, times, progress):
    """One diffrax solve on the output grid. Returns the saved states and ``(row, reason)``
    or None (also when the solver gives up)."""
    ts = jnp.asarray(times, dtype=scene.dtype)
    ys, result, n_steps = _solve_on_grid(scene, params, state.phys, ts, bool(progress))
    # row 0 is the initial state itself; a solve that gives up on its first output
    # interval leaves every saved row unfilled (inf), that one included
    phys = jax.tree.map(lambda y, y0: np.concatenate([np.asarray(y0, np.asarray(y).dtype)[None],
                                                      np.asarray(y)[1:]]), ys, state.phys)
    states = State(phys=phys, time=times.astype(phys.point_pos.dtype))
    failure = _non_finite(scene, states, times, 0)
    if result != diffrax.RESULTS.successful:
        row = failure[0] if failure is not None else len(times)
        failure = (row, (
            f"the adaptive solver ({scene.integrator}) gave up after t = {times[max(row - 1, 0)]:g} s and "
            f"{int(n_steps):,} steps: {diffrax.RESULTS[result]} This happens when the state turns non-finite "
            "(every step is then rejected) or when rtol / atol ask for more steps than sim.max_steps = "
            f"{scene.max_steps:,}: raise sim.max_steps, loosen sim.rtol / sim.atol, or look for forces "
            "that blow up. The saved states before that time are kept."))
    return states, failure


def simulate(scene: Scene, params: Params, state: State, run, progress: bool = True, chunk: int = 200,
             policy=None) -> Trajectory:
    """Run the scene from ``state`` to ``run.t_end``, saving every ``run.output_dt``
    (``run``: :class:`~mysim_jax.config.scene.RunSettings`, e.g. ``config.run_settings()``; it is
    not part of the physics: it sets how many steps run and which are saved).

    Fixed-step integrators run as jitted ``lax.scan`` chunks of ``chunk`` outputs with a
    progress bar between chunks (a run of fewer outputs runs one chunk of the next power
    of two, so a short run does not pay for a whole chunk); adaptive solvers run as one
    diffrax solve (with diffrax's progress meter). Scenes with quadrotors always step (their controller acts once per
    step). Accelerations are evaluated exactly at the saved states, with the actuator
    inputs the controller holds from there.

    The run is watched: after each chunk (or the solve) the saved states, controller
    memory and accelerations are checked for NaN and inf. At the first non-finite row the
    run stops and the :class:`Trajectory` keeps the rows before it, with ``failure``
    naming the time interval, the points or bodies concerned and what to try; an
    adaptive solve that gives up (``max_steps``) is reported the same way.

    ``policy(scene, params, state) -> control`` gives the control of every step (see
    :func:`rollout`); it is a static argument of the compiled run, so it must be
    hashable (a frozen dataclass, or a module-level function).

    The compiled functions are cached per Scene (``params`` and ``state`` are arguments,
    not constants): a second call with new params or a new state does not recompile, nor
    does another ``t_end`` with as many chunks of the same size.
    This runs one environment, so the scene is run as :func:`single_env_scene` makes it.
    """
    scene = single_env_scene(scene)
    times = output_times(run)
    if scene.integrator in FIXED_STEP or scene.quadrotor is not None or scene.effects:
        states, failure = _stepped_run(scene, params, state, run, times, progress, chunk, policy)
    else:
        states, failure = _adaptive_run(scene, params, state, times, progress)
    n_kept = len(times) if failure is None else failure[0]
    states = jax.tree.map(lambda a: a[:n_kept], states)
    acc = jax.tree.map(np.asarray, _accelerations_on_grid(scene, params, jax.tree.map(jnp.asarray, states), policy))
    bad = _first_non_finite_row(acc)
    if bad is not None:
        failure = (bad, f"the acceleration turned non-finite at t = {times[bad]:g} s: "
                        f"{_describe(scene, acc, bad)}. The rows before are kept. Usual causes: forces so "
                        "large they overflow (check stiffnesses, gains and loads)")
        n_kept = bad
    keep = lambda a: a[:n_kept]   # noqa: E731
    return Trajectory(time=times[:n_kept], phys=jax.tree.map(keep, states.phys), acc=jax.tree.map(keep, acc),
                      controller=None if states.controller is None else jax.tree.map(keep, states.controller),
                      failure=None if failure is None else failure[1],
                      effects=jax.tree.map(keep, states.effects) if states.effects else None)


def _first_non_finite_row(tree) -> int | None:
    """Index of the first row (leading axis) of any float leaf holding NaN or inf, or None."""
    first = None
    for leaf in jax.tree.leaves(tree):
        leaf = np.asarray(leaf)
        if not np.issubdtype(leaf.dtype, np.floating) or leaf.size == 0:
            continue
        bad = ~np.isfinite(leaf.reshape(leaf.shape[0], -1)).all(axis=1)
        if bad.any():
            row = int(np.argmax(bad))
            first = row if first is None else min(first, row)
    return first


def _describe(scene: Scene, rows, row: int, memory=None, limit: int = 6) -> str:
    """The points and bodies (and which of their quantities) that are non-finite in ``row``
    of a stacked PhysState or Accelerations ``rows``; else the controller memory fields."""
    found: dict[str, list[str]] = {}
    for field in rows.__dataclass_fields__:
        kind, quantity = field.split("_", 1)
        names = scene.point_names if kind == "point" else scene.body_names
        if not names:
            continue
        values = np.asarray(getattr(rows, field))[row].reshape(len(names), -1)
        for i in np.flatnonzero(~np.isfinite(values).all(axis=1)):
            found.setdefault(f"{kind} '{names[i]}'", []).append(quantity)
    parts = [f"{who} ({', '.join(what)})" for who, what in list(found.items())[:limit]]
    if len(found) > limit:
        parts.append(f"and {len(found) - limit} more")
    if not parts and memory is not None:
        fields = [f for f in memory.__dataclass_fields__
                  if np.asarray(getattr(memory, f)).dtype.kind == "f"
                  and not np.isfinite(np.asarray(getattr(memory, f))[row]).all()]
        parts = [f"the controller memory ({', '.join(fields)})"]
    return "non-finite values in " + ", ".join(parts)


def _non_finite(scene: Scene, states: State, times, first_row: int):
    """``(output row, message)`` of the first saved state in ``states`` (output rows
    ``first_row, first_row + 1, ...``) with a NaN or inf anywhere, or None."""
    row = _first_non_finite_row((states.phys, states.controller))
    if row is None:
        return None
    where = _describe(scene, states.phys, row, states.controller)
    out = first_row + row
    when = f"at t = {times[0]:g} s" if out == 0 else f"between t = {times[out - 1]:g} s and {times[out]:g} s"
    return out, (
        f"the state turned non-finite {when}: {where}. The rows before are kept. Usual causes: a step "
        "too large for the motion (try a smaller sim.dt, more sim.substeps, or an adaptive integrator), "
        "forces so large they overflow (check stiffnesses, gains and loads), or, with an adaptive "
        "integrator stepping a controlled scene, a step on which the solver gave up (sim.max_steps)")


def _progress(total: int, enabled: bool, scene: Scene, name: str):
    if not enabled:
        return None

    return tqdm(total=total, desc=f"{name} ({scene.integrator})", unit="out", leave=False)
