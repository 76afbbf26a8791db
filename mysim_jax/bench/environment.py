"""The capture environment's throughput: section (e) of BENCHMARKS.md.

:func:`env_call` AOT-compiles ``jit(vmap(...))`` of ``CaptureEnv`` team steps (or of the
physics alone, its control periods with the setpoint held) over a batch of environments
reset from distinct keys; sections (i) and (j) time it too. :func:`section_e` times the
scripted team's steps at each batch size (batch-last and ``jax.vmap`` side by side) and,
at one batch size, where a team step's time goes: the environment against the physics
alone, and the physics without one stage at a time (contact, friction, drag, wind).
"""

from __future__ import annotations

from functools import partial
from typing import Callable

import jax
from tqdm.auto import tqdm

from mysim_jax.bench.report import CAPTURE_ENV
from mysim_jax.bench.timing import (
    Compiled, ThroughputRow, aot_compile, contention_note, median, spread, time_round_robin, wait_for_quiet,
)
from mysim_jax.config.scene import load_config
from mysim_jax.control.setpoint import setpoint_from_action
from mysim_jax.core import batching
from mysim_jax.sim import step
from mysim_jax.tasks.capture import make_env
from mysim_jax.tasks.evaluate import scripted_policy
from mysim_jax.tasks.runner import rollout, shared_key


def env_call(env, params, batch: int, n_steps: int, kind: str = "env", vmap: Callable = batching.vmap,
             compiler_options: dict | None = None):
    """AOT-compiled ``jit(vmap(...))`` over ``batch`` environments reset from distinct keys
    (``vmap``: the library's batch-last ``mysim_jax.core.batching.vmap`` or ``jax.vmap``):
    ``kind="env"``: ``n_steps`` team steps (the episode runner,
    :func:`mysim_jax.tasks.runner.rollout`, with the scripted team's actions, each step's
    key to the environment); ``kind="control"``: ``n_steps`` control periods of the physics alone
    (:func:`mysim_jax.sim.step` with the scripted team's setpoint held). Returns a Compiled."""
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    obs, states = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)

    def run_env(key, obs, state):
        if kind == "env":
            (_, state, _), _ = rollout(env, params, scripted_policy(env), obs, state, jax.random.split(key, n_steps),
                                       keys=shared_key)
            return state
        sim_params = env.episode_params(params, state.episode)
        sp = setpoint_from_action(env.scene, sim_params, env.scripted_actions(state, params))

        def period(s, _):
            return step(env.scene, sim_params, s, sp), None
        return jax.lax.scan(period, state.sim, None, length=n_steps)[0]

    if vmap is batching.vmap:      # the library's batched path: cache-sized blocks of environments
        vmap = partial(batching.vmap, chunk=batching.chunk_for(jax.tree.map(lambda x: x[0], states)))
    compiled, compile_s, memory = aot_compile(jax.jit(vmap(run_env)), keys, obs, states,
                                              compiler_options=compiler_options)
    return Compiled(kind, batch, n_steps, lambda: compiled(keys, obs, states), compile_s, memory)


def env_variant(overrides: list[str]):
    """``(env, params)`` of ``configs/capture_env_falling.yaml`` with ``overrides`` (``--set`` style)."""
    return make_env(load_config(CAPTURE_ENV, overrides))


def section_e(cfg, results) -> list[str]:
    """(e) The capture environment's team steps/s at each of ``cfg.env_batches`` and where a
    team step's time goes."""
    env, params = env_variant([])
    rows, first_rows = _time_batches(cfg, env, params)
    results["env_rows"] = rows
    results["env_first_rows"] = first_rows
    results["env_rate_level"] = (1.0 / env.policy_dt, env.level)     # what a team step is here

    # where the time goes, at B = 256: the physics alone (control periods), and variants
    # of the scene with one stage removed
    pb = 256 if not cfg.quick else 16
    n = env.control_steps
    variants = _stage_variants(n)
    t, substeps, auto_no_contact = _time_stages(cfg, env, params, variants, pb)
    results["env_profile"] = t

    per_sub = t["physics"] / (pb * n * substeps["physics"])
    return (_batch_table(cfg, env, params, rows, first_rows) + _stage_table(cfg, env, rows, pb, variants, t)
            + _stage_findings(cfg, env, pb, t, per_sub, auto_no_contact))


def _time_batches(cfg, env, params) -> tuple[list[ThroughputRow], dict[int, ThroughputRow]]:
    """The scripted team's steps at each batch size, batch-last, and with ``jax.vmap`` up to
    ``cfg.env_first_max_batch``: ``(rows, jax.vmap rows by batch)``."""
    rows: list[ThroughputRow] = []
    first_rows: dict[int, ThroughputRow] = {}
    bar = tqdm(total=len(cfg.env_batches), desc="(e) capture env", leave=False)
    for b in cfg.env_batches:
        k = max(1, int(round(32 / b)))          # about 32 team steps per call (one at B >= 64)
        calls = {"env": env_call(env, params, b, k)}
        if b <= cfg.env_first_max_batch:        # the batch-first path, side by side
            calls["first"] = env_call(env, params, b, k, vmap=jax.vmap)
        wait_for_quiet(cfg.max_wait_s, "e")
        times = time_round_robin({key: c.call for key, c in calls.items()}, cfg.env_repeats, section="e")
        rows.append(ThroughputRow(f"{b}", b, k, times["env"], calls["env"].compile_s, calls["env"].bytes_per_env()))
        if "first" in calls:
            first_rows[b] = ThroughputRow(f"{b}", b, k, times["first"], calls["first"].compile_s,
                                          calls["first"].bytes_per_env())
        bar.update(1)
    bar.close()
    return rows, first_rows


def _stage_variants(n: int) -> dict[str, tuple[str, list[str], str]]:
    """The rows of where a team step's time goes: ``key -> (label, overrides, kind)``, ``kind``
    as in :func:`env_call`; ``n`` control periods per team step."""
    return {
        "env": ("the environment's team step (scripted team, rewards, checks, auto-reset)", [], "env"),
        "physics": (f"the physics alone: {n} control periods with the setpoint held", [], "control"),
        "no_contact": ("physics without contact (`contact: null`)", ["contact=null"], "control"),
        "no_line_contact": ("physics without the target–line capsule pairs",
                            ["contact.pairs=[[target, uavs], [uavs, uavs], [target, ground], [net, ground], "
                             "[uavs, ground]]"], "control"),
        "no_friction": ("physics without contact friction (`contact.friction: null`)", ["contact.friction=null"],
                        "control"),
        "no_drag": ("physics without line drag (`net.line.drag_coefficient=0`, tethers too)",
                    ["net.line.drag_coefficient=0", "net.tethers.line.drag_coefficient=0"], "control"),
        "no_target_drag": ("physics without the target's air drag (`target.drag_coefficient=0`)",
                           ["target.drag_coefficient=0"], "control"),
        "no_wind": ("physics without wind (`env.randomize.wind_force: null`)", ["env.randomize.wind_force=null"], "control"),
    }


def _time_stages(cfg, env, params, variants, pb: int):
    """Time every variant at batch ``pb`` round-robin (the physics variants at the scene's
    sub-step): ``(median call [s] by key, sub-steps per period by key, the sub-steps
    ``substeps: auto`` would choose without contact)``."""
    scene = env.scene
    n = env.control_steps
    calls, compiled, substeps = {}, {}, {}
    same = [f"sim.substeps={scene.substeps}"]      # every variant at the scene's sub-step
    for key, (_, overrides, kind) in variants.items():
        e, p = (env, params) if not overrides else env_variant(overrides + same)
        c = env_call(e, p, pb, 1 if kind == "env" else n, kind)   # batch-last
        calls[key], compiled[key], substeps[key] = c.call, c, e.scene.substeps
    auto_no_contact = env_variant(["contact=null"])[0].scene.substeps
    wait_for_quiet(cfg.max_wait_s, "e")
    times = time_round_robin(calls, cfg.env_repeats, section="e")
    t = {k: median(v) for k, v in times.items()}
    return t, substeps, auto_no_contact


def _batch_table(cfg, env, params, rows, first_rows) -> list[str]:
    """Section (e)'s heading, what one call is, and its row at each batch size."""
    scene = env.scene
    lines = [
        "## (e) Capture environment",
        "",
        f"`configs/capture_env_falling.yaml` (float32, {scene.n_points} point masses, {scene.n_springs} springs, "
        f"4 quadrotors and the target, contact, line drag; {env.control_steps} control periods of "
        f"{scene.dt * 1e3:g} ms per team step at {1.0 / env.policy_dt:g} Hz, the scene's own rate, on its level "
        f"`{env.level}`, {scene.substeps} semi-implicit Euler sub-steps each). "
        "One call = `jax.jit(mysim_jax.core.batching.vmap(run_env, chunk=c))(keys, states)` (batch axis last, in blocks of "
        f"c = `batching.chunk_for(state)` = {batching.chunk_for(env.reset(jax.random.PRNGKey(0), params)[1])} environments when B is larger) with `run_env` a `lax.scan` of K "
        "`CaptureEnv.step` calls whose actions are the scripted team's (`CaptureEnv.scripted_actions`): "
        "B environments reset from distinct keys, so their spawns, masses and wind differ; auto-reset "
        f"included. Team steps/s = B·K / median of {cfg.env_repeats} timed calls after one warm-up call. Memory "
        "per env = (arguments + outputs + temporaries − aliased) of the compiled call / B.",
        "",
        "| batch B | K team steps/call | team steps/s | control periods/s | physics sub-steps/s | median call [s] "
        "| spread | compile [s] | memory/env [KiB] | `jax.vmap` team steps/s | batch-last / `jax.vmap` |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        v = r.env_steps_per_s
        f = first_rows.get(r.batch)
        cmp = f"{f.env_steps_per_s:,.1f} | {v / f.env_steps_per_s:.2f}×" if f is not None else "– | –"
        lines.append(f"| {r.batch} | {r.n_steps} | {v:,.1f} | {v * env.control_steps:,.0f} | "
                     f"{v * env.control_steps * scene.substeps:,.0f} | {median(r.times):.3f} | {spread(r.times)} | "
                     f"{r.compile_s:.1f} | {r.bytes_per_env / 1024:.1f} | {cmp} |")
    return lines


def _stage_table(cfg, env, rows, pb: int, variants, t) -> list[str]:
    """The target line, and the table of where a team step's time goes."""
    scene = env.scene
    top = rows[-1]
    lines = [
        "",
        f"The fidelity levels' speed targets are section (i)'s (at 10 Hz); at B = {top.batch} this section's "
        f"environment runs {top.env_steps_per_s:,.1f} team steps/s.",
        "",
        f"`jax.vmap` rows are timed only up to B = {cfg.env_first_max_batch} (at B = 4096 one batch-first call "
        "takes minutes).",
        "",
        f"### Where a team step's time goes (B = {pb})",
        "",
        "All rows timed round-robin in one loop; a row's time is per batched call (B environments). "
        "Physics rows run the control periods of one team step with the scripted team's setpoint held, all "
        f"at the scene's {scene.substeps} sub-steps per period.",
        "",
        "| variant | median call [s] | vs physics |",
        "|---|---:|---:|",
    ]
    for key, (label, _, _) in variants.items():
        lines.append(f"| {label} | {t[key]:.3f} | {t[key] / t['physics']:.2f}× |")
    return lines


def _stage_findings(cfg, env, pb: int, t, per_sub: float, auto_no_contact: int) -> list[str]:
    """Section (e)'s contention note and findings."""
    scene = env.scene
    lines = [
        "",
        contention_note("e", cfg.env_repeats),
        "",
        "### Findings",
        "",
        f"- A team step is {env.control_steps} control periods × {scene.substeps} physics sub-steps = "
        f"{env.control_steps * scene.substeps} sub-steps of the whole multibody system; the physics alone runs "
        f"{1.0 / per_sub:,.0f} sub-steps/s at B = {pb} ({per_sub * 1e6:.2f} µs per environment and sub-step).",
        f"- The environment's own work (team policy, rewards, checks, observations, auto-reset) adds "
        f"{100 * (t['env'] / t['physics'] - 1):.0f}% to the physics of a team step.",
        f"- Contact costs {100 * (1 - t['no_contact'] / t['physics']):.0f}% of the physics at the same sub-step "
        f"(without it a sub-step is {t['physics'] / t['no_contact']:.2f}× faster, and `substeps: auto` would "
        f"also allow {auto_no_contact} sub-steps per period instead of {scene.substeps}); the target–line "
        "capsules alone "
        f"{100 * (1 - t['no_line_contact'] / t['physics']):.0f}%; friction "
        f"{100 * (1 - t['no_friction'] / t['physics']):.0f}%; line drag {100 * (1 - t['no_drag'] / t['physics']):.0f}%; "
        f"the target's drag {100 * (1 - t['no_target_drag'] / t['physics']):.0f}%; wind "
        f"{100 * (1 - t['no_wind'] / t['physics']):.0f}% (a share near 0 is within the timing noise). The tethers "
        "cannot be left out of the environment (nothing would carry the net). The capture scene has no motor "
        "lag, body drag, gimbal or "
        "target propulsion (the evading target's), so they cost it nothing: `tests/test_effects_absent.py` "
        "checks that a scene without an effect traces none of its work.",
        "- The sub-step count is set by the stiffest element (the contact stiffness on the net's lightest masses; "
        "see the config): halving it halves the cost of a team step. The batch-last layout is in; what is "
        "left is the work per sub-step itself: fewer contact candidates per sub-step, implicit lines.",
        "",
    ]
    return lines
