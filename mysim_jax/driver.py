"""The host-side driver of whole runs: :func:`simulate` runs a scene to ``t_end`` on its
output grid and returns a :class:`~mysim_jax.core.types.Trajectory`.

It drives the pure pipeline of :mod:`mysim_jax.sim` (``rollout`` in jitted chunks, or one
adaptive diffrax solve), shows a progress bar between chunks, checks every chunk for NaN
and inf (stopping at the first non-finite row with a message naming the points or bodies
and what to try), and evaluates the accelerations at the saved states. This is the one
place the library calls ``jax.jit`` itself.
"""

from __future__ import annotations

from functools import partial

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from mysim_jax.core.types import Params, PhysState, Scene, State, Trajectory
from mysim_jax.dynamics.integrators import FIXED_STEP
from mysim_jax.dynamics.quaternion import quat_normalize
from mysim_jax.sim import adaptive_solution, has_step_updates, held_accelerations, rollout, step_updates


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
    sol = adaptive_solution(scene, params, phys, ts[0], ts[-1], ts, progress)
    return sol.ys.replace(body_quat=quat_normalize(sol.ys.body_quat)), sol.result, sol.stats["num_steps"]


@partial(jax.jit, static_argnums=(0, 3))
def _accelerations_on_grid(scene: Scene, params: Params, states: State, policy=None):
    """Accelerations at stacked states, with what the controller and the effects hold
    from there (the updates a step would run from each state, :func:`~mysim_jax.sim.step_updates`)."""
    def at(s):
        held, _ = step_updates(scene, params, s, None if policy is None else policy(scene, params, s))
        return held_accelerations(scene, params, s.phys, held)
    return jax.vmap(at)(states)


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
            f"{scene.solver_max_steps:,}: raise sim.max_steps, loosen sim.rtol / sim.atol, or look for forces "
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
    diffrax solve (with diffrax's progress meter). Scenes with updates at the start of every
    step (a controller, effects, a contact broad phase: :func:`~mysim_jax.sim.has_step_updates`)
    always step. Accelerations are evaluated exactly at the saved states, with the actuator
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
    """
    times = output_times(run)
    if scene.integrator in FIXED_STEP or has_step_updates(scene):
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
