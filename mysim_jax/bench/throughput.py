"""Throughput of the library's batched step: sections (a), (b), (f) and (j) of BENCHMARKS.md.

* (a) :func:`section_a` — the rope net (``configs/rope_net.yaml`` in the throughput setting
  :data:`THROUGHPUT_OVERRIDES`) at several batch sizes, side by side with the hand-written
  batch-last kernel (:mod:`mysim_jax.bench.rope_kernel`) and with plain ``jax.vmap``; and the
  capture scene's env steps/s at batch :data:`CAPTURE_BATCH`. :func:`plot_throughput` draws
  its rows against the targets (and MuJoCo's rate when section (c) ran).
* (b) :func:`section_b` — the node-force accumulation methods of ``Scene.accumulate``.
* (f) :func:`section_f` — where the time of one batched step goes: variants of the step
  (options of the Scene or of the call site) timed side by side, and op counts of the
  optimised HLO.
* (j) :func:`section_j` — XLA's two CPU code generators for fusions on the same programs.

Every variant compared in a section is AOT-compiled and timed round-robin
(:mod:`mysim_jax.bench.timing`).
"""

from __future__ import annotations

import dataclasses
import re
from functools import partial
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
from tqdm.auto import tqdm

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mysim_jax.bench.environment import env_call, env_variant  # noqa: E402
from mysim_jax.bench.report import (  # noqa: E402
    CAPTURE_FALLING, HEADLINE_BATCH, ROPE_NET, TARGET_ENV_STEPS, TARGET_KERNEL_RATIO, TARGET_MUJOCO_RATIO,
)
from mysim_jax.bench.rope_kernel import from_node_columns, rope_net_kernel, to_node_columns  # noqa: E402
from mysim_jax.bench.timing import (  # noqa: E402
    Compiled, ThroughputRow, aot_compile, broadcast, compile_batched, contention_note, library_run_env, median,
    spread, steps_for_batch, time_round_robin, wait_for_quiet,
)
from mysim_jax.build import build  # noqa: E402
from mysim_jax.config.scene import load_config  # noqa: E402
from mysim_jax.core import batching  # noqa: E402
from mysim_jax.sim import rollout  # noqa: E402
from mysim_jax.tasks.scripted import team_policy  # noqa: E402

# The throughput setting of the performance targets.
THROUGHPUT_OVERRIDES = ("sim.precision=float32", "sim.integrator=semi_implicit_euler",
                        "sim.dt=1e-4", "sim.substeps=1")
ROPE_BATCHES = (1, 64, 1024, 4096)  # rope-net throughput (section a)
CAPTURE_BATCH = 1024              # capture-scene throughput (section a)


def _throughput_scene():
    """The rope net in the throughput setting: ``(scene, params, state)``."""
    return build(load_config(ROPE_NET, list(THROUGHPUT_OVERRIDES)))


def _capture_throughput_run(n_steps: int):
    """The capture scene in float32 as configured (its ``sim.dt`` and sub-steps) and a
    ``run_env(params, state) -> state`` of ``n_steps`` env steps closed by its scripted
    team policy: ``(scene, params, state, run_env)``."""
    config = load_config(CAPTURE_FALLING, ["sim.precision=float32"])
    scene, params, state = build(config)
    policy = team_policy(config, scene)

    def run_env(p, s):
        return rollout(scene, p, s, n_steps, n_steps, policy)[0]
    return scene, params, state, run_env


def compile_kernel(scene, params, state, batch: int, n_steps: int) -> tuple[Compiled, Callable]:
    """The hand-written batch-last kernel (:mod:`mysim_jax.bench.rope_kernel`) on ``batch``
    copies of ``state``; also returns a function giving its final positions ``(B, n, 3)``."""
    run = jax.jit(rope_net_kernel(scene, params, n_steps))
    pos = to_node_columns(broadcast(state.phys.point_pos, batch))
    vel = to_node_columns(broadcast(state.phys.point_vel, batch))
    compiled, compile_s, memory = aot_compile(run, pos, vel)
    return (Compiled("kernel", batch, n_steps, lambda: compiled(pos, vel), compile_s, memory),
            lambda: from_node_columns(compiled(pos, vel)[0]))


def _measure_a(cfg):
    """Compile and time every rope-net row of section (a) (library, hand-written kernel and
    ``jax.vmap`` at each of :data:`ROPE_BATCHES`, and params batched too at
    :data:`HEADLINE_BATCH`) and the capture scene's two rows, all round-robin; check the
    kernel's final positions against the library's. Returns ``(scene, rows by key, memory
    stats of the B = 4096 call, kernel difference [m], capture scene, its state, capture row,
    its jax.vmap row)``."""
    scene, params, state = _throughput_scene()
    batches = ROPE_BATCHES
    runners: dict[str, Compiled] = {}
    kernel_pos = {}
    n_calls = 3 * len(batches) + 3
    bar = tqdm(total=n_calls * (cfg.repeats + 2), desc="(a) throughput", leave=False)
    for b in batches:
        k = steps_for_batch(b, cfg.env_steps_per_call)
        runners[f"B={b}"] = compile_batched(f"{b}", library_run_env(scene, k), params, state, b, k,
                                            vmap=batching.vmap)
        runners[f"B={b} jax.vmap"] = compile_batched(f"{b}, `jax.vmap` (batch first)", library_run_env(scene, k),
                                                     params, state, b, k, vmap=jax.vmap)
        runners[f"B={b} kernel"], kernel_pos[b] = compile_kernel(scene, params, state, b, k)
        bar.update(3)
    b = HEADLINE_BATCH
    k = steps_for_batch(b, cfg.env_steps_per_call)
    runners["B=4096 params batched"] = compile_batched("4096, params batched too", library_run_env(scene, k),
                                                       params, state, b, k, batch_params=True, vmap=batching.vmap)
    bar.update(1)
    cap_scene, cap_params, cap_state, cap_run = _capture_throughput_run(cfg.capture_steps)
    capture = compile_batched("capture", cap_run, cap_params, cap_state, CAPTURE_BATCH, cfg.capture_steps,
                              vmap=partial(batching.vmap, chunk=batching.chunk_for(cap_state)))
    capture_first = compile_batched("capture, jax.vmap", cap_run, cap_params, cap_state, CAPTURE_BATCH,
                                    cfg.capture_steps, vmap=jax.vmap)
    bar.update(2)
    wait_for_quiet(cfg.max_wait_s, "a")
    times = time_round_robin({**{key: r.call for key, r in runners.items()}, "capture": capture.call,
                              "capture_first": capture_first.call}, cfg.repeats, bar, section="a")
    bar.close()
    rows_all = {key: ThroughputRow(r.label, r.batch, r.n_steps, times[key], r.compile_s, r.bytes_per_env())
                for key, r in runners.items()}
    cap_row = ThroughputRow("capture", CAPTURE_BATCH, cfg.capture_steps, times["capture"], capture.compile_s,
                            capture.bytes_per_env())
    cap_first = ThroughputRow("capture, jax.vmap", CAPTURE_BATCH, cfg.capture_steps, times["capture_first"],
                              capture_first.compile_s, capture_first.bytes_per_env())
    # the kernel is separate code: check that it computes the library's trajectory
    lib_final = jax.jit(batching.vmap(library_run_env(scene, steps_for_batch(64, cfg.env_steps_per_call)),
                                      in_axes=(None, 0)))(params, broadcast(state, 64)).phys.point_pos
    kernel_diff = float(jnp.abs(kernel_pos[64]() - lib_final).max())
    return (scene, rows_all, runners["B=4096"].memory, kernel_diff, cap_scene, cap_state, cap_row, cap_first)


def section_a(cfg, results) -> list[str]:
    """(a) Rope-net throughput at each batch size against the kernel and ``jax.vmap``, the
    targets, and the capture scene's throughput."""
    scene, rows_all, mem, kernel_diff, cap_scene, cap_state, cap_row, cap_first = _measure_a(cfg)
    batches = ROPE_BATCHES
    rows = [row for key, row in rows_all.items() if not key.endswith(("jax.vmap", "kernel"))]
    results["capture_throughput"] = (cap_row, cap_scene.substeps, cap_first)
    results["a"] = rows
    headline = rows[batches.index(HEADLINE_BATCH)]
    results["ours_4096"] = headline.env_steps_per_s
    ratio = {b: rows_all[f"B={b}"].env_steps_per_s / rows_all[f"B={b} kernel"].env_steps_per_s for b in batches}
    first = {b: rows_all[f"B={b}"].env_steps_per_s / rows_all[f"B={b} jax.vmap"].env_steps_per_s for b in batches}
    results["kernel_ratio"] = ratio
    results["kernel_rows"] = {b: rows_all[f"B={b} kernel"].env_steps_per_s for b in batches}
    lines = _rope_net_table(cfg, scene, rows) + _kernel_table(batches, rows_all, ratio, first)
    big = [b for b in batches if b >= 1024]
    kernel_met = all(ratio[b] >= TARGET_KERNEL_RATIO for b in big)
    lines += [
        "",
        f"**Target library ≥ {TARGET_KERNEL_RATIO}× the kernel at B = {' and '.join(map(str, big))}: "
        f"{'MET' if kernel_met else 'NOT MET'}.** The kernel's final positions after K steps at B = 64 differ from "
        f"the library's by {kernel_diff:.1e} m (float32 round-off: the same physics).",
    ]
    results["kernel_met"] = kernel_met
    met = headline.env_steps_per_s >= TARGET_ENV_STEPS
    lines += [
        "",
        f"**Target ≥ {TARGET_ENV_STEPS:,} env-steps/s at B = {HEADLINE_BATCH}: "
        f"{'MET' if met else 'NOT MET'}** ({headline.env_steps_per_s:,.0f} env-steps/s"
        + ("" if met else f", {headline.env_steps_per_s / TARGET_ENV_STEPS:.0%} of target; see (f) for where the time goes")
        + ").",
        "",
        contention_note("a", cfg.repeats),
        "",
        "Memory/env is XLA's buffer assignment for one compiled call "
        "(`compiled.memory_analysis()`: argument + output + temporary bytes − aliased bytes) divided by B. "
        "Arguments are the batched input states plus the shared params (counted once), outputs the final "
        "states; temporaries are the scan carry and the loop body's intermediates, which are reused from one "
        "step to the next, so the figure does not grow with K. It excludes generated code and the "
        "Python/JAX runtime."
        + (f" At B = 4096: arguments {mem.argument_size_in_bytes / 2**20:.2f} MiB, outputs "
           f"{mem.output_size_in_bytes / 2**20:.2f} MiB, temporaries {mem.temp_size_in_bytes / 2**20:.2f} MiB."
           if mem is not None else ""),
        "",
        "![throughput](docs/bench/throughput.png)",
        "",
    ]
    return lines + _capture_lines(cfg, cap_scene, cap_state, cap_row, cap_first, rows)


def _rope_net_table(cfg, scene, rows) -> list[str]:
    """Section (a)'s heading, what one call is, and the library's row at each batch size."""
    lines = [
        "## (a) Rope-net throughput",
        "",
        f"`configs/rope_net.yaml` with `{' '.join('--set ' + o for o in THROUGHPUT_OVERRIDES)}` "
        f"({scene.n_points} point masses, {scene.n_springs} springs, {scene.accumulate!r} accumulation as "
        "built). One call = `jax.jit(mysim_jax.core.batching.vmap(run_env, in_axes=(None, 0)))(params, states)` "
        "(the library's batched path: the per-environment step evaluated with the batch axis last) where "
        "`run_env` is a `lax.scan` of K `mysim_jax.sim.step` calls: the batch of states is the single-env "
        "state broadcast to B copies, **params are shared by all envs (not vmapped)**; the last row "
        "also broadcasts and vmaps params (`in_axes=(0, 0)`). "
        f"env-steps/s = B·K / median of {cfg.repeats} timed calls after one warm-up call (see the contention "
        "note below).",
        "",
        "| batch B | K steps/call | env-steps/s | median call [s] | spread | compile [s] | memory/env [KiB] |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r.label} | {r.n_steps} | {r.env_steps_per_s:,.0f} | {median(r.times):.3f} | "
                     f"{spread(r.times)} | {r.compile_s:.2f} | {r.bytes_per_env / 1024:.2f} |")
    return lines


def _kernel_table(batches, rows_all, ratio, first) -> list[str]:
    """The library against the hand-written kernel and against ``jax.vmap``, batch by batch."""
    lines = [
        "",
        "### Against a hand-written batch-last kernel and against `jax.vmap`",
        "",
        "The same rollout, timed round-robin with the rows above: the hand-written kernel of "
        "`mysim_jax/bench/rope_kernel.py` (every node its own `(3, B)` array, the batch the contiguous last "
        "axis, every operation element-wise, the topology unrolled: no vmap, no gathers, no scatters) and the "
        "library's step batched with plain `jax.vmap` (batch axis first). Ratio = library (batch-last) / other.",
        "",
        "| batch B | library env-steps/s | kernel env-steps/s | library / kernel | `jax.vmap` env-steps/s "
        "| library / `jax.vmap` |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for b in batches:
        lib_r, ker_r, first_r = rows_all[f"B={b}"], rows_all[f"B={b} kernel"], rows_all[f"B={b} jax.vmap"]
        lines.append(f"| {b} | {lib_r.env_steps_per_s:,.0f} | {ker_r.env_steps_per_s:,.0f} | **{ratio[b]:.2f}×** | "
                     f"{first_r.env_steps_per_s:,.0f} | {first[b]:.2f}× |")
    return lines


def _capture_lines(cfg, cap_scene, cap_state, cap_row, cap_first, rows) -> list[str]:
    """The capture scene's throughput (batch-last and ``jax.vmap``) beside the rope net's row at
    B = 1024."""
    n_sub = cap_scene.substeps
    lines = [
        "### Capture scene throughput",
        "",
        f"`configs/capture_falling.yaml` with `--set sim.precision=float32`, as configured otherwise: "
        f"{sum(1 for n in cap_scene.body_names if n.startswith('uav'))} quadrotors and the target (rigid bodies), "
        f"{cap_scene.n_points} point masses (a {int(round(sum(n.startswith('net_k') for n in cap_scene.point_names) ** 0.5))}"
        f"² -knot net, its lines' and tethers' interior masses), {cap_scene.n_springs} springs, contact, line drag. "
        f"One env step = one control period `sim.dt` = {cap_scene.dt:g} s: the scripted team policy "
        "(`mysim_jax.tasks.scripted.team_policy`) and the cascaded PID run once, then "
        f"{n_sub} physics sub-steps of {cap_scene.substep:.3g} s ({cap_scene.integrator}, `substeps: auto`). "
        f"One call = `jax.jit(mysim_jax.core.batching.vmap(run_env, in_axes=(None, 0), chunk={batching.chunk_for(cap_state)}))(params, states)` "
        "(blocks from `batching.chunk_for`) with `run_env` one "
        f"`mysim_jax.sim.rollout(scene, params, state, K, K, policy)` of K = {cfg.capture_steps} env steps "
        f"(a short rollout from the start: the target is still falling and the net is not yet hit; "
        f"B·K = {CAPTURE_BATCH * cfg.capture_steps:,} env steps per call), the B states the single-env start "
        "state broadcast. Timed round-robin with the rope-net rows above, median of the same rounds.",
        "",
        "| scene | batch B | K env steps/call | env-steps/s | physics sub-steps/s | median call [s] | spread | "
        "compile [s] | memory/env [KiB] |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        f"| capture_falling | {CAPTURE_BATCH} | {cap_row.n_steps} | {cap_row.env_steps_per_s:,.0f} | "
        f"{cap_row.env_steps_per_s * n_sub:,.0f} | {median(cap_row.times):.3f} | {spread(cap_row.times)} | "
        f"{cap_row.compile_s:.2f} | {cap_row.bytes_per_env / 1024:.1f} |",
        f"| capture_falling, `jax.vmap` (batch first) | {CAPTURE_BATCH} | {cap_first.n_steps} | "
        f"{cap_first.env_steps_per_s:,.0f} | {cap_first.env_steps_per_s * n_sub:,.0f} | {median(cap_first.times):.3f} | "
        f"{spread(cap_first.times)} | {cap_first.compile_s:.2f} | {cap_first.bytes_per_env / 1024:.1f} |",
        f"| rope_net (row B = 1024 above) | 1024 | {rows[2].n_steps} | {rows[2].env_steps_per_s:,.0f} | "
        f"{rows[2].env_steps_per_s:,.0f} | {median(rows[2].times):.3f} | {spread(rows[2].times)} | "
        f"{rows[2].compile_s:.2f} | {rows[2].bytes_per_env / 1024:.2f} |",
        "",
        f"In simulated time: {cap_row.env_steps_per_s * cap_scene.dt:,.1f} simulated seconds per wall second over the "
        f"batch, i.e. {cap_row.env_steps_per_s * cap_scene.dt / CAPTURE_BATCH:.2e} per env. Batch-last against "
        f"`jax.vmap`: {cap_row.env_steps_per_s / cap_first.env_steps_per_s:.2f}×.",
        "",
    ]
    return lines


ACCUMULATE_METHODS = ("matmul", "segment_sum")


def section_b(cfg, results) -> list[str]:
    """(b) The node-force accumulation methods side by side at each batch size."""
    scene, params, state = _throughput_scene()
    batches = (1, 64, HEADLINE_BATCH) if not cfg.quick else (1, HEADLINE_BATCH)
    runners: dict[str, Compiled] = {}
    n_methods = len(ACCUMULATE_METHODS)
    bar = tqdm(total=n_methods * len(batches) * (cfg.repeats + 2), desc="(b) accumulate", leave=False)
    for b in batches:
        k = steps_for_batch(b, cfg.env_steps_per_call)
        for method in ACCUMULATE_METHODS:
            sc = dataclasses.replace(scene, accumulate=method)
            runners[f"{b}/{method}"] = compile_batched(method, library_run_env(sc, k), params, state, b, k)
            bar.update(1)
    wait_for_quiet(cfg.max_wait_s, "b")
    times = time_round_robin({key: r.call for key, r in runners.items()}, cfg.repeats, bar, section="b")
    bar.close()
    head = " | ".join(f"{m} env-steps/s" for m in ACCUMULATE_METHODS)
    lines = [
        "## (b) Node-force accumulation: " + ", ".join(f"`{m}`" for m in ACCUMULATE_METHODS),
        "",
        "Same rollout as (a), only `Scene.accumulate` changed with `dataclasses.replace(scene, accumulate=...)`. "
        "`matmul` multiplies the spring forces by a dense signed one-hot incidence matrix "
        f"({scene.n_nodes} × {scene.n_springs}); `segment_sum` scatters them with `jax.ops.segment_sum`. "
        f"The node gathers are the same in all three. Built scenes use `{scene.accumulate}`. "
        "The methods are timed round-robin at each batch size.",
        "",
        f"| batch B | K | {head} | fastest |",
        "|---:|---:|" + "---:|" * n_methods + "---|",
    ]
    rates = {}
    for b in batches:
        row = {}
        for m in ACCUMULATE_METHODS:
            r = runners[f"{b}/{m}"]
            row[m] = b * r.n_steps / median(times[f"{b}/{m}"])
        rates[b] = row
        best = max(row, key=row.get)
        cells = " | ".join(f"{row[m]:,.0f} (spread {spread(times[f'{b}/{m}'])})" for m in ACCUMULATE_METHODS)
        lines.append(f"| {b} | {runners[f'{b}/{best}'].n_steps} | {cells} | `{best}` |")
    results["b"] = rates
    default = scene.accumulate
    verdicts = []
    for b in batches:
        row = rates[b]
        ratio = row[default] / max(row.values())
        verdicts.append(f"B = {b}: `{default}` runs at {ratio:.2f}× the fastest method")
    lines += ["", "The built default: " + "; ".join(verdicts) + ".", "", contention_note("b", cfg.repeats), ""]
    return lines


def _gravity_only_run_env(scene, n_steps: int):
    """The floor: the same scan and semi-implicit update with gravity as the only force."""
    h = scene.substep

    def run_env(params, state):
        def body(s, _):
            vel = s.phys.point_vel + h * (jnp.zeros_like(s.phys.point_vel) + params.gravity)
            phys = s.phys.replace(point_pos=s.phys.point_pos + h * vel, point_vel=vel)
            return s.replace(phys=phys, time=s.time + scene.dt), None
        return jax.lax.scan(body, state, None, length=n_steps)[0]
    return run_env


def _hlo_census(text: str) -> dict[str, int]:
    """How many of each op of interest the optimised HLO ``text`` holds."""
    ops = {}
    for op in ("gather", "scatter", "transpose", "copy", "dot", "concatenate", "fusion"):
        ops[op] = len(re.findall(rf"= \S+ {op}\(", text))
    return ops


def _profile_variants(scene, params, state, B: int, K: int,
                     quick: bool) -> list[tuple[str, str, Callable[[], Compiled]]]:
    """The variants of section (f): ``(key, description, compile)``; ``quick`` keeps five."""
    lib = library_run_env(scene, K)

    def lib_with(**options):
        return library_run_env(dataclasses.replace(scene, **options), K)

    # every variant is an option of the Scene or of the call site, never a patched library function
    variants: list[tuple[str, str, Callable[[], Compiled]]] = [
        ("library", "library step as in (a): `batching.vmap` (batch last), slice gathers, `segment_sum`",
         lambda: compile_batched("library", lib, params, state, B, K, keep_hlo=True)),
        ("first", "library step with `jax.vmap` (batch first)",
         lambda: compile_batched("", lib, params, state, B, K, vmap=jax.vmap, keep_hlo=True)),
        ("matmul", "library step, `Scene.accumulate=\"matmul\"` (dense incidence product)",
         lambda: compile_batched("", lib_with(accumulate="matmul"), params, state, B, K)),
        ("index", "library step, `Scene.gather=\"index\"` (`x[index_array]` gathers)",
         lambda: compile_batched("", lib_with(gather="index"), params, state, B, K)),
        ("params_batched", "library step, params broadcast and batched too",
         lambda: compile_batched("", lib, params, state, B, K, batch_params=True)),
        ("chunked", f"library step, the {B} envs as 64 chunks × {B // 64} (`lax.map` over a batched chunk)",
         lambda: compile_batched("", lib, params, state, B, K, chunk=64)),
        ("floor", "floor: the scan + semi-implicit update with gravity only (no springs), batch last",
         lambda: compile_batched("", _gravity_only_run_env(scene, K), params, state, B, K)),
        ("kernel", "the hand-written batch-last kernel of (a)",
         lambda: compile_kernel(scene, params, state, B, K)[0]),
    ]
    if quick:
        keep = {"library", "first", "index", "floor", "kernel"}
        variants = [v for v in variants if v[0] in keep]
    return variants


def section_f(cfg, results) -> list[str]:
    """(f) Where the time of one batched step goes: variants of the step at
    :data:`HEADLINE_BATCH`, timed round-robin, their distance to the library's positions, and
    the op counts of the optimised HLO."""
    scene, params, state = _throughput_scene()
    B = HEADLINE_BATCH
    K = steps_for_batch(B, cfg.env_steps_per_call)
    variants = _profile_variants(scene, params, state, B, K, cfg.quick)
    bar = tqdm(total=len(variants) * (cfg.repeats + 2), desc="(f) profile", leave=False)
    runners: dict[str, Compiled] = {}
    for key, _, make in variants:
        runners[key] = make()
        bar.update(1)

    def positions(key):
        out = runners[key].call()
        return np.asarray(from_node_columns(out[0]) if key == "kernel" else out.phys.point_pos)

    reference = positions("library")
    max_diff = {key: float(np.abs(positions(key) - reference).max()) for key in runners}
    wait_for_quiet(cfg.max_wait_s, "f")
    times = time_round_robin({k: r.call for k, r in runners.items()}, cfg.repeats, bar, section="f")
    bar.close()
    base = median(times["library"])
    census = _hlo_census(runners["library"].hlo_text)
    census_first = _hlo_census(runners["first"].hlo_text)
    lines = [
        f"## (f) Where the time goes (batch {B}, float32, semi-implicit Euler)",
        "",
        f"Variants of the batched rollout of (a) at B = {B}, K = {K}, all timed round-robin in one loop (median "
        f"of {cfg.repeats} quiet rounds). Each is an option of the Scene (`accumulate`, `gather`) or of the call "
        "site (how it is batched); the last column is how far each variant's positions are from the library's "
        "after K steps (0 or float32 round-off = same physics; the floor drops the springs by design).",
        "",
        "| variant | env-steps/s | ms per batched step | vs library | spread | \\|Δx\\| vs library [m] |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    desc = {k: d for k, d, _ in variants}
    for key, r in runners.items():
        t = median(times[key])
        lines.append(f"| {desc[key]} | {B * K / t:,.0f} | {1e3 * t / K:.3f} | {base / t:.2f}× | {spread(times[key])} | "
                     f"{max_diff[key]:.1e} |")
    rate = {k: B * K / median(v) for k, v in times.items()}
    results["f"] = rate
    lines += [
        "",
        contention_note("f", cfg.repeats),
        "",
        "Optimised HLO of the batched rollout (`compiled.as_text()`), op counts, batch last (library): "
        + ", ".join(f"{k} {v}" for k, v in census.items()) + "; batch first (`jax.vmap`): "
        + ", ".join(f"{k} {v}" for k, v in census_first.items()) + ".",
        "",
        "### Findings",
        "",
    ]
    return lines + _profile_findings(rate)


def _profile_findings(rate: dict[str, float]) -> list[str]:
    """Section (f)'s findings from the env-steps/s of each variant ``rate``."""
    lines = []

    def x(key):
        return rate[key] / rate["library"]

    lines.append(f"- The scan and the semi-implicit update alone (gravity only) run at {rate['floor']:,.0f} "
                 f"env-steps/s, {x('floor'):.1f}× the library: the rest of the time is the spring stage.")
    lines.append(f"- Batch last against batch first (`jax.vmap`) for the same per-environment code: "
                 f"{1 / x('first'):.2f}×; against the hand-written kernel: {rate['library'] / rate['kernel']:.2f}×.")
    for key, what in (("matmul", "the dense `matmul` accumulation"), ("index", "`x[index_array]` gathers")):
        if key in rate:
            lines.append(f"- With {what} instead: {x(key):.2f}× the library.")
    if "chunked" in rate:
        lines.append(f"- 64 chunks (a call-site change): {x('chunked'):.2f}×"
                     + (" — cache blocking helps." if x("chunked") > 1.2 else " — no clear gain."))
    if "params_batched" in rate:
        lines.append(f"- Batching params too (a parameter sweep) runs at {x('params_batched'):.2f}× the shared-params "
                     "speed.")
    lines.append("")
    return lines


EMITTERS = {"older (LLVM) emitters": {"xla_cpu_use_fusion_emitters": False},
            "fusion emitters (XLA's default)": {"xla_cpu_use_fusion_emitters": True}}


def section_j(cfg, results) -> list[str]:
    """XLA's two CPU code generators for fusions, on the same programs side by side."""
    scene, params, state = _throughput_scene()
    rope_b = 64 if cfg.quick else 1024
    rope_k = steps_for_batch(rope_b, cfg.env_steps_per_call)
    train_b, full_b = (16, 16) if cfg.quick else (1024, 256)
    train_env, train_params = env_variant(["level=train", "env.policy_rate=10.0"])
    full_env, full_params = env_variant(["env.policy_rate=10.0"])
    programs = {
        f"capture env, level train, B = {train_b} (1 team step at 10 Hz)":
            lambda o: env_call(train_env, train_params, train_b, 1, compiler_options=o),
        f"capture env, level full, B = {full_b} (1 team step at 10 Hz)":
            lambda o: env_call(full_env, full_params, full_b, 1, compiler_options=o),
        f"rope net (a), B = {rope_b}, {rope_k} steps":
            lambda o: compile_batched("rope", library_run_env(scene, rope_k), params, state, rope_b, rope_k,
                                      compiler_options=o),
    }
    compiled = {}
    for name, make in tqdm(programs.items(), desc="(j) emitters", leave=False):
        for emitter, options in EMITTERS.items():
            compiled[name, emitter] = make(options)
    wait_for_quiet(cfg.max_wait_s, "j")
    times = time_round_robin({f"{k[0]} / {k[1]}": c.call for k, c in compiled.items()}, cfg.env_repeats,
                             section="j")
    older, default = EMITTERS
    lines = [
        "## (j) XLA CPU code generation: older emitters vs fusion emitters",
        "",
        "Each program compiled twice in this process, once per code generator "
        "(`.lower().compile(compiler_options={'xla_cpu_use_fusion_emitters': ...})`, which overrides `XLA_FLAGS`), "
        f"and the six timed round-robin (median of {cfg.env_repeats} calls); the environments blocked as the "
        "library blocks them (`batching.chunk_for`). The library runs with XLA's default; the test suite compiles "
        "with the older emitters (`tests/conftest.py`), which compile faster.",
        "",
        f"| program | compile [s] {older} | compile [s] {default} | call [ms] {older} | call [ms] {default} "
        "| speed-up of the older emitters |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    ratios = {}
    for name in programs:
        a, b = compiled[name, older], compiled[name, default]
        ta, tb = median(times[f"{name} / {older}"]), median(times[f"{name} / {default}"])
        ratios[name] = tb / ta
        lines.append(f"| {name} | {a.compile_s:.1f} | {b.compile_s:.1f} | {1e3 * ta:,.1f} | {1e3 * tb:,.1f} | "
                     f"{tb / ta:.2f}× |")
    results["emitter_speedup"] = ratios
    return lines + ["", contention_note("j", cfg.env_repeats), ""]


def plot_throughput(results, plots_dir: Path) -> Path | None:
    """``throughput.png`` in ``plots_dir``: section (a)'s env-steps/s against the batch size, the
    target and (when section (c) ran) MuJoCo's single-thread rate; None without section (a)."""
    if "a" not in results:
        return None
    rows = [r for r in results["a"] if "params" not in r.label]
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    ax.plot([r.batch for r in rows], [r.env_steps_per_s for r in rows], "o-", label="mysim_jax (float32, 2 cores)")
    ax.axhline(TARGET_ENV_STEPS, color="C3", ls="--", lw=1, label=f"target {TARGET_ENV_STEPS:,.0f}")
    if "mujoco_steps_per_s" in results:
        ax.axhline(results["mujoco_steps_per_s"], color="C2", ls=":", lw=1.2, label="MuJoCo Euler, 1 thread")
        ax.axhline(TARGET_MUJOCO_RATIO * results["mujoco_steps_per_s"], color="C2", ls="--", lw=0.8,
                   label=f"{TARGET_MUJOCO_RATIO:.0f}× MuJoCo")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("batch size B (envs)")
    ax.set_ylabel("env-steps / s")
    ax.set_title("rope net, semi-implicit Euler, dt 1e-4")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = plots_dir / "throughput.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
