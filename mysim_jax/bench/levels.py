"""What a catch looks like at each fidelity level: the quantities a level must keep close.

A cheaper level of the capture scene (``levels:`` in its YAML) is only useful if the catch
it simulates is the catch of ``full``. :func:`catch_measures` flies the scripted team
through the same episodes (the same spawns, masses and wind, drawn from one key) at a
level and records, per policy step, what the capture depends on:

* the **target**'s position, and the **net centre** (the mean of the knots nearest the
  net's middle: one knot for an odd number per side, four for an even one);
* the net's **sag**: the mean height of the tethered corner knots above the net centre;
* the net's **size**: the mean distance between the tethered corner knots that are
  neighbours around the net's outline;
* the **tether tension**: the largest over the tethers of the tension in each tether's
  knot end segment (the scene's spring law at the state's positions and velocities);
* whether the target **touches** the net (the environment's own check).

:func:`summarize` reduces one episode's rows to the numbers BENCHMARKS.md (i) compares:
the sag and size when the target first touches the net, the target's **stopping
distance** (its height at first touch minus the lowest it reaches afterwards), the peak
tether tension over the episode, and (against the same episode at another level) the RMS
and largest distance between the two target trajectories and the two net-centre
trajectories over the steps both episodes last.

Run both levels at the same policy rate, a multiple of both control periods (the tension
of a line rings faster than a 10 Hz team looks), so that rows pair step by step.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.core import batching
from mysim_jax.dynamics.forces import spring_tension
from mysim_jax.dynamics.markers import node_states
from mysim_jax.tasks.episode import episode_rollout
from mysim_jax.tasks.evaluate import scripted_policy

CATCH_EPISODES = 32     # scripted catches recorded per level (BENCHMARKS.md (i))
CATCH_RATE = 50.0       # Hz: their policy rate, a multiple of every level's control period
CATCH_SEED = 2025       # the draw they come from


def _net_layout(env, net):
    """Static indices: centre knots (points), tethered corner knots (points), tether end
    springs, neighbouring corner pairs around the outline."""
    scene = env.scene
    g = net.knots
    mid = [g // 2] if g % 2 else [g // 2 - 1, g // 2]
    centre = [scene.point_names.index(net.knot_name(i, j)) for i in mid for j in mid]
    knots = net.tether_knots()
    corners = [scene.point_names.index(net.knot_name(*k)) for k in knots]
    springs = [scene.spring_names.index(f"{net.name}_t{n}[0]") for n in range(len(knots))]
    n = len(corners)
    around = [(i, (i + 1) % n) for i in range(n)] if n > 2 else [(0, 1)] if n == 2 else []
    return np.asarray(centre), np.asarray(corners), np.asarray(springs), around


def catch_measures(env, params, net, key, n_episodes: int, chunk: int = 8) -> dict[str, np.ndarray]:
    """Per-step rows ``(n_episodes, max_steps, ...)`` of the module docstring (``net``: the
    scene's NetConfig, whose knots and tethers are measured) for the scripted team's
    episodes ``0 .. n_episodes − 1`` drawn from ``key`` (as
    :func:`~mysim_jax.tasks.evaluate.run_episodes` draws them; each is one
    :func:`~mysim_jax.tasks.episode.episode_rollout`, its saved states reduced step by
    step): ``target`` and ``centre`` ``(..., 3)`` [m], ``sag``, ``size``, ``tension``
    [N], ``touching`` and ``done``."""
    if net is None or net.tethers is None:
        raise ValueError("catch_measures: the scene has no tethered net")
    centre, corners, springs, around = _net_layout(env, net)
    scene = env.scene
    end_a = np.asarray(scene.spring_node_a, np.int32)[springs]
    end_b = np.asarray(scene.spring_node_b, np.int32)[springs]
    tension_only = tuple(np.asarray(scene.spring_tension_only)[springs])
    pair_a = np.asarray([a for a, _ in around], np.int32)
    pair_b = np.asarray([b for _, b in around], np.int32)

    def measure(sim_params, phys):
        knots = phys.point_pos[corners]
        mid = jnp.mean(phys.point_pos[centre], axis=0)
        node_pos, node_vel = node_states(scene, sim_params, phys)
        d = node_pos[end_b] - node_pos[end_a]
        length = jnp.linalg.norm(d, axis=-1)
        rate = jnp.sum((node_vel[end_b] - node_vel[end_a]) * d, axis=-1) / jnp.maximum(length, 1e-12)
        tension = spring_tension(sim_params.spring_stiffness[springs], sim_params.spring_damping[springs],
                                 sim_params.spring_rest_length[springs], length, rate, tension_only)
        size = (jnp.mean(jnp.linalg.norm(knots[pair_b] - knots[pair_a], axis=-1)) if len(around)
                else jnp.zeros((), knots.dtype))
        return {"target": phys.body_pos[env.target_body], "centre": mid,
                "sag": jnp.mean(knots[:, 2]) - mid[2], "size": size, "tension": jnp.max(tension)}

    def episode(index):
        _, sim_params, rows = episode_rollout(env, params, scripted_policy(env), key, index)
        out = jax.vmap(lambda phys: measure(sim_params, phys))(rows["sim"].phys)
        out.update(touching=rows["touching"], done=rows["done"])
        return out

    run = jax.jit(batching.vmap(episode, chunk=chunk))
    return jax.tree.map(np.asarray, run(jnp.arange(n_episodes)))


@dataclass
class CatchSummary:
    """One episode's catch (module docstring); NaN where the target never touched."""

    length: int                 # policy steps up to and including the first ``done``
    touched: bool
    sag: float                  # [m] at first touch
    size: float                 # [m] at first touch
    stopping_distance: float    # [m]
    peak_tension: float         # [N] over the episode


def summarize(rows: dict[str, np.ndarray], episode: int) -> CatchSummary:
    """:class:`CatchSummary` of episode ``episode`` of :func:`catch_measures`' rows."""
    done = np.flatnonzero(rows["done"][episode])
    n = int(done[0]) + 1 if done.size else rows["done"].shape[1]
    touching = rows["touching"][episode, :n]
    z = rows["target"][episode, :n, 2]
    first = np.flatnonzero(touching)
    if first.size == 0:
        nan = float("nan")
        return CatchSummary(n, False, nan, nan, nan, float(rows["tension"][episode, :n].max()))
    f = int(first[0])
    return CatchSummary(n, True, float(rows["sag"][episode, f]), float(rows["size"][episode, f]),
                        float(z[f] - z[f:].min()), float(rows["tension"][episode, :n].max()))


def trajectory_difference(rows: dict[str, np.ndarray], reference: dict[str, np.ndarray], episode: int,
                          what: str) -> tuple[float, float]:
    """RMS and largest distance [m] between ``what`` (``target`` or ``centre``) of episode
    ``episode`` in ``rows`` and in ``reference``, over the steps both episodes last."""
    def length(r):
        done = np.flatnonzero(r["done"][episode])
        return int(done[0]) + 1 if done.size else r["done"].shape[1]

    n = min(length(rows), length(reference))
    dist = np.linalg.norm(rows[what][episode, :n] - reference[what][episode, :n], axis=-1)
    return float(np.sqrt(np.mean(dist ** 2))), float(dist.max())


def catch_table(measures: dict[str, dict[str, np.ndarray]], rate: float = CATCH_RATE,
                seed: int = CATCH_SEED) -> list[str]:
    """Markdown lines comparing the levels' catches side by side (``measures``: level ->
    :func:`catch_measures` rows of the same episodes, ``full`` among them): medians over
    the episodes in which the target touched the net, and each level's trajectory
    difference to ``full``."""
    def med(values):
        values = np.asarray([v for v in values if np.isfinite(v)], float)
        return float(np.median(values)) if values.size else float("nan")

    n = next(iter(measures.values()))["done"].shape[0]
    lines = [
        f"What the capture depends on, level by level: the scripted team's episodes 0–{n - 1} of one draw "
        f"(seed {seed}) at a policy rate of {rate:g} Hz (rows every {1e3 / rate:g} ms, a multiple of every "
        "level's control period), the same episodes at every level (`mysim_jax/bench/levels.py`). Medians over the "
        "episodes in which the target touched the net: the net's sag (tethered corner knots' mean height above the "
        "net centre) and size (mean distance between neighbouring tethered corners) when the target first touches "
        "it, the target's stopping distance (its height at first touch minus the lowest it reaches afterwards), "
        "and the peak tether tension of the episode; then the RMS and the largest distance between each level's "
        "target and net-centre trajectories and `full`'s over the steps both episodes last (median over episodes).",
        "",
        "| level | touched | sag at first touch [m] | size at first touch [m] | stopping distance [m] | "
        "peak tether tension [N] | target vs full, RMS / max [m] | net centre vs full, RMS / max [m] |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for level, rows in measures.items():
        s = [summarize(rows, e) for e in range(n)]
        touched = [x for x in s if x.touched]
        if level == "full":
            diffs = "– | –"
        else:
            t = [trajectory_difference(rows, measures["full"], e, "target") for e in range(n)]
            c = [trajectory_difference(rows, measures["full"], e, "centre") for e in range(n)]
            diffs = (f"{med([x[0] for x in t]):.3f} / {med([x[1] for x in t]):.3f} | "
                     f"{med([x[0] for x in c]):.3f} / {med([x[1] for x in c]):.3f}")
        lines.append(f"| {level} | {len(touched)} of {n} | {med([x.sag for x in touched]):.3f} | "
                     f"{med([x.size for x in touched]):.3f} | {med([x.stopping_distance for x in touched]):.3f} | "
                     f"{med([x.peak_tension for x in touched]):.2f} | {diffs} |")
    return lines
