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

:func:`section_i` (BENCHMARKS.md (i)) sets the levels side by side: team steps/s at several
batch sizes (all levels timed in one round-robin), sub-steps per team step, memory per
environment, the scripted team's success on the same episodes at every level with the
paired difference to ``full``, and :func:`catch_table` of the catches.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from mysim_jax.bench.environment import env_call, env_variant
from mysim_jax.bench.report import CAPTURE_ENV, level_targets_text
from mysim_jax.bench.timing import contention_note, median, time_round_robin, wait_for_quiet
from mysim_jax.config.overrides import override_list
from mysim_jax.config.scene import load_config
from mysim_jax.core import batching
from mysim_jax.dynamics.forces import spring_tension
from mysim_jax.dynamics.markers import node_states
from mysim_jax.tasks.capture import make_env
from mysim_jax.tasks.episode import episode_rollout
from mysim_jax.tasks.evaluate import run_episodes, scripted_policy
from mysim_jax.tasks.sweep import paired_difference_interval

CATCH_EPISODES = 32     # scripted catches recorded per level (BENCHMARKS.md (i))
CATCH_RATE = 50.0       # Hz: their policy rate, a multiple of every level's control period
CATCH_SEED = 2025       # the draw they come from

LEVEL_BATCHES = (256, 1024, 4096)
LEVEL_EPISODES = 1000         # scripted episodes per level, the same draws for every level
LEVEL_CALL_S = 1.0            # a timed call repeats a level's team step until it lasts about this long


def target_lines(rows: dict) -> list[str]:
    """The section's target line (:func:`~mysim_jax.bench.report.level_targets_text`)."""
    text = level_targets_text(rows, "MET", "NOT MET")
    return ["", f"**Targets at B = 1024, 10 Hz: {text}**."] if text else []


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


def _level_outcomes(env, params, n_episodes: int, seed: int = 2024):
    """Success and failure flags of the scripted team's episodes ``0 .. n − 1`` drawn from
    ``seed`` (:func:`mysim_jax.tasks.evaluate.run_episodes`: the same spawns, masses and
    wind at every level, so outcomes pair episode by episode)."""
    return run_episodes(env, params, scripted_policy(env), n_episodes, min(n_episodes, 1024),
                        jax.random.PRNGKey(seed), progress=False)


def _repeated(call, seconds: float):
    """``call`` repeated so that one timed call lasts about ``seconds`` (one warm-up call
    measures it); returns ``(fn, repeats)``."""
    jax.block_until_ready(call())
    t0 = time.perf_counter()
    jax.block_until_ready(call())
    n = max(1, round(seconds / max(time.perf_counter() - t0, 1e-9)))
    return (lambda: [call() for _ in range(n)]), n


def section_i(cfg, results) -> list[str]:
    """(i) Fidelity levels of the capture scene side by side (10 Hz policy): team steps/s,
    sub-steps, memory, the scripted team's success paired with ``full``'s, and what a catch
    looks like at each level (:func:`catch_table`)."""
    base = load_config(CAPTURE_ENV)
    names = ["full"] + list(base.levels)
    batches = (16, 64) if cfg.quick else LEVEL_BATCHES
    n_eps = 16 if cfg.quick else LEVEL_EPISODES
    n_catch = 4 if cfg.quick else CATCH_EPISODES
    top = 1024 if 1024 in batches else batches[-1]
    calls, envs, rows, outcomes, measures = {}, {}, {}, {}, {}
    for level in tqdm(names, desc="(i) levels: compile", leave=False):
        envs[level] = env_variant(override_list(level=level, then={"env.policy_rate": 10.0}))
        for b in batches:
            calls[level, b] = env_call(*envs[level], b, 1)
    timed, repeats = {}, {}
    for key, c in calls.items():
        timed[key], repeats[key] = _repeated(c.call, 0.05 if cfg.quick else LEVEL_CALL_S)
    wait_for_quiet(cfg.max_wait_s, "i")
    # every level and batch in one round-robin: the ratio to full is measured side by side
    times = time_round_robin(timed, cfg.env_repeats, section="i")
    for level in tqdm(names, desc="(i) levels: episodes", leave=False):
        env, params = envs[level]
        stats = _level_outcomes(env, params, n_eps)
        outcomes[level] = stats.success
        rec_config = load_config(CAPTURE_ENV, override_list(level=level, then={"env.policy_rate": CATCH_RATE}))
        rec_env, rec_params = make_env(rec_config)
        measures[level] = catch_measures(rec_env, rec_params, rec_config.net, jax.random.PRNGKey(CATCH_SEED), n_catch)
        rows[level] = dict(substeps=env.control_steps * env.scene.substeps, points=env.scene.n_points,
                           dt=env.scene.dt, sub=env.scene.substeps,
                           rate={b: b * repeats[level, b] / median(times[level, b]) for b in batches},
                           memory={b: calls[level, b].bytes_per_env() for b in batches},
                           success=stats.success.mean(), bad=int(stats.failures["non_finite"].sum()))
    results["levels"] = rows
    lines = [
        "## (i) Fidelity levels of the capture scene",
        "",
        "`configs/capture_env_falling.yaml` at each of its levels (`--set level=NAME`; `full` is the file's own "
        "values, the others are listed and explained under `levels:` in the file), with the policy at 10 Hz "
        "(`env.policy_rate=10`). Team steps/s as in (e): one call = one `CaptureEnv.step` of B environments "
        f"(scripted team), repeated within a timed call until the call lasts ~{LEVEL_CALL_S:g} s; every level and "
        f"batch timed in one round-robin (median of {cfg.env_repeats} rounds), so the ratio to `full` is measured "
        f"side by side. Scripted success: episodes 0–{n_eps - 1} of one draw (seed 2024), run to their end at "
        "every level (the same spawns, masses and wind), so the difference to `full` is paired episode by episode "
        "(95 % interval, `tasks.sweep.paired_difference_interval`). Non-finite: episodes that ended with a "
        "non-finite state.",
        "",
        "| level | point masses | control period / sub-steps | sub-steps per team step | "
        + " | ".join(f"team steps/s B = {b}" for b in batches) + f" | × full (B = {top}) | memory/env [KiB] (B = {top}) "
        f"| scripted success ({n_eps} episodes) | paired difference to full [points] | non-finite |",
        "|---|---:|---:|---:|" + "---:|" * len(batches) + "---:|---:|---:|---:|---:|",
    ]
    for level, r in rows.items():
        diff = ("–" if level == "full" else
                "{:+.1f} ({:+.1f} to {:+.1f})".format(*(100 * x for x in
                                                          paired_difference_interval(outcomes[level], outcomes["full"]))))
        lines.append(f"| {level} | {r['points']} | {r['dt'] * 1e3:g} ms / {r['sub']} | {r['substeps']:,} | "
                     + " | ".join(f"{r['rate'][b]:,.0f}" for b in batches)
                     + f" | {r['rate'][top] / rows['full']['rate'][top]:.1f}× | {r['memory'][top] / 1024:.1f} | "
                     f"{r['success']:.1%} | {diff} | {r['bad']} |")
    lines += target_lines(rows)
    lines += ["", *catch_table(measures)]
    return lines + ["", contention_note("i", cfg.env_repeats), ""]
