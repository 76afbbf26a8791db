#!/usr/bin/env python
"""Benchmarks of mysim_jax: write BENCHMARKS.md and plots into docs/bench/.

    python scripts/bench.py                  # full run: ~45 min on 2 cores
    python scripts/bench.py --quick          # smoke test: fewer repeats and points
    python scripts/bench.py --only a,c       # some sections only

Sections (``--only`` takes their letters):

  a  rope-net throughput: jit(batching.vmap(scan of K steps)) at batch 1, 64, 1024, 4096
     (float32, semi-implicit Euler, dt 1e-4): env-steps/s, compile time, memory per env,
     side by side with a hand-written batch-last kernel (mysim_jax/bench/rope_kernel.py)
     and with plain jax.vmap; and the capture scene's env-steps/s at batch 1024 (float32,
     scripted team policy), batch-last and jax.vmap.
  b  node-force accumulation: Scene.accumulate "matmul" vs "segment_sum", side by side.
  c  MuJoCo (C engine, one thread) on the same net exported by mysim_jax.io.mjcf.
  d  accuracy against cost: each integrator / step / tolerance / precision against a
     float64 tsit5 reference at rtol 1e-11 (table + log-log plot). Scenes are the entries
     returned by ``accuracy_cases()``, so a new scene (e.g. contact) is one more entry.
     The contact scenes compare ball and payload z over 1.5 s and also report
     when each method first drifts more than 2e-3 m from the reference.
     ``--cases collision_light,collision_heavy`` runs only those scenes of (d).
     rope_net_slack (tension-only ropes that start slack) and capture_falling (the closed-loop
     capture scene, sub-steps of its fixed control period) also report the observed order
     of the fixed-step methods across slack-taut switches.
  i  fidelity levels of the capture scene: team steps/s at B = 256 and 1024 (10 Hz), sub-steps
     per team step, memory per env, the scripted team's success on the same 256 episodes
     at each level with the paired difference to full.
  e  capture environment (configs/capture_env_falling.yaml): team (policy) steps/s of
     jit(batching.vmap(CaptureEnv.step)) with the scripted team at batch 1 to 4096 (and
     jax.vmap up to 1024, side by side), compile time,
     memory per env; and where a policy step's time goes (control periods, physics
     stages, the environment's own work) at batch 256.
  f  profile: where the time of one batched step goes, by timing stage variants.
  g  training throughput (MAPPO).
  h  rendering: frames per second of the camera renderer (mysim_jax/bench/render.py) at
     1920 x 1080 and 640 x 360, for an onboard and an observer view of a capture run and
     a ground-only view; writes an example frame to docs/bench/render_example.png.

Timing method: every timed quantity is the median of repeats; variants that are compared
with each other are timed round-robin (one call of each in turn, repeated) so that a busy
machine slows all of them alike. The machine may be shared: the CPU time other processes
take is measured from /proc for every timed round, a section first waits (bounded) for a
quiet machine, and rounds during which others used >= 10% of the CPU are discarded and
redone (up to 2x the repeats + 1); each section says how busy the machine was. Compilation is
done ahead of time (``.lower().compile()``) and timed separately.

A run with --quick or --only writes to docs/bench/partial/ unless --out is given, so a
smoke test never overwrites the full BENCHMARKS.md. ``--only a,e --update`` instead
reruns those sections and splices them into the existing BENCHMARKS.md: the sections not
rerun, and their summary lines, are kept as they were, and the header says which
sections come from which run.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import datetime as _dt
import os
import platform
import re
import shlex
import sys
import time
from contextlib import contextmanager
from functools import partial
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
ROPE_NET = ROOT / "configs" / "rope_net.yaml"
COLLISION_LIGHT = ROOT / "configs" / "collision_light.yaml"
COLLISION_HEAVY = ROOT / "configs" / "collision_heavy.yaml"
ROPE_NET_SLACK = ROOT / "configs" / "rope_net_slack.yaml"
CAPTURE_FALLING = ROOT / "configs" / "capture_falling.yaml"
CAPTURE_ENV = ROOT / "configs" / "capture_env_falling.yaml"
SECTIONS = ("a", "b", "c", "d", "e", "f", "g", "h", "i", "j")
TRAIN_CAPTURE = ROOT / "configs" / "train_capture_falling.yaml"

# The throughput setting of the performance targets.
THROUGHPUT_OVERRIDES = ("sim.precision=float32", "sim.integrator=semi_implicit_euler",
                        "sim.dt=1e-4", "sim.substeps=1")
TARGET_ENV_STEPS = 1_000_000      # env-steps/s at batch 4096
TARGET_POLICY_STEPS = 20_000      # capture environment: team (policy) steps/s at batch 4096
TARGET_MUJOCO_RATIO = 50.0        # ours@4096 / MuJoCo single-thread
TARGET_KERNEL_RATIO = 0.8         # library / hand-written batch-last kernel at B = 1024 and 4096
HEADLINE_BATCH = 4096
CAPTURE_BATCH = 1024              # capture-scene throughput (section a)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

from mysim_jax.core import batching  # noqa: E402
from mysim_jax.bench.rope_kernel import from_node_columns, rope_net_kernel, to_node_columns  # noqa: E402
from mysim_jax.build import build  # noqa: E402
from mysim_jax.config.scene import ConfigError, load_config  # noqa: E402
from mysim_jax.dynamics.integrators import FIXED_STEP  # noqa: E402
from mysim_jax.sim import output_times, rollout, single_env_scene, solve_adaptive, step, steps_per_output  # noqa: E402
from mysim_jax.tasks.scripted import team_policy  # noqa: E402


# =========================================================================================
# timing helpers
# =========================================================================================


from mysim_jax.bench.timing import (  # noqa: E402
    CPU, QUIET_SHARE, Compiled, aot_compile, broadcast, compile_batched, contention_note, contention_shares,
    cpu_model, git_revision, library_run_env, load_average, median, record_contention, spread, steps_for_batch,
    time_round_robin, wait_for_quiet,
)


# =========================================================================================
# machine / header
# =========================================================================================


def header_lines(args, started: str, load_start: str, load_end: str, wall_s: float) -> list[str]:
    import diffrax
    import jaxlib

    try:
        import mujoco
        mujoco_version = mujoco.__version__
    except ImportError:
        mujoco_version = "not installed"
    n_cpu = os.cpu_count()
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = n_cpu
    command = "python " + " ".join(shlex.quote(a) for a in sys.argv)
    lines = [
        "# Benchmarks",
        "",
        f"Generated by `scripts/bench.py` — do not edit by hand; rerun it. "
        f"{'**QUICK smoke-test run: numbers are not representative.**' if args.quick else ''}".rstrip(),
        "",
        "| | |",
        "|---|---|",
        f"| command | `{command}` |",
        f"| date | {started} (total wall time {wall_s / 60:.1f} min) |",
        f"| machine | {cpu_model()}, {n_cpu} logical cores ({usable} usable), {platform.system()} {platform.release()} |",
        f"| load average (1/5/15 min) | at start {load_start}; at end {load_end} |",
        f"| software | Python {platform.python_version()}, jax {jax.__version__}, jaxlib {jaxlib.__version__}, "
        f"diffrax {diffrax.__version__}, mujoco {mujoco_version}, numpy {np.__version__} |",
        f"| JAX backend | {jax.default_backend()} ({len(jax.devices())} device), XLA_FLAGS={os.environ.get('XLA_FLAGS', '(unset)')!r} |",
        f"| code | git {git_revision()} |",
        "",
        "Timings are medians of repeats; compared variants are timed round-robin in the same run "
        "(one call of each in turn), so background load slows them alike. The machine is shared: rounds "
        f"during which other processes used ≥ {100 * QUIET_SHARE:.0f}% of the CPU (measured from /proc) are "
        "discarded and redone, and every section states how busy the machine was. Spread = (max − min) / "
        "median of the counted repeats. Compile time is measured separately (`jit(...).lower(...).compile()`).",
        "",
    ]
    return lines


# =========================================================================================
# (a) throughput and (b) accumulation
# =========================================================================================


@dataclass
class ThroughputRow:
    label: str
    batch: int
    n_steps: int
    times: list[float]
    compile_s: float
    bytes_per_env: float

    @property
    def env_steps_per_s(self) -> float:
        return self.batch * self.n_steps / median(self.times)


def _throughput_scene():
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


def section_a(cfg, results) -> list[str]:
    scene, params, state = _throughput_scene()
    batches = (1, 64, 1024, 4096)
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
    rows = [row for key, row in rows_all.items() if not key.endswith(("jax.vmap", "kernel"))]
    cap_row = ThroughputRow("capture", CAPTURE_BATCH, cfg.capture_steps, times["capture"], capture.compile_s,
                            capture.bytes_per_env())
    cap_first = ThroughputRow("capture, jax.vmap", CAPTURE_BATCH, cfg.capture_steps, times["capture_first"],
                              capture_first.compile_s, capture_first.bytes_per_env())
    results["capture_throughput"] = (cap_row, cap_scene.substeps, cap_first)
    results["a"] = rows
    headline = rows[batches.index(HEADLINE_BATCH)]
    results["ours_4096"] = headline.env_steps_per_s
    ratio = {b: rows_all[f"B={b}"].env_steps_per_s / rows_all[f"B={b} kernel"].env_steps_per_s for b in batches}
    first = {b: rows_all[f"B={b}"].env_steps_per_s / rows_all[f"B={b} jax.vmap"].env_steps_per_s for b in batches}
    results["kernel_ratio"] = ratio
    results["kernel_rows"] = {b: rows_all[f"B={b} kernel"].env_steps_per_s for b in batches}
    # the kernel is separate code: check that it computes the library's trajectory
    lib_final = jax.jit(batching.vmap(library_run_env(scene, steps_for_batch(64, cfg.env_steps_per_call)),
                                      in_axes=(None, 0)))(params, broadcast(state, 64)).phys.point_pos
    kernel_diff = float(jnp.abs(kernel_pos[64]() - lib_final).max())

    mem = runners["B=4096"].memory
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
    lines += [
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
    n_sub = cap_scene.substeps
    lines += [
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


# =========================================================================================
# accuracy reference (shared by c and d)
# =========================================================================================


@dataclass(frozen=True)
class Method:
    """One integrator setting of the accuracy table."""

    integrator: str
    setting: str                       # "dt = 1e-4" / "rtol = 1e-8"
    overrides: tuple[str, ...]
    precision: str                     # float64 / float32
    max_steps: int | None = None       # cap for adaptive solvers (diffrax max_steps)
    note: str = ""
    step: float | None = None          # fixed-step integrators: the (sub-)step h [s]


def point_coordinate(point: str, axis: int) -> Callable:
    """Quantity: one coordinate of one point mass over time, ``(n_out,)``."""
    def quantity(scene, point_pos: np.ndarray, body_pos: np.ndarray) -> np.ndarray:
        return point_pos[:, scene.point_names.index(point), axis]
    return quantity


@dataclass(frozen=True)
class AccuracyCase:
    """One scene of the accuracy-vs-cost study.

    ``overrides`` apply to every run of the scene; ``reference`` is added on top for the
    reference solution; every entry of ``methods`` is added on top for the compared runs.
    ``quantity(scene, point_pos (n_out, n_points, 3), body_pos (n_out, n_bodies, 3))`` is
    what is compared: ``(n_out, ...)`` coordinates whose largest absolute difference is the
    error, or, with ``vector``, ``(n_out, k, 3)`` positions whose largest distance is.
    ``extra`` adds more such ``(label, quantity)`` errors as table columns.

    ``policy(config, scene)`` gives the control policy of every step (the same for every
    method; e.g. :func:`mysim_jax.tasks.scripted.team_policy`). ``reference_check`` is a
    second tight setting run like the reference; its distance to the reference is reported
    so that the reference's own error is known.
    """

    name: str
    config: Path
    quantity_label: str
    quantity: Callable
    t_end: float = 2.0
    reference_dt: float = 1e-3                     # output grid of the reference
    overrides: tuple[str, ...] = ()
    reference: tuple[str, ...] = ("sim.integrator=tsit5", "sim.rtol=1e-11", "sim.atol=1e-13",
                                  "sim.precision=float64")
    methods: tuple[Method, ...] = ()
    drift_tolerance: float | None = None           # report when the error first exceeds it
    tolerances: tuple[float, ...] = ()             # for tolerance_highlights
    policy: Callable | None = None                 # (config, scene) -> policy for rollout
    vector: bool = False
    extra: tuple[tuple[str, Callable], ...] = ()
    reference_check: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()                    # paragraphs printed above the table
    order_note: bool = False                       # report the observed order of the fixed-step methods
    highlights: Callable | None = None             # (case, rows) -> markdown lines under the table


def fixed_step_methods(integrator: str, dts, precisions) -> list[Method]:
    out = []
    for dt in dts:
        for prec in precisions:
            out.append(Method(integrator, f"dt = {dt:.0e}", (f"sim.integrator={integrator}", f"sim.dt={dt:g}",
                                                           "sim.substeps=1"), prec, step=dt))
    return out


def substep_methods(integrator: str, env_dt: float, substeps, precisions) -> list[Method]:
    """Fixed-step runs that keep the env step ``sim.dt`` (the control period) and vary the
    physics sub-step ``h = env_dt / substeps``."""
    out = []
    for n in substeps:
        for prec in precisions:
            h = env_dt / n
            out.append(Method(integrator, f"h = {h:.2e} ({n} sub-steps)",
                              (f"sim.integrator={integrator}", f"sim.substeps={n}"), prec, step=h))
    return out


def adaptive_methods(integrator: str, rtols, precision: str, max_steps: int | None = None, note: str = "",
                     atol: float | None = None) -> list[Method]:
    """Adaptive runs at each rtol; atol = rtol / 100 unless given (then named in the setting)."""
    out = []
    for r in rtols:
        a = r * 1e-2 if atol is None else atol
        setting = f"rtol = {r:.0e}" + ("" if atol is None else f", atol = {a:.0e}")
        out.append(Method(integrator, setting, (f"sim.integrator={integrator}", f"sim.rtol={r:g}", f"sim.atol={a:g}"),
                          precision, max_steps, note))
    return out


def default_methods(quick: bool) -> tuple[Method, ...]:
    if quick:
        return tuple(
            fixed_step_methods("semi_implicit_euler", (5e-5, 1e-4, 2e-4), ("float64",))
            + fixed_step_methods("semi_implicit_euler", (1e-4,), ("float32",))
            + fixed_step_methods("rk4", (1e-4, 3e-4), ("float64",))
            + fixed_step_methods("implicit_euler", (1e-3,), ("float64",))
            + adaptive_methods("tsit5", (1e-8,), "float64")
        )
    dts = (2e-5, 5e-5, 1e-4, 2e-4, 3e-4)
    return tuple(
        fixed_step_methods("semi_implicit_euler", dts, ("float64", "float32"))
        + fixed_step_methods("rk4", dts, ("float64", "float32"))
        # linearly implicit springs: from the explicit range up to ~10x the explicit limit
        + fixed_step_methods("implicit_euler", (2e-5, 1e-4, 3e-4, 1e-3), ("float64",))
        + fixed_step_methods("implicit_euler", (1e-4, 1e-3), ("float32",))
        + adaptive_methods("tsit5", (1e-6, 1e-8, 1e-10), "float64")
        # float32 resolves ~1e-7 relative: the config rejects tolerances below 1e-6 there
        # (config.FLOAT32_MIN_TOLERANCE); these are the tightest and a looser float32 setting
        + adaptive_methods("tsit5", (1e-6,), "float32", max_steps=200_000, atol=1e-6)
        + adaptive_methods("tsit5", (1e-5,), "float32", max_steps=200_000, atol=1e-5)
        # implicit solver, observed very slow on this scene: one loose tolerance, capped
        + adaptive_methods("kvaerno5", (1e-4,), "float64", max_steps=60_000,
                           note="max_steps capped at 60,000; not reached")
    )


def ball_and_payload_z(scene, point_pos: np.ndarray, body_pos: np.ndarray) -> np.ndarray:
    """Quantity of the contact scenes: z of the ball and of the payload, ``(n_out, 2)``."""
    return point_pos[:, [scene.point_names.index("ball"), scene.point_names.index("payload")], 2]


def target_position(scene, point_pos: np.ndarray, body_pos: np.ndarray) -> np.ndarray:
    """Quantity of the capture scene: the target's position, ``(n_out, 1, 3)``."""
    return body_pos[:, [scene.body_names.index("target")]]


def target_and_knots(scene, point_pos: np.ndarray, body_pos: np.ndarray) -> np.ndarray:
    """Quantity of the capture scene: the target's and every net knot's position,
    ``(n_out, 1 + n_knots, 3)`` (knots are the points named ``net_k*``; the lines' interior
    masses and the tethers' are left out)."""
    knots = [i for i, n in enumerate(scene.point_names) if n.startswith("net_k")]
    return np.concatenate([target_position(scene, point_pos, body_pos), point_pos[:, knots]], axis=1)


def contact_methods(quick: bool, light: bool) -> tuple[Method, ...]:
    """Issue #3: the default (tsit5 rtol 1e-12, float64) against looser tolerances, the
    fixed-step paths (``substeps: auto`` = the stable step chosen from the contact
    stiffness, and finer steps), float32, and the implicit kvaerno5."""
    auto = [Method(i, "dt = 1e-3, substeps auto", (f"sim.integrator={i}", "sim.dt=0.001", "sim.substeps=auto"), p)
            for i, p in (("semi_implicit_euler", "float64"), ("semi_implicit_euler", "float32"),
                         ("rk4", "float64"), ("rk4", "float32"))]
    float32_tsit5 = adaptive_methods("tsit5", (1e-5,), "float32", max_steps=400_000, atol=1e-5)
    # the heavy scene's chattering contact makes loose tolerances hit-or-miss: the same
    # tolerance with another initial step (dt0 = sim.dt) shows how robust each one is
    dt0 = [Method("tsit5", f"rtol = {r:.0e}, dt0 = {h:.0e}", ("sim.integrator=tsit5", f"sim.rtol={r:g}",
                                                          f"sim.atol={r * 1e-2:g}", f"sim.dt={h:g}"), "float64")
           for r in (1e-11, 1e-12) for h in (5e-4, 2e-4)]
    if quick:
        return tuple(adaptive_methods("tsit5", (1e-12,), "float64") + auto[:1] + float32_tsit5)
    return tuple(
        adaptive_methods("tsit5", (1e-9, 1e-10, 1e-11, 1e-12), "float64")
        + ([] if light else dt0)
        + float32_tsit5
        + auto
        + fixed_step_methods("rk4", (2e-6,), ("float64",))
        + fixed_step_methods("semi_implicit_euler", (1e-6,), ("float64",))
        # implicit: measured >100x slower than tsit5 on the light scene; one tolerance, capped
        + (adaptive_methods("kvaerno5", (1e-6,), "float64", max_steps=60_000, note="max_steps capped at 60,000")
           if light else [])
    )


def slack_methods(quick: bool) -> tuple[Method, ...]:
    """The slack-rope net: fixed steps from the stability limit down (for the observed
    order across slack-taut switches), adaptive tsit5 and one capped kvaerno5."""
    if quick:
        return tuple(fixed_step_methods("semi_implicit_euler", (1e-4,), ("float64",))
                     + fixed_step_methods("rk4", (5e-5, 1e-4), ("float64",))
                     + adaptive_methods("tsit5", (1e-8,), "float64"))
    return tuple(
        fixed_step_methods("semi_implicit_euler", (5e-6, 2e-5, 5e-5, 1e-4, 2e-4), ("float64",))
        + fixed_step_methods("semi_implicit_euler", (2e-5, 1e-4), ("float32",))
        + fixed_step_methods("rk4", (5e-6, 2e-5, 5e-5, 1e-4, 2e-4), ("float64",))
        + fixed_step_methods("rk4", (2e-5, 1e-4), ("float32",))
        + adaptive_methods("tsit5", (1e-6, 1e-8, 1e-10), "float64")
        + adaptive_methods("tsit5", (1e-5,), "float32", max_steps=200_000, atol=1e-5)
        + adaptive_methods("kvaerno5", (1e-4,), "float64", max_steps=60_000, note="max_steps capped at 60,000")
    )


STIFF_EA = 1e9     # N: the stiff rope net's lines (10,000x the paper's EA)
STIFF_ROPES = tuple(f"ropes.{i}.EA={STIFF_EA:g}" for i in range(4))


def stiff_methods(quick: bool) -> tuple[Method, ...]:
    """The stiff rope net: explicit methods at steps near their stability limit (~4e-6 s
    for semi-implicit Euler) and implicit_euler from 25x to 500x that limit."""
    if quick:
        return tuple(fixed_step_methods("semi_implicit_euler", (3e-6,), ("float64",))
                     + fixed_step_methods("implicit_euler", (1e-3,), ("float64",)))
    return tuple(
        fixed_step_methods("semi_implicit_euler", (1e-6, 2e-6, 3e-6, 5e-6), ("float64",))
        + fixed_step_methods("semi_implicit_euler", (3e-6,), ("float32",))
        + fixed_step_methods("rk4", (2e-6, 4e-6), ("float64",))
        + fixed_step_methods("implicit_euler", (1e-4, 3e-4, 1e-3, 2e-3), ("float64",))
        + fixed_step_methods("implicit_euler", (1e-3, 2e-3), ("float32",))
        + adaptive_methods("tsit5", (1e-6,), "float64", max_steps=3_000_000)
        + adaptive_methods("kvaerno5", (1e-4,), "float64", max_steps=20_000,
                           note="max_steps capped at 20,000; not reached")
    )


# The capture scene's target spawn is drawn from a PRNG key, and the draw differs between
# float32 and float64: the accuracy runs fix it (to the float32 draw of the scene's seed,
# rounded) so that every method starts from the same state.
CAPTURE_SPAWN = ("target.spawn.position.low=[1.03,-0.95,6.23]", "target.spawn.position.high=[1.03,-0.95,6.23]",
                 "target.spawn.velocity.low=[-0.3,-0.29,0.29]", "target.spawn.velocity.high=[-0.3,-0.29,0.29]")
CAPTURE_DT = 2e-3        # the capture scene's env step (control period), kept for every method
TSIT5_CAPTURE: list[Method] = []   # tsit5 rtol 1e-6 per control period: > 5 min for 1.6 s, not run


def capture_methods(quick: bool) -> tuple[Method, ...]:
    """The capture scene: sub-steps of the fixed 2 ms control period from the stability
    limit (semi-implicit Euler 51, RK4 26; below that the builder rejects) down, and
    adaptive tsit5 on each control period."""
    if quick:
        return tuple(substep_methods("semi_implicit_euler", CAPTURE_DT, (51,), ("float32",)))
    return tuple(
        substep_methods("semi_implicit_euler", CAPTURE_DT, (40,), ("float64",))
        + substep_methods("semi_implicit_euler", CAPTURE_DT, (51,), ("float64", "float32"))
        + substep_methods("semi_implicit_euler", CAPTURE_DT, (102, 204), ("float64",))
        + substep_methods("rk4", CAPTURE_DT, (20,), ("float64",))
        + substep_methods("rk4", CAPTURE_DT, (26,), ("float64", "float32"))
        + substep_methods("rk4", CAPTURE_DT, (52, 104), ("float64",))
        # implicit net springs; contact and the tethers on the UAVs stay explicit (auto: 33)
        + substep_methods("implicit_euler", CAPTURE_DT, (33,), ("float64", "float32"))
        + substep_methods("implicit_euler", CAPTURE_DT, (66,), ("float64",))
        + TSIT5_CAPTURE
    )


def tolerance_highlights(case: AccuracyCase, rows: list[AccuracyRow]) -> list[str]:
    """The cheapest run within each of ``case.tolerances``, for the main error and each
    ``case.extra`` error."""
    ok = [r for r in rows if r.status == "ok"]
    out = []
    measures = [(case.quantity_label.split(" [")[0], lambda r: r.error)] + [
        (label, (lambda i: lambda r: r.extra_errors[i])(i)) for i, (label, _) in enumerate(case.extra)]
    for label, error in measures:
        for tol in case.tolerances:
            cands = sorted((r for r in ok if error(r) <= tol), key=lambda r: r.wall_per_sim_s)
            if cands:
                r = cands[0]
                out.append(f"- cheapest run with {label} within {tol:g} m: **{r.method.integrator} {r.method.setting} "
                           f"{r.method.precision}** ({error(r):.1e} m, {r.wall_per_sim_s:.3f} s per simulated s)")
            else:
                out.append(f"- no run has {label} within {tol:g} m")
    out += [f"- {r.method.integrator} {r.method.setting} {r.method.precision}: {r.status}" for r in rows
            if r.status != "ok"]
    return out + [""]


def accuracy_cases(quick: bool) -> list[AccuracyCase]:
    """The scenes of part (d). Issue #3 adds contact scenes here."""
    rope_net = AccuracyCase(
        name="rope_net",
        config=ROPE_NET,
        quantity_label="payload z [m]",
        quantity=point_coordinate("payload", 2),
        t_end=2.0,
        methods=default_methods(quick),
        order_note=True,
    )
    return [
        rope_net,
        AccuracyCase(
            name="rope_net_slack",
            config=ROPE_NET_SLACK,
            quantity_label="payload position [m]",
            quantity=lambda scene, point_pos, body_pos: point_pos[:, [scene.point_names.index("payload")]],
            vector=True,
            t_end=2.0,
            reference_check=("sim.integrator=tsit5", "sim.rtol=1e-12", "sim.atol=1e-14", "sim.precision=float64"),
            methods=slack_methods(quick),
            order_note=True,
            tolerances=(1e-2, 1e-3, 1e-4, 1e-6),
            highlights=tolerance_highlights,
            notes=("`model: tension_only` ropes whose anchors are 0.71 m from the payload (rope length 1 m): "
                   "they start slack, the payload falls about 0.6 m, the ropes snap taut and it bounces; over 2 s "
                   "the 24 rope segments switch between slack and taut about 360 times (tsit5 reference). At "
                   "every switch the force has a kink (spring) and a jump (the damper, 50 N s/m, switches on "
                   "at once).",),
        ),
        dataclasses.replace(
            rope_net,
            name="rope_net_stiff",
            order_note=False,
            overrides=STIFF_ROPES,
            reference=("sim.integrator=tsit5", "sim.rtol=1e-10", "sim.atol=1e-12", "sim.precision=float64",
                       "sim.max_steps=3000000"),
            reference_check=("sim.integrator=rk4", "sim.dt=1e-6", "sim.substeps=1", "sim.precision=float64"),
            methods=stiff_methods(quick),
            tolerances=(1e-2, 5e-3, 1e-3, 1e-5),
            highlights=tolerance_highlights,
            notes=(f"The rope net with every line 10,000x stiffer (`ropes.*.EA={STIFF_EA:g}`; each of the 6 segments "
                   "of a line is a 6e9 N/m spring: a Dyneema line of EA 1e7 N lumped every 1.7 mm would be as stiff). "
                   "The payload's motion (its fall, the bounce, the net's transverse swing) stays slow, "
                   "but the axial modes of the lines are 100x faster than on the paper's net, so every explicit method is held "
                   "to steps of a few microseconds by stability, not accuracy. implicit_euler takes the lines "
                   "implicitly (the net has no contact and no body markers, so nothing explicit limits its step).",),
        ),
    ] + [
        AccuracyCase(
            name=config.stem,
            config=config,
            quantity_label="ball and payload z [m]",
            quantity=ball_and_payload_z,
            t_end=1.5,
            overrides=("contact.friction=null",),      # friction off for the comparison
            reference=("sim.integrator=tsit5", "sim.rtol=1e-13", "sim.atol=1e-15", "sim.precision=float64",
                       "sim.max_steps=3000000"),
            methods=contact_methods(quick, light=config is COLLISION_LIGHT),
            drift_tolerance=2e-3,
            notes=("Friction is off in every run (`contact.friction=null`; on the scene's symmetry axis the slip is "
                   "zero anyway).",),
        )
        for config in ((COLLISION_LIGHT,) if quick else (COLLISION_LIGHT, COLLISION_HEAVY))   # quick: a smoke test
    ] + [
        AccuracyCase(
            name="capture_falling",
            config=CAPTURE_FALLING,
            quantity_label="target and net-knot positions [m]",
            quantity=target_and_knots,
            vector=True,
            extra=(("target", target_position),),
            t_end=1.6,
            reference_dt=1e-2,
            overrides=CAPTURE_SPAWN,
            reference=("sim.integrator=rk4", f"sim.substeps={52 if quick else 400}", "sim.precision=float64"),
            reference_check=() if quick else ("sim.integrator=rk4", "sim.substeps=200", "sim.precision=float64"),
            methods=capture_methods(quick),
            policy=team_policy,
            drift_tolerance=1e-2,
            order_note=True,
            tolerances=(1e-2, 1e-3),
            highlights=tolerance_highlights,
            notes=("Closed loop: every method runs the scene's scripted team policy "
                   "(`mysim_jax.tasks.scripted.team_policy`) and cascaded PID once per 2 ms control period "
                   "(`sim.dt` is kept; the methods differ in `sim.substeps` or, for tsit5, in one adaptive diffrax "
                   "solve per control period). The target falls from 6.2 m, hits the net at about 1.2 s and "
                   "sinks into it; tethers and net lines are tension-only, so they switch between slack and taut "
                   "all along. The error is over the target and the 121 net knots (3-D distance); the target alone "
                   "is the second error column. The target's spawn is fixed (`target.spawn` low = high) so that "
                   "float32 and float64 runs start alike.",),
        ),
    ]


_REFERENCE_CACHE: dict[str, tuple] = {}


@contextmanager
def precision_mode(precision: str):
    """float64 runs need JAX's x64 mode; float32 runs use the default 32-bit mode."""
    if precision == "float64":
        with jax.enable_x64(True):
            yield
    else:
        with jax.enable_x64(False):
            yield


def _case_run(case: AccuracyCase, overrides: list[str]):
    """Build the case's scene with ``overrides`` on top of its own and compile its run:
    ``(scene, run)``. Raises ConfigError for a setting the config or builder rejects."""
    config = load_config(case.config, list(case.overrides) + overrides)
    scene, params, state = build(config)
    policy = None if case.policy is None else case.policy(config, scene)
    return scene, _compile_run(scene, params, state, config.run_settings(), policy)


def reference_solution(case: AccuracyCase, settings: tuple[str, ...] | None = None):
    """``(times, (point_pos (n_out, n_points, 3), body_pos (n_out, n_bodies, 3)), scene,
    wall_s)`` of the case's reference run (or of another float64 ``settings`` on the
    reference grid)."""
    key = (case.name, settings)
    if key in _REFERENCE_CACHE:
        return _REFERENCE_CACHE[key]
    overrides = list(case.reference if settings is None else settings) + [
        f"sim.t_end={case.t_end:g}", f"sim.output_dt={case.reference_dt:g}"]
    with precision_mode("float64"):
        scene, run = _case_run(case, overrides)
        t0 = time.perf_counter()
        pos = tuple(np.asarray(x) for x in jax.block_until_ready(run.call()))
        wall = time.perf_counter() - t0
    out = (run.times, pos, scene, wall)
    _REFERENCE_CACHE[key] = out
    return out


def case_error(case: AccuracyCase, quantity: Callable, scene, pos, ref_q, idx=None) -> np.ndarray:
    """Error of ``quantity`` against its reference values ``ref_q`` at every output time
    ``(n_out,)``: the largest absolute coordinate difference, or with ``case.vector`` the
    largest distance. ``idx`` picks the reference rows of the output times."""
    q = quantity(scene, *(np.asarray(x, dtype=np.float64) for x in pos))
    diff = q - (ref_q if idx is None else ref_q[idx])
    err = np.linalg.norm(diff, axis=-1) if case.vector else np.abs(diff)
    return err.reshape(len(err), -1).max(axis=1)


@dataclass
class _Run:
    call: Callable[[], Any]        # returns (point_pos (n_out, n_points, 3), body_pos (n_out, n_bodies, 3))
    times: np.ndarray
    compile_s: float


def _compile_run(scene, params, state, run_settings, policy=None) -> _Run:
    """AOT-compile the whole run of a scene to ``t_end`` on its output grid (one env).

    Stepped (fixed-step integrators, and every scene with quadrotors or effects, whose
    controller and effect updates act once per env step ``dt``): one ``rollout`` scan saving
    every ``output_dt``, asking ``policy`` (if given) for the control of every step; an
    adaptive integrator then solves each env step with diffrax. Otherwise adaptive: the
    library's ``solve_adaptive`` over the whole run, saving at the grid. These are the
    computations ``mysim_jax.sim.simulate`` does (with its ``single_env_scene``), minus its
    host-side chunking and the acceleration pass.
    """
    scene = single_env_scene(scene)
    times = output_times(run_settings)
    if scene.integrator in FIXED_STEP or scene.quadrotor is not None or scene.effects:
        every = steps_per_output(scene, run_settings)
        n_steps = (len(times) - 1) * every

        def run(p, s):
            _, traj = rollout(scene, p, s, n_steps, every, policy)
            return (jnp.concatenate([s.phys.point_pos[None], traj.phys.point_pos], axis=0),
                    jnp.concatenate([s.phys.body_pos[None], traj.phys.body_pos], axis=0))
        args = (params, state)
    else:
        ts = jnp.asarray(times, dtype=scene.dtype)

        def run(p, y):
            ys = solve_adaptive(scene, p, y, ts[0], ts[-1], ts)
            return ys.point_pos, ys.body_pos
        args = (params, state.phys)
    t0 = time.perf_counter()
    compiled = jax.jit(run).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    return _Run(lambda: compiled(*args), times, compile_s)


# =========================================================================================
# (c) MuJoCo
# =========================================================================================


def section_c(cfg, results) -> list[str]:
    try:
        import mujoco
    except ImportError:
        return ["## (c) MuJoCo", "", "MuJoCo is not installed (`pip install mujoco`); section skipped.", ""]
    from mysim_jax.io.mjcf import mujoco_point_positions, scene_to_mjcf

    case = accuracy_cases(cfg.quick)[0]
    bar = tqdm(total=5 + 2 * cfg.repeats, desc="(c) MuJoCo", leave=False)
    ref_times, (ref_pos, _), ref_scene, _ = reference_solution(case)
    bar.update(1)
    payload = ref_scene.point_names.index("payload")
    h = 1e-4
    overrides = ["sim.integrator=semi_implicit_euler", "sim.precision=float64", f"sim.dt={h:g}", "sim.substeps=1",
                 f"sim.t_end={case.t_end:g}", f"sim.output_dt={case.reference_dt:g}"]
    with precision_mode("float64"):
        config = load_config(ROPE_NET, overrides)
        scene, params, state = build(config)
        ours_pos = np.asarray(_compile_run(scene, params, state, config.run_settings()).call()[0])
        xml = scene_to_mjcf(scene, params, state, h)
    bar.update(1)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    every = int(round(case.reference_dt / h))

    def trajectory(integrator):
        model.opt.integrator = integrator
        mujoco.mj_resetDataKeyframe(model, data, 0)
        out = [mujoco_point_positions(model, data)]
        for _ in range(len(ref_times) - 1):
            mujoco.mj_step(model, data, nstep=every)
            out.append(mujoco_point_positions(model, data))
        return np.stack(out)

    euler = mujoco.mjtIntegrator.mjINT_EULER
    rk4 = mujoco.mjtIntegrator.mjINT_RK4
    mj_euler = trajectory(euler)
    mj_rk4 = trajectory(rk4)
    bar.update(1)

    n_time = int(round(case.t_end / h))

    def mj_run(integ):
        def call():
            model.opt.integrator = integ
            mujoco.mj_resetDataKeyframe(model, data, 0)
            mujoco.mj_step(model, data, nstep=n_time)
        return call

    wait_for_quiet(cfg.max_wait_s, "c")
    # the reset inside each call is < 1e-5 of the call's time
    timings = time_round_robin({"Euler": mj_run(euler), "RK4": mj_run(rk4)}, cfg.repeats, bar, section="c")
    bar.close()
    sps = {k: n_time / median(v) for k, v in timings.items()}
    results["mujoco_steps_per_s"] = sps["Euler"]
    err_euler = np.abs(mj_euler[:, payload, 2] - ref_pos[:, payload, 2]).max()
    err_rk4 = np.abs(mj_rk4[:, payload, 2] - ref_pos[:, payload, 2]).max()
    err_ours = np.abs(ours_pos[:, payload, 2] - ref_pos[:, payload, 2]).max()
    same_map = np.abs(mj_euler - ours_pos).max()
    results["mujoco_err"] = err_euler

    lines = [
        "## (c) MuJoCo on the same net",
        "",
        f"The float64 scene exported by `mysim_jax.io.mjcf.scene_to_mjcf` (point masses on three slide joints, "
        f"{model.ntendon} spatial tendons with stiffness/damping/springlength, contact off), MuJoCo "
        f"{mujoco.__version__}, step {h:g} s. Steps/s = {n_time} steps in one `mujoco.mj_step(m, d, nstep={n_time})` "
        f"call (the 2 s run from rest), median of {cfg.repeats}, one thread (MuJoCo's `mj_step` does not use a "
        "thread pool unless one is attached). MuJoCo always computes in float64.",
        "",
        "| engine | integrator | steps/s | spread | max \\|payload z − reference\\| over 2 s [m] |",
        "|---|---|---:|---:|---:|",
        f"| MuJoCo | Euler (semi-implicit), {h:g} s | {sps['Euler']:,.0f} | {spread(timings['Euler'])} | {err_euler:.3e} |",
        f"| MuJoCo | RK4, {h:g} s | {sps['RK4']:,.0f} | {spread(timings['RK4'])} | {err_rk4:.3e} |",
        f"| mysim_jax float64, 1 env | semi-implicit Euler, {h:g} s | (see d) | | {err_ours:.3e} |",
        "",
        f"Reference: float64 tsit5 at rtol 1e-11, atol 1e-13 (part d), compared on its {case.reference_dt:g} s "
        f"output grid. MuJoCo's Euler and our float64 semi-implicit Euler take the same discrete steps: their "
        f"positions differ by at most {same_map:.2e} m over the whole 2 s (all {scene.n_points} masses), i.e. "
        "round-off — so the exporter, the tendon force law (k(s − s̄) + c ṡ along the segment, damping explicit) "
        "and the velocity-first Euler update are the same in both engines.",
        "",
        contention_note("c", cfg.repeats),
        "",
    ]
    if "ours_4096" in results:
        ratio = results["ours_4096"] / sps["Euler"]
        results["ratio"] = ratio
        met = ratio >= TARGET_MUJOCO_RATIO
        lines += [
            f"**Ours at B = {HEADLINE_BATCH} (float32, section a) / MuJoCo Euler single thread = "
            f"{results['ours_4096']:,.0f} / {sps['Euler']:,.0f} = {ratio:.1f}×. Target ≥ {TARGET_MUJOCO_RATIO:.0f}×: "
            f"{'MET' if met else 'NOT MET'}.** (Ours uses both cores of the machine; MuJoCo one. A fair per-core "
            f"comparison halves our figure.)",
            "",
        ]
    else:
        lines += ["(Run section a in the same invocation for the ours / MuJoCo ratio.)", ""]
    return lines


# =========================================================================================
# (d) accuracy against cost
# =========================================================================================


@dataclass
class AccuracyRow:
    case: str
    method: Method
    status: str                      # "ok" / "unstable (rejected)" / "diverged" / "failed: ..."
    error: float = float("nan")
    wall_per_sim_s: float = float("nan")
    compile_s: float = float("nan")
    n_repeats: int = 0
    drift_time: float | None = None  # first output time with error > case.drift_tolerance (None: never)
    extra_errors: tuple[float, ...] = ()   # errors of case.extra, in order


def run_method(case: AccuracyCase, method: Method, ref_qs, cfg) -> AccuracyRow:
    """Run one integrator setting; error of the case's quantity (and of ``case.extra``)
    against the reference values ``ref_qs`` (the same order) on the reference grid."""
    overrides = list(method.overrides) + [f"sim.precision={method.precision}"]
    # the output grid must hold whole steps and land on the reference grid; the run ends on
    # the last output at or before case.t_end (t_end must be a whole multiple of output_dt)
    dt = float(next((o.split("=", 1)[1] for o in method.overrides if o.startswith("sim.dt=")), case.reference_dt))
    mult = 1
    while abs(round(mult * case.reference_dt / dt) - mult * case.reference_dt / dt) > 1e-9:
        mult += 1
    out_dt = mult * case.reference_dt
    overrides += [f"sim.output_dt={out_dt:g}", f"sim.t_end={math.floor(case.t_end / out_dt + 1e-9) * out_dt!r}"]
    if method.max_steps is not None:
        overrides.append(f"sim.max_steps={method.max_steps}")
    with precision_mode(method.precision):
        try:
            scene, run = _case_run(case, overrides)
        except ConfigError as err:
            if "stability limit" in str(err):
                return AccuracyRow(case.name, method, "unstable (rejected)")
            return AccuracyRow(case.name, method, f"config error: {str(err).splitlines()[0]}")
        try:
            # timed calls until `accuracy_repeats` quiet ones (others < QUIET_SHARE of the
            # machine) or the time budget is spent; expensive runs are timed once
            walls, quiet, shares, pos = [], [], [], None
            while True:
                a = CPU.sample()
                t0 = time.perf_counter()
                out = jax.block_until_ready(run.call())
                walls.append(time.perf_counter() - t0)
                shares.append(CPU.share(a, CPU.sample()))
                if not shares[-1] >= QUIET_SHARE:
                    quiet.append(walls[-1])
                if pos is None:
                    pos = tuple(np.asarray(x) for x in out)
                if (len(quiet) >= cfg.accuracy_repeats or sum(walls) > cfg.accuracy_time_budget
                        or len(walls) >= 3 * cfg.accuracy_repeats):
                    break
            record_contention("d", shares)
            if quiet:
                walls = quiet
        except Exception as err:  # noqa: BLE001 - diffrax max_steps, XLA runtime errors
            msg = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            if "max_steps" in str(err) or "maximum number of solver steps" in str(err):
                msg = f"did not finish: hit max_steps = {method.max_steps}"
            return AccuracyRow(case.name, method, msg[:120])
    idx = np.rint(run.times / case.reference_dt).astype(int)
    quantities = [case.quantity] + [q for _, q in case.extra]
    errs = [case_error(case, q, scene, pos, ref_q, idx) for q, ref_q in zip(quantities, ref_qs)]
    if not all(np.all(np.isfinite(e)) for e in errs):
        return AccuracyRow(case.name, method, "diverged (non-finite)", compile_s=run.compile_s)
    err_t = errs[0]
    err = float(err_t.max())
    drift = None
    if case.drift_tolerance is not None and err > case.drift_tolerance:
        drift = float(run.times[np.argmax(err_t > case.drift_tolerance)])
    status = "ok" if err < 1.0 else "diverged"
    return AccuracyRow(case.name, method, status, err, median(walls) / float(run.times[-1]), run.compile_s, len(walls),
                       drift, tuple(float(e.max()) for e in errs[1:]))


def adaptive_stats(case: AccuracyCase, method: Method, t_stats: float):
    """Accepted / rejected steps of an adaptive method over ``[0, t_stats]``, from the
    statistics ``mysim_jax.sim.solve_adaptive(..., stats=True)`` returns."""
    overrides = list(case.overrides) + list(method.overrides) + [
        f"sim.precision={method.precision}", f"sim.t_end={t_stats:g}", f"sim.output_dt={t_stats:g}"]
    if method.max_steps is not None:
        overrides.append(f"sim.max_steps={method.max_steps}")
    with precision_mode(method.precision):
        scene, params, state = build(load_config(case.config, overrides))

        def solve(p, y):
            return solve_adaptive(scene, p, y, 0.0, t_stats, stats=True)[1]

        t0 = time.perf_counter()
        st = jax.jit(solve)(params, state.phys)
        wall = time.perf_counter() - t0
    return int(st["num_accepted_steps"]), int(st["num_rejected_steps"]), bool(st["successful"]), wall


def section_d(cfg, results) -> list[str]:
    lines = ["## (d) Accuracy against cost", ""]
    all_rows = []
    for case in accuracy_cases(cfg.quick):
        if cfg.cases and case.name not in cfg.cases:
            continue
        bar = tqdm(total=1 + len(case.methods), desc=f"(d) accuracy {case.name}", leave=False)
        ref_times, ref_pos, ref_scene, ref_wall = reference_solution(case)
        ref_qs = [q(ref_scene, *ref_pos) for q in [case.quantity] + [q for _, q in case.extra]]
        bar.update(1)
        rows = []
        for method in case.methods:
            bar.set_postfix_str(f"{method.integrator} {method.setting} {method.precision}")
            rows.append(run_method(case, method, ref_qs, cfg))
            bar.update(1)
        bar.close()
        all_rows += rows
        plot = plot_accuracy(case, rows, cfg.plots_dir)
        what = case.quantity_label.split(" [")[0]
        measure = (f"the 3-D distance |{what} − reference| (the largest over the points)" if case.vector
                   else f"|{what} − reference|")
        lines += [
            f"### {case.name}: {case.quantity_label}",
            "",
            f"Reference: `{case.config.relative_to(ROOT)}` with `{' '.join(case.overrides + case.reference)}` "
            f"(its wall time {ref_wall:.1f} s). Error = max over the output grid of {measure} "
            f"up to {case.t_end:g} s (grid {case.reference_dt:g} s; for steps that do not "
            f"divide {case.reference_dt:g} s, the nearest common multiple, e.g. 3 ms for dt = 3e-4, and the run ends at "
            f"the last output at or before {case.t_end:g} s). "
            "Cost = wall time per simulated second of one env: the whole run AOT-compiled with `jax.jit` "
            "(stepped — fixed-step integrators, and scenes with quadrotors or effects, whose controller acts once per "
            "env step: one `mysim_jax.sim.rollout` scan saving every output step; otherwise adaptive: "
            "`mysim_jax.sim.solve_adaptive` saving at the grid), timed after compilation, median of up to "
            f"{cfg.accuracy_repeats} runs while other processes used < {100 * QUIET_SHARE:.0f}% of the machine "
            f"(at most {3 * cfg.accuracy_repeats} runs and {cfg.accuracy_time_budget:g} s per row, so long runs are "
            "timed once). "
            "This is the computation `simulate()` performs (one env, `segment_sum` accumulation), without its "
            "host-side chunking and acceleration pass, and with compilation timed apart. Adaptive tolerances use atol = rtol / 100 unless the setting names atol.",
            "",
        ]
        lines += [x for note in case.notes for x in (note, "")]
        if case.reference_check:
            chk_times, chk_pos, chk_scene, chk_wall = reference_solution(case, case.reference_check)
            agree = [case_error(case, q, chk_scene, chk_pos, rq).max()
                     for q, rq in zip([case.quantity] + [q for _, q in case.extra], ref_qs)]
            results.setdefault("reference_check", {})[case.name] = agree
            lines += [
                f"The reference's own error: a second tight setting, `{' '.join(case.reference_check)}` (wall time "
                f"{chk_wall:.1f} s), is {agree[0]:.1e} m from it ("
                + ", ".join([f"{what}"] + [label for label, _ in case.extra])
                + (": " + ", ".join(f"{a:.1e} m" for a in agree) if case.extra else "")
                + "); errors well above this are errors of the compared method.",
                "",
            ]
        tol = case.drift_tolerance
        extra_head = "".join(f" max error, {label} [m] |" for label, _ in case.extra)
        extra_align = "---:|" * len(case.extra)
        if tol is not None:
            lines += [
                f"*Drifts past {tol:g} m at* = first output time at which the error is more than {tol:g} m "
                f"(— : never within {case.t_end:g} s).",
                "",
                f"| integrator | setting | precision | max error [m] |{extra_head} drifts past {tol:g} m at [s] | "
                "wall s / simulated s | compile [s] | status |",
                f"|---|---|---|---:|{extra_align}---:|---:|---:|---|",
            ]
        else:
            lines += [
                f"| integrator | setting | precision | max error [m] |{extra_head} wall s / simulated s | compile [s] | "
                "status |",
                f"|---|---|---|---:|{extra_align}---:|---:|---|",
            ]
        for r in rows:
            m = r.method
            err = f"{r.error:.3e}" if np.isfinite(r.error) else "—"
            err += "".join(f" | {e:.3e}" for e in r.extra_errors) if r.extra_errors else " | —" * len(case.extra)
            wall = f"{r.wall_per_sim_s:.3f}" if np.isfinite(r.wall_per_sim_s) else "—"
            comp = f"{r.compile_s:.1f}" if np.isfinite(r.compile_s) else "—"
            status = r.status + (f" ({m.note})" if m.note and r.status == "ok" else "")
            if tol is not None:
                drift = "—" if r.drift_time is None or not np.isfinite(r.error) else f"{r.drift_time:.3f}"
                if not np.isfinite(r.error):
                    drift = "n/a"
                lines.append(f"| {m.integrator} | {m.setting} | {m.precision} | {err} | {drift} | {wall} | {comp} "
                             f"| {status} |")
            else:
                lines.append(f"| {m.integrator} | {m.setting} | {m.precision} | {err} | {wall} | {comp} | {status} |")
        lines += ["", f"![accuracy {case.name}](docs/bench/{plot.name})", ""]
        if case.highlights is not None:
            lines += case.highlights(case, rows)
        else:
            lines += accuracy_highlights(rows) if tol is None else contact_highlights(case, rows)
        if case.order_note:
            orders = observed_orders(rows)
            results.setdefault("orders", {})[case.name] = orders
            lines += order_lines(case, orders)
        adaptive = [m for m in case.methods if m.integrator in ("tsit5", "kvaerno5")]
        if adaptive:
            t_stats = 0.25
            lines += [
                f"Adaptive solver statistics over the first {t_stats:g} s (a separate "
                "`solve_adaptive(..., stats=True)` over that interval):",
                "",
                "| integrator | setting | precision | accepted | rejected | rejected share | mean accepted step [s] |",
                "|---|---|---|---:|---:|---:|---:|",
            ]
            for m in adaptive:
                st = adaptive_stats(case, m, t_stats)
                if st is None:
                    continue
                acc, rej, ok, _ = st
                lines.append(f"| {m.integrator} | {m.setting} | {m.precision} | {acc:,} | {rej:,} | "
                             f"{rej / max(1, acc + rej):.0%} | {t_stats / max(1, acc):.2e}"
                             + ("" if ok else " (stopped at max_steps)") + " |")
            lines.append("")
        lines += [accuracy_contention_note(), ""]
    if not cfg.quick and not any(r.method.integrator == "kvaerno5" for r in all_rows):
        lines += ["kvaerno5 was not run.", ""]
    results["d"] = all_rows
    return lines


def contact_highlights(case: AccuracyCase, rows: list[AccuracyRow]) -> list[str]:
    """Issue #3: which path is fastest for equal accuracy, and how far the fast fixed-step
    paths get before they drift.

    The contact scenes are chaotic: an error made at one impact is amplified ~10³ by the
    later ones, so a single run that ends just inside the tolerance may be luck (another
    initial step or precision lands outside, see the dt0 rows). "Equal accuracy" is
    therefore judged with a 10× margin: max error ≤ tolerance / 10 over the whole run."""
    tol = case.drift_tolerance
    margin = tol / 10
    ok = [r for r in rows if r.status == "ok"]

    def name(r):
        return f"{r.method.integrator} {r.method.setting} {r.method.precision}"

    def fastest(pred):
        cands = sorted((r for r in ok if pred(r)), key=lambda r: r.wall_per_sim_s)
        return cands[0] if cands else None

    out = []
    lucky = fastest(lambda r: r.error <= tol)
    best = fastest(lambda r: r.error <= margin)
    if lucky is not None:
        out.append(f"- Fastest single run within {tol:g} m over {case.t_end:g} s: {name(lucky)} ({lucky.error:.1e} m, "
                   f"{lucky.wall_per_sim_s:.3f} s per simulated s).")
    if best is None:
        return out + [f"- no run stays within {margin:g} m (tolerance / 10).", ""]
    out.append(f"- Fastest within {margin:g} m (tolerance / 10, robust to the scene's chaos): **{name(best)}** "
               f"({best.error:.1e} m, {best.wall_per_sim_s:.3f} s per simulated s).")
    for family in ("semi_implicit_euler", "rk4", "kvaerno5"):
        tried = [r for r in rows if r.method.integrator == family]
        if not tried:
            continue
        fam = fastest(lambda r: r.method.integrator == family and r.error <= margin)
        if fam is not None:
            out.append(f"- fastest {family} within {margin:g} m: {name(fam)} at {fam.wall_per_sim_s:.3f} s/sim-s = "
                       f"{fam.wall_per_sim_s / best.wall_per_sim_s:.1f}× the time of the fastest.")
        else:
            reach = [f"{r.method.setting} {r.method.precision}: "
                     + (f"{r.error:.1e} m" + (f", drifts past {tol:g} m at {r.drift_time:.3f} s" if r.drift_time else "")
                        + f", {r.wall_per_sim_s:.3f} s/sim-s" if r.status == "ok" else r.status) for r in tried]
            out.append(f"- no {family} run stays within {margin:g} m (" + "; ".join(reach) + ").")
    for r in rows:
        if r.status != "ok":
            out.append(f"- {name(r)}: {r.status}")
    return out + [""]


def observed_orders(rows: list[AccuracyRow]) -> dict[tuple[str, str], dict]:
    """Observed order p of each fixed-step integrator and precision (error ∝ h^p): the
    least-squares slope of log(error) against log(h) over its stable runs, and the slope
    between each pair of neighbouring steps."""
    out = {}
    for integ in FIXED_STEP:
        for prec in ("float64", "float32"):
            pts = sorted((r.method.step, r.error) for r in rows if r.method.integrator == integ
                         and r.method.precision == prec and r.status == "ok" and r.method.step and r.error > 0)
            if len(pts) < 2:
                continue
            h, e = np.log(np.array(pts)).T
            pair = [float((e[i + 1] - e[i]) / (h[i + 1] - h[i])) for i in range(len(pts) - 1)]
            out[(integ, prec)] = {"slope": float(np.polyfit(h, e, 1)[0]), "pairs": pair,
                                  "steps": [x for x, _ in pts], "errors": [y for _, y in pts]}
    return out


def order_lines(case: AccuracyCase, orders: dict) -> list[str]:
    if not orders:
        return []
    out = [f"Observed order on {case.name} (error ∝ h^p; least-squares slope of log error against log h over the "
           "stable runs, and the slope between neighbouring steps):", ""]
    for (integ, prec), o in orders.items():
        steps = ", ".join(f"{h:.2g}" for h in o["steps"])
        pairs = ", ".join(f"{x:.2f}" for x in o["pairs"])
        out.append(f"- {integ} {prec}: **p = {o['slope']:.2f}** (h = {steps} s; neighbouring slopes {pairs})")
    return out + [""]


def accuracy_contention_note() -> str:
    shares = contention_shares("d")
    if not shares:
        return "(CPU contention not measured: no /proc on this system.)"
    quiet = sum(x < QUIET_SHARE for x in shares)
    text = (f"Machine contention: other processes used a median {100 * median(shares):.0f}% (max "
            f"{100 * max(shares):.0f}%) of the machine's CPU during the {len(shares)} timed runs; {quiet} were quiet "
            f"(< {100 * QUIET_SHARE:.0f}%). Each row's wall time is the median of its quiet runs when it has any, "
            "else of all its runs")
    if quiet < len(shares) / 2:
        text += " — **most runs were not quiet, so wall times are inflated by the other load**"
    return text + "."


def accuracy_highlights(rows: list[AccuracyRow]) -> list[str]:
    ok = [r for r in rows if r.status == "ok"]
    out = []
    if not ok:
        return out

    def best_under(tol):
        cands = [r for r in ok if r.error <= tol]
        return min(cands, key=lambda r: r.wall_per_sim_s) if cands else None

    for tol in (2e-4, 1e-6, 1e-9):
        r = best_under(tol)
        if r is not None:
            out.append(f"- cheapest run within {tol:g} m: {r.method.integrator} {r.method.setting} "
                       f"{r.method.precision} ({r.error:.1e} m, {r.wall_per_sim_s:.3f} s per simulated s)")
    rejected = [r for r in rows if r.status != "ok"]
    for r in rejected:
        out.append(f"- {r.method.integrator} {r.method.setting} {r.method.precision}: {r.status}")
    return out + [""]


def plot_accuracy(case: AccuracyCase, rows: list[AccuracyRow], plots_dir: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    markers = {"semi_implicit_euler": "o", "rk4": "s", "tsit5": "^", "kvaerno5": "D"}
    colors = {"semi_implicit_euler": "C0", "rk4": "C1", "tsit5": "C2", "kvaerno5": "C3"}
    fig, ax = plt.subplots(figsize=(7.5, 5.5))
    groups: dict[tuple, list[AccuracyRow]] = {}
    for r in rows:
        if r.status == "ok" and r.error > 0:
            groups.setdefault((r.method.integrator, r.method.precision), []).append(r)
    for (integ, prec), rs in groups.items():
        rs = sorted(rs, key=lambda r: r.wall_per_sim_s)
        x = [r.wall_per_sim_s for r in rs]
        y = [r.error for r in rs]
        filled = prec == "float64"
        ax.plot(x, y, marker=markers.get(integ, "x"), color=colors.get(integ, "k"), ls="-" if filled else "--",
                mfc=colors.get(integ, "k") if filled else "white", ms=7, lw=1,
                label=f"{integ} ({prec})")
        for r in rs:
            ax.annotate(r.method.setting.split("= ", 1)[-1], (r.wall_per_sim_s, r.error), textcoords="offset points",
                        xytext=(4, 3), fontsize=7, color=colors.get(integ, "k"))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time per simulated second [s] (one env, CPU)")
    ax.set_ylabel(f"max |{case.quantity_label.split(' [')[0]} − reference| [m]")
    ref_rtol = next((o.split("=", 1)[1] for o in case.reference if o.startswith("sim.rtol=")), "?")
    ax.set_title(f"{case.name}: accuracy against cost (reference: tsit5 rtol {ref_rtol}, float64)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = plots_dir / f"accuracy_{case.name}.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# =========================================================================================
# (f) profile by stage variants
# =========================================================================================


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
    ops = {}
    for op in ("gather", "scatter", "transpose", "copy", "dot", "concatenate", "fusion"):
        ops[op] = len(re.findall(rf"= \S+ {op}\(", text))
    return ops


def section_f(cfg, results) -> list[str]:
    scene, params, state = _throughput_scene()
    B = HEADLINE_BATCH
    K = steps_for_batch(B, cfg.env_steps_per_call)
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
    if cfg.quick:
        keep = {"library", "first", "index", "floor", "kernel"}
        variants = [v for v in variants if v[0] in keep]
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


# =========================================================================================
# plots for a/c and the summary
# =========================================================================================


def plot_throughput(results, plots_dir: Path) -> Path | None:
    if "a" not in results:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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


def summary_lines(results) -> list[str]:
    out = ["## Summary", ""]
    if "emitter_speedup" in results:
        out.append("- XLA CPU code generation (j): XLA's older emitters (the test suite's) run the same programs "
                   + ", ".join(f"{x:.2f}×" for x in results["emitter_speedup"].values())
                   + " as fast as its default fusion emitters (capture env train, capture env full, rope net).")
    if "ours_4096" in results:
        v = results["ours_4096"]
        out.append(f"- Throughput (a) at B = {HEADLINE_BATCH}: **{v:,.0f} env-steps/s** — target ≥ {TARGET_ENV_STEPS:,}: "
                   f"**{'met' if v >= TARGET_ENV_STEPS else 'NOT met'}**.")
    if "kernel_ratio" in results:
        r = results["kernel_ratio"]
        out.append("- Library (batch-last, `mysim_jax.core.batching.vmap`) / hand-written batch-last kernel (a), same run: "
                   + ", ".join(f"B={b}: **{x:.2f}×**" for b, x in r.items())
                   + f" — target ≥ {TARGET_KERNEL_RATIO}× at B = 1024 and 4096: "
                   f"**{'met' if results['kernel_met'] else 'NOT met'}**.")
    if "env_rows" in results:
        top = results["env_rows"][-1]
        out.append(f"- Capture environment (e), scripted team, B = {top.batch}: **{top.env_steps_per_s:,.1f} team "
                   f"(policy) steps/s** — target ≥ {TARGET_POLICY_STEPS:,}: "
                   f"**{'met' if top.env_steps_per_s >= TARGET_POLICY_STEPS else 'NOT met'}** (where the time goes: (e)).")
    if "mujoco_steps_per_s" in results:
        out.append(f"- MuJoCo (c), Euler, one thread: **{results['mujoco_steps_per_s']:,.0f} steps/s**; its payload z "
                   f"is {results['mujoco_err']:.2e} m from the float64 reference.")
    if "ratio" in results:
        r = results["ratio"]
        out.append(f"- Ours@{HEADLINE_BATCH} (a) / MuJoCo (c) = **{r:.1f}×** — target ≥ {TARGET_MUJOCO_RATIO:.0f}×: "
                   f"**{'met' if r >= TARGET_MUJOCO_RATIO else 'NOT met'}**.")
    if "b" in results:
        out.append("- Node-force accumulation, env-steps/s (b): " + "; ".join(
            f"B={b}: " + ", ".join(f"{m} {x:,.0f}" for m, x in row.items()) for b, row in results["b"].items()) + ".")
    if "d" in results:
        rows = {(r.method.integrator, r.method.setting, r.method.precision): r for r in results["d"]
                if r.case == "rope_net"}
        picks = [("semi_implicit_euler", "dt = 1e-04", "float32"), ("semi_implicit_euler", "dt = 1e-04", "float64"),
                 ("rk4", "dt = 1e-04", "float64"), ("tsit5", "rtol = 1e-08", "float64"),
                 ("kvaerno5", "rtol = 1e-04", "float64")]
        parts = [f"{k[0]} {k[1].split('= ')[1]} {k[2]}: {rows[k].error:.1e} m at {rows[k].wall_per_sim_s:.3f} s/sim-s"
                 for k in picks if k in rows and rows[k].status == "ok"]
        if parts:
            out.append("- Accuracy (d), max |payload z − reference| over 2 s, single env: " + "; ".join(parts) + ".")
    for case in ("collision_light", "collision_heavy"):
        if "d" not in results:
            break
        crows = [r for r in results["d"] if r.case == case and r.status == "ok"]
        default = next((r for r in crows if r.method.integrator == "tsit5" and r.method.setting == "rtol = 1e-12"
                        and r.method.precision == "float64"), None)
        fixed = [r for r in crows if r.method.integrator in ("semi_implicit_euler", "rk4")]
        if default is not None:
            line = (f"- Contact (d), {case}: default tsit5 rtol 1e-12 float64 is {default.error:.1e} m from the reference "
                    f"(ball and payload z, 1.5 s) at {default.wall_per_sim_s:.2f} s/sim-s")
            if fixed:
                closest = min(fixed, key=lambda r: r.error)
                line += (f"; most accurate fixed-step run: {closest.method.integrator} {closest.method.setting} "
                         f"{closest.method.precision}, {closest.error:.1e} m"
                         + ("" if closest.drift_time is None else f" (past 2e-3 m at {closest.drift_time:.2f} s)")
                         + f", {closest.wall_per_sim_s:.2f} s/sim-s")
            out.append(line + ".")
    if "capture_throughput" in results:
        row, n_sub, first = results["capture_throughput"]
        out.append(f"- Capture scene (a), float32, B = {row.batch}, scripted team policy: "
                   f"**{row.env_steps_per_s:,.0f} env-steps/s** (2 ms control periods) = "
                   f"{row.env_steps_per_s * n_sub:,.0f} physics sub-steps/s ({n_sub} sub-steps each); "
                   f"with `jax.vmap` (batch first) {first.env_steps_per_s:,.0f} "
                   f"({row.env_steps_per_s / first.env_steps_per_s:.2f}×).")
    for case, orders in results.get("orders", {}).items():
        parts = [f"{integ} {prec} p = {o['slope']:.2f}" for (integ, prec), o in orders.items() if prec == "float64"]
        if parts:
            out.append(f"- Observed order (d), {case}: " + ", ".join(parts) + ".")
    for case in ("rope_net_slack", "capture_falling"):
        crows = [r for r in results.get("d", []) if r.case == case and r.status == "ok"]
        if not crows:
            continue
        tol = 1e-2 if case == "capture_falling" else 1e-3
        err = (lambda r: r.extra_errors[0]) if case == "capture_falling" else (lambda r: r.error)
        what = "target position" if case == "capture_falling" else "payload position"
        best = sorted((r for r in crows if err(r) <= tol), key=lambda r: r.wall_per_sim_s)
        if best:
            r = best[0]
            out.append(f"- Accuracy (d), {case}: cheapest run with the {what} within {tol:g} m: {r.method.integrator} "
                       f"{r.method.setting} {r.method.precision} ({err(r):.1e} m, {r.wall_per_sim_s:.2f} s/sim-s).")
    stiff = [r for r in results.get("d", []) if r.case == "rope_net_stiff" and r.status == "ok"]
    if stiff:
        parts = []
        for tol in (1e-2, 1e-3):
            best = sorted((r for r in stiff if r.error <= tol), key=lambda r: r.wall_per_sim_s)
            explicit = [r for r in best if r.method.integrator != "implicit_euler"]
            if best:
                r = best[0]
                part = (f"within {tol:g} m: {r.method.integrator} {r.method.setting} {r.method.precision} "
                        f"({r.error:.1e} m, {r.wall_per_sim_s:.3f} s/sim-s")
                if r.method.integrator == "implicit_euler" and explicit:
                    e = explicit[0]
                    part += (f"; cheapest explicit: {e.method.integrator} {e.method.setting} {e.method.precision}, "
                             f"{e.wall_per_sim_s:.3f} s/sim-s, {e.wall_per_sim_s / r.wall_per_sim_s:.1f}x dearer")
                parts.append(part + ")")
        if parts:
            out.append("- Accuracy (d), rope_net_stiff (EA 1e9 N), payload z, cheapest run " + "; ".join(parts) + ".")
    if "g" in results:
        g = results["g"]
        out.append(f"- Training (g), MAPPO on the capture environment: **{g['iteration']:,.0f} team env-steps/s "
                   f"including the update**, against {g['env']:,.0f} for the environment alone "
                   f"({g['iteration'] / g['env']:.0%}).")
    if "h" in results:
        h = results["h"]
        rates = lambda size: ", ".join(f"{k.split()[0]} {v:.1f}" for k, v in h.items() if k.endswith(size))
        out.append(f"- Rendering (h), frames/s: 640 × 360: {rates('640x360')}; 1920 × 1080: {rates('1920x1080')}.")
    if "f" in results and "floor" in results["f"]:
        f = results["f"]
        out.append(f"- Profile (f), B = {HEADLINE_BATCH}: library (batch last) {f['library']:,.0f} env-steps/s; "
                   + (f"`jax.vmap` {f['first']:,.0f}; " if "first" in f else "")
                   + (f"hand-written kernel {f['kernel']:,.0f}; " if "kernel" in f else "")
                   + f"gravity-only floor {f['floor']:,.0f}.")
    return out + [""]


# =========================================================================================
# (e) the capture environment
# =========================================================================================


def _env_call(env, params, batch: int, n_steps: int, kind: str = "env", vmap: Callable = batching.vmap,
              compiler_options: dict | None = None):
    """AOT-compiled ``jit(vmap(...))`` over ``batch`` environments reset from distinct keys
    (``vmap``: the library's batch-last ``mysim_jax.core.batching.vmap`` or ``jax.vmap``):
    ``kind="env"``: ``n_steps`` team steps (:meth:`CaptureEnv.step` with the scripted team's
    actions); ``kind="control"``: ``n_steps`` control periods of the physics alone
    (:func:`mysim_jax.sim.step` with the scripted team's setpoint held). Returns a Compiled."""
    from mysim_jax.control.setpoint import setpoint_from_action

    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    _, states = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)

    def run_env(key, state):
        if kind == "env":
            def body(s, k):
                return env.step(k, s, env.scripted_actions(s, params), params)[1], None
            return jax.lax.scan(body, state, jax.random.split(key, n_steps))[0]
        sim_params = env.episode_params(params, state.episode)
        sp = setpoint_from_action(env.scene, sim_params, env.scripted_actions(state, params))

        def period(s, _):
            return step(env.scene, sim_params, s, sp), None
        return jax.lax.scan(period, state.sim, None, length=n_steps)[0]

    if vmap is batching.vmap:      # the library's batched path: cache-sized blocks of environments
        vmap = partial(batching.vmap, chunk=batching.chunk_for(jax.tree.map(lambda x: x[0], states)))
    compiled, compile_s, memory = aot_compile(jax.jit(vmap(run_env)), keys, states,
                                              compiler_options=compiler_options)
    return Compiled(kind, batch, n_steps, lambda: compiled(keys, states), compile_s, memory)


def _env_variant(overrides: list[str]):
    from mysim_jax.tasks.capture import make_env

    return make_env(load_config(CAPTURE_ENV, overrides))


LEVEL_BATCHES = (256, 1024, 4096)
LEVEL_EPISODES = 1000         # scripted episodes per level, the same draws for every level
LEVEL_TARGET = 3000.0         # team steps/s at B = 1024 (10 Hz) the training level should reach
LEVEL_RATIO = 30.0            # ... and this many times `full` in the same run
LEVEL_CALL_S = 1.0            # a timed call repeats a level's team step until it lasts about this long


def _level_outcomes(env, params, n_episodes: int, seed: int = 2024):
    """Success and failure flags of the scripted team's episodes ``0 .. n − 1`` drawn from
    ``seed`` (:func:`mysim_jax.tasks.evaluate.run_episodes`: the same spawns, masses and
    wind at every level, so outcomes pair episode by episode)."""
    from mysim_jax.tasks.evaluate import run_episodes, scripted_policy

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
    """Fidelity levels of the capture scene side by side (10 Hz policy)."""
    from mysim_jax.bench import levels as catch
    from mysim_jax.tasks.capture import make_env
    from mysim_jax.tasks.sweep import paired_difference_interval

    base = load_config(CAPTURE_ENV)
    names = ["full"] + list(base.levels)
    batches = (16, 64) if cfg.quick else LEVEL_BATCHES
    n_eps = 16 if cfg.quick else LEVEL_EPISODES
    n_catch = 4 if cfg.quick else catch.CATCH_EPISODES
    top = 1024 if 1024 in batches else batches[-1]
    calls, envs, rows, outcomes, measures = {}, {}, {}, {}, {}
    for level in tqdm(names, desc="(i) levels: compile", leave=False):
        envs[level] = _env_variant([f"level={level}", "env.policy_rate=10.0"])
        for b in batches:
            calls[level, b] = _env_call(*envs[level], b, 1)
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
        rec_config = load_config(CAPTURE_ENV, [f"level={level}", f"env.policy_rate={catch.CATCH_RATE}"])
        rec_env, rec_params = make_env(rec_config)
        measures[level] = catch.catch_measures(rec_env, rec_params, rec_config.net, jax.random.PRNGKey(catch.CATCH_SEED), n_catch)
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
    train = rows.get("train")
    if train is not None:
        met = train["rate"].get(1024, 0) >= LEVEL_TARGET and train["rate"].get(1024, 0) >= LEVEL_RATIO * rows["full"]["rate"].get(1024, 1e9)
        lines += ["", f"**Target: the training level at ≥ {LEVEL_TARGET:,.0f} team steps/s at B = 1024 and ≥ "
                  f"{LEVEL_RATIO:g}× `full` in the same run: {'MET' if met else 'NOT MET'}**."]
    lines += ["", *catch.catch_table(measures)]
    return lines + ["", contention_note("i", cfg.env_repeats), ""]


EMITTERS = {"older (LLVM) emitters": {"xla_cpu_use_fusion_emitters": False},
            "fusion emitters (XLA's default)": {"xla_cpu_use_fusion_emitters": True}}


def section_j(cfg, results) -> list[str]:
    """XLA's two CPU code generators for fusions, on the same programs side by side."""
    scene, params, state = _throughput_scene()
    rope_b = 64 if cfg.quick else 1024
    rope_k = steps_for_batch(rope_b, cfg.env_steps_per_call)
    train_b, full_b = (16, 16) if cfg.quick else (1024, 256)
    train_env, train_params = _env_variant(["level=train", "env.policy_rate=10.0"])
    full_env, full_params = _env_variant(["env.policy_rate=10.0"])
    programs = {
        f"capture env, level train, B = {train_b} (1 team step at 10 Hz)":
            lambda o: _env_call(train_env, train_params, train_b, 1, compiler_options=o),
        f"capture env, level full, B = {full_b} (1 team step at 10 Hz)":
            lambda o: _env_call(full_env, full_params, full_b, 1, compiler_options=o),
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


def section_e(cfg, results) -> list[str]:
    env, params = _env_variant([])
    scene = env.scene
    rows: list[ThroughputRow] = []
    first_rows: dict[int, ThroughputRow] = {}
    bar = tqdm(total=len(cfg.env_batches), desc="(e) capture env", leave=False)
    for b in cfg.env_batches:
        k = max(1, int(round(32 / b)))          # about 32 team steps per call (one at B >= 64)
        calls = {"env": _env_call(env, params, b, k)}
        if b <= cfg.env_first_max_batch:        # the batch-first path, side by side
            calls["first"] = _env_call(env, params, b, k, vmap=jax.vmap)
        wait_for_quiet(cfg.max_wait_s, "e")
        times = time_round_robin({key: c.call for key, c in calls.items()}, cfg.env_repeats, section="e")
        rows.append(ThroughputRow(f"{b}", b, k, times["env"], calls["env"].compile_s, calls["env"].bytes_per_env()))
        if "first" in calls:
            first_rows[b] = ThroughputRow(f"{b}", b, k, times["first"], calls["first"].compile_s,
                                          calls["first"].bytes_per_env())
        bar.update(1)
    bar.close()
    results["env_rows"] = rows
    results["env_first_rows"] = first_rows

    # where the time goes, at B = 256: the physics alone (control periods), and variants
    # of the scene with one stage removed
    pb = 256 if not cfg.quick else 16
    n = env.control_steps
    variants = {
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
        "no_wind": ("physics without wind (`env.randomize.wind: null`)", ["env.randomize.wind=null"], "control"),
    }
    calls, compiled, substeps = {}, {}, {}
    same = [f"sim.substeps={scene.substeps}"]      # every variant at the scene's sub-step
    for key, (_, overrides, kind) in variants.items():
        e, p = (env, params) if not overrides else _env_variant(overrides + same)
        c = _env_call(e, p, pb, 1 if kind == "env" else n, kind)   # batch-last
        calls[key], compiled[key], substeps[key] = c.call, c, e.scene.substeps
    auto_no_contact = _env_variant(["contact=null"])[0].scene.substeps
    wait_for_quiet(cfg.max_wait_s, "e")
    times = time_round_robin(calls, cfg.env_repeats, section="e")
    t = {k: median(v) for k, v in times.items()}
    results["env_profile"] = t

    per_sub = t["physics"] / (pb * n * substeps["physics"])
    lines = [
        "## (e) Capture environment",
        "",
        f"`configs/capture_env_falling.yaml` (float32, {scene.n_points} point masses, {scene.n_springs} springs, "
        f"4 quadrotors and the target, contact, line drag; {env.control_steps} control periods of "
        f"{scene.dt * 1e3:g} ms per team step at 25 Hz, {scene.substeps} semi-implicit Euler sub-steps each). "
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
    top = rows[-1]
    need = TARGET_POLICY_STEPS * env.control_steps * scene.substeps
    lines += [
        "",
        f"**Target ≥ {TARGET_POLICY_STEPS:,} team steps/s at B = 4096: "
        f"{'MET' if top.env_steps_per_s >= TARGET_POLICY_STEPS else 'NOT MET'}** "
        f"({top.env_steps_per_s:,.1f} at B = {top.batch}, "
        f"{top.env_steps_per_s / TARGET_POLICY_STEPS:.2%} of it).",
        "",
        f"`jax.vmap` rows are timed only up to B = {cfg.env_first_max_batch} (at B = 4096 one batch-first call "
        "takes over two minutes). For B = 4096 the batch-first figure is the previous full run's, at git bb2af88 "
        "on this machine type: 28.3 team steps/s.",
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
    lines += [
        "",
        contention_note("e", cfg.env_repeats),
        "",
        "### Findings",
        "",
        f"- A team step is {env.control_steps} control periods × {scene.substeps} physics sub-steps = "
        f"{env.control_steps * scene.substeps} sub-steps of the whole multibody system. "
        f"{TARGET_POLICY_STEPS:,} team steps/s would need {need:,.0f} sub-steps/s; the physics alone runs "
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


# =========================================================================================
# main
# =========================================================================================


_SECTION_HEAD = re.compile(r"^## \(([a-z])\) ")


def _split_sections(lines: list[str]) -> tuple[list[str], list[str], dict[str, list[str]]]:
    """``(header, summary, {letter: lines})`` of a BENCHMARKS.md text."""
    header, summary, sections, current = [], [], {}, None
    for ln in lines:
        m = _SECTION_HEAD.match(ln)
        if m:
            current = m.group(1)
            sections[current] = []
        elif ln.startswith("## Summary"):
            current = "summary"
            continue
        if current is None:
            header.append(ln)
        elif current == "summary":
            summary.append(ln)
        else:
            sections[current].append(ln)
    return header, summary, sections


def splice_sections(old: list[str], new: list[str], rerun: list[str]) -> list[str]:
    """The new run's header, summary and sections ``rerun``, with every other section of
    the old text (and the old summary lines that name it, ``(x)``) kept as it was."""
    old_header, old_summary, old_sections = _split_sections(old)
    header, summary, sections = _split_sections(new)
    kept = [s for s in SECTIONS if s in old_sections and s not in rerun]
    if not kept:
        return new
    def field(name):
        line = next((ln for ln in old_header if ln.startswith(f"| {name} |")), f"| {name} | unknown |")
        return line.split("|")[2].strip()

    note = (f"Sections {', '.join(rerun)} are from this run; sections {', '.join(kept)} (and their summary "
            f"lines) are kept from the earlier file ({field('date')}, {field('code')}, on {field('machine')}), "
            f"spliced by `scripts/bench.py --only {','.join(rerun)} --update`.")
    # that file may itself have been spliced: its note says where its kept sections came from
    earlier = next((ln for ln in old_header if ln.startswith("Sections ") and " are from this run" in ln), None)
    if earlier is not None:
        note += " That file's own note: " + earlier
    # every summary line names its section(s), "(a)" ...; keep those of sections not rerun
    kept_summary = [ln for ln in old_summary
                    if ln.startswith("- ") and any(f"({s})" in ln for s in kept)
                    and not any(f"({s})" in ln for s in rerun)]
    summary = [ln for ln in summary if ln.strip()] + kept_summary
    out = header + [note, "", "## Summary", ""] + summary + [""]
    for s in SECTIONS:
        block = sections.get(s) if s in sections else old_sections.get(s) if s in kept else None
        if block:
            # the last section of a file lost its trailing blank line when it was written
            out += block + ([""] if block[-1].strip() else [])
    return out


# =========================================================================================
# (g) training throughput
# =========================================================================================


def section_g(cfg, results) -> list[str]:
    """MAPPO: one training iteration against the rollout alone and the environment alone
    (mysim_jax/bench/training.py), on the environment and sizes of the default training file."""
    from mysim_jax.bench.training import measure
    from mysim_jax.mappo.run import load_run_config, make_environment
    from mysim_jax.mappo.trainer import Trainer

    overrides = ["algo.num_envs=16", "algo.num_steps=4", "algo.num_minibatches=4"] if cfg.quick else []
    prepared = load_run_config(str(TRAIN_CAPTURE), overrides)
    env, env_params = make_environment(prepared)
    algo = prepared.config.algo
    trainer = Trainer(algo, env, env_params)
    wait_for_quiet(cfg.max_wait_s, "g")
    m = measure(trainer, jax.random.PRNGKey(0), repeats=2 if cfg.quick else 3)
    rate = {k: m.steps_per_s(k) for k in m.times}
    results["g"] = rate
    update_s = median(m.times["iteration"]) - median(m.times["rollout"])
    lines = [
        "## (g) Training throughput (MAPPO)",
        "",
        f"`{TRAIN_CAPTURE.relative_to(ROOT)}`" + (f" with `{' '.join(overrides)}`" if overrides else "")
        + f": {algo.num_envs} environments × {algo.num_steps} team steps per iteration, update of "
        f"{algo.update_epochs} epochs × {algo.num_minibatches} minibatches, networks {list(algo.hidden)} "
        f"(mysim_jax/bench/training.py). Each call AOT-compiled; timed round-robin, median of "
        f"{len(m.times['iteration'])} rounds. env-steps/s = team (policy) steps of all environments per second; "
        f"a team step is {env.control_steps} control periods of {env.scene.substeps} physics sub-steps.",
        "",
        "| call | what | s per call | team env-steps/s | compile [s] |",
        "|---|---|---:|---:|---:|",
        f"| iteration | rollout + GAE + update (`Trainer.iteration`) | {median(m.times['iteration']):.2f} | "
        f"{rate['iteration']:,.0f} | {m.compile_s['iteration']:.1f} |",
        f"| rollout | policy + critic + environment steps, no update | {median(m.times['rollout']):.2f} | "
        f"{rate['rollout']:,.0f} | {m.compile_s['rollout']:.1f} |",
        f"| env | environment steps alone (zero actions) | {median(m.times['env']):.2f} | {rate['env']:,.0f} | "
        f"{m.compile_s['env']:.1f} |",
        "",
        f"Training runs at **{rate['iteration'] / rate['env']:.0%}** of the environment's own steps/s; the update "
        f"takes {update_s:.2f} s of an iteration ({update_s / median(m.times['iteration']):.0%}). "
        + (f"The networks add {median(m.times['rollout']) - median(m.times['env']):.2f} s to the rollout."
           if median(m.times["rollout"]) >= median(m.times["env"]) else
           f"The rollout (policy, critic and environment) took {median(m.times['env']) - median(m.times['rollout']):.2f} s "
           "less than the environment alone with zero actions: the networks cost less than the difference the "
           "actions make to the environment's own cost (contact and line work depend on where the team flies)."),
        "",
        contention_note("g", 2 if cfg.quick else 3),
        "",
    ]
    return lines + training_runs_lines()


TRAIN_RUNS = ROOT / "docs" / "train"


def _scripted_outcomes(runs) -> dict:
    """The scripted team's outcomes on the evaluation episodes of ``runs`` that compared
    against it (``eval/comparison_episodes.csv``), keyed by ``(scene, evaluation seed)``:
    episode i of a seed is the same episode in every evaluation of that environment, so a
    run evaluated on fewer episodes pairs with the first of these."""
    import csv
    import json

    found = {}
    for run in runs:
        table = run / "eval" / "comparison_episodes.csv"
        base = json.loads((run / "summary.json").read_text()).get("baseline")
        if base is None or not table.is_file():
            continue
        with table.open() as f:
            rows = list(csv.DictReader(f))
        found[(_run_scene(run), base["seed"])] = np.array([r["outcome_scripted"] == "success" for r in rows])
    return found


def _run_scene(run):
    """The name of the scene a kept run was evaluated on (``scene_eval.yaml``, else the
    ``scene.yaml`` it trained on)."""
    import yaml

    scene = next((run / f for f in ("scene_eval.yaml", "scene.yaml") if (run / f).is_file()), None)
    return yaml.safe_load(scene.read_text()).get("name") if scene is not None else None


def _run_settings(run):
    """``(train.yaml as a dict, seed, init, eval seed)`` of a kept run folder."""
    import yaml

    cfg = yaml.safe_load((run / "train.yaml").read_text())
    run_cfg, algo = cfg.get("run", {}), cfg.get("algo", {})
    return cfg, run_cfg.get("seed", 0), algo.get("init", "none"), run_cfg.get("eval_seed")


def training_runs_lines() -> list[str]:
    """The training runs kept in docs/train/<run>/ (copied from scripts/train.py run folders:
    summary.json, train.yaml, metrics.csv, curves.png, eval/): one table row each with the
    paired difference to the scripted team on the same episodes where it was measured, the
    spread over seeds of runs that differ only in ``run.seed``, every run's curves side
    by side (``docs/train/runs.png``) and each run's own."""
    import json

    from mysim_jax.mappo.run import plot_runs, read_metrics
    from mysim_jax.tasks.sweep import paired_difference_interval

    runs = sorted(p for p in TRAIN_RUNS.glob("*") if (p / "metrics.csv").is_file() and (p / "train.yaml").is_file())
    if not runs:
        return []
    scripted = _scripted_outcomes([run for run in runs if (run / "summary.json").is_file()])
    lines = [
        "### Training runs",
        "",
        "Each run is `python scripts/train.py configs/<file>.yaml` (with the `--set` overrides its `train.yaml` "
        "records) on this machine, its folder's `summary.json`, `train.yaml`, `metrics.csv`, `curves.png` and "
        "`eval/` kept in `docs/train/<run>/`. Training success is the share of episodes ended in the iteration "
        "that succeeded (exploration noise on); the selection curve is the deterministic policy on the fixed "
        "selection episodes; evaluation is the saved (selected) policy on `run.eval_episodes` fresh episodes "
        "(`eval_seed`), as `scripts/evaluate.py` reports it. *vs scripted* is the paired difference to the "
        "scripted team on the same evaluation episodes (the run's own `eval/comparison.json`, or the scripted "
        "outcomes another run measured on the same episodes), with its 95 % interval.",
        "",
        "| run | init | seed | team steps | training [min] | env-steps/s (update incl.) | evaluation [min] | "
        "success (95 % interval) | vs scripted [points] | how the others ended |",
        "|---|---|---:|---:|---:|---:|---:|---|---|---|",
    ]
    groups: dict[str, list[tuple[str, float]]] = {}
    for run in runs:
        cfg, seed, init, eval_seed = _run_settings(run)
        if not (run / "summary.json").is_file():
            # stopped before its evaluation: what metrics.csv says
            rows = read_metrics(run)
            last = rows[-1]
            selected = [r for r in rows if r.get("select_success") not in ("", None)]
            sel = ", ".join(f"{float(r['select_success']):.0%} at {r['iteration']}" for r in selected)
            lines.append(f"| `{run.name}` | {init} | {seed} | {int(last['env_steps']):,} | "
                         f"{float(last['wall_s']) / 60:.1f} | — | — | not evaluated (stopped after training); "
                         f"selection success {sel or '—'} | — | — |")
            continue
        s = json.loads((run / "summary.json").read_text())
        ev = s.get("evaluation", {})
        fails = ", ".join(f"{v['count']} {k}" for k, v in ev.get("failures", {}).items() if v["count"])
        if ev.get("timeout", {}).get("count"):
            fails = (fails + ", " if fails else "") + f"{ev['timeout']['count']} timeouts"
        succ = ev.get("success")
        succ_text = (f"**{succ['rate']:.1%}** ({succ['interval95'][0]:.1%}–{succ['interval95'][1]:.1%}) of "
                     f"{ev['episodes']}" if succ else "—")
        versus = "—"
        if "baseline" in s:
            d = s["baseline"]["difference"]
            versus = f"{100 * d['estimate']:+.1f} ({100 * d['interval95'][0]:+.1f} to {100 * d['interval95'][1]:+.1f})"
        elif succ and (run / "eval" / "episodes.csv").is_file():
            import csv

            with (run / "eval" / "episodes.csv").open() as f:
                mine = np.array([r["success"] == "1" for r in csv.DictReader(f)])
            base = scripted.get((_run_scene(run), eval_seed))
            if base is not None and len(base) >= len(mine):
                d, lo, hi = paired_difference_interval(mine, base[:len(mine)])
                versus = f"{100 * d:+.1f} ({100 * lo:+.1f} to {100 * hi:+.1f})"
        stopped = " (time limit)" if s.get("stopped_by_time_limit") else ""
        rate = s.get("env_steps_per_s_with_update")
        rate_text = "—" if rate is None else f"{rate:,.0f}"
        lines.append(f"| `{run.name}` | {init} | {seed} | {s['env_steps']:,}{stopped} | "
                     f"{s['training_wall_s_total'] / 60:.1f} | {rate_text} | "
                     f"{s.get('evaluation_wall_s', float('nan')) / 60:.1f} | {succ_text} | {versus} | {fails or '—'} |")
        if succ:
            cfg.get("run", {}).pop("seed", None)
            groups.setdefault(json.dumps(cfg, sort_keys=True), []).append((run.name, succ["rate"]))
    lines.append("")
    for members in groups.values():
        if len(members) > 1:
            rates = np.array([r for _, r in members])
            lines.append(f"**Over seeds** ({', '.join(f'`{n}`' for n, _ in members)}: the same file and settings, "
                         f"`run.seed` alone differs): evaluation success mean **{rates.mean():.1%}**, "
                         f"range {rates.min():.1%}–{rates.max():.1%}, standard deviation {rates.std(ddof=1):.1%} "
                         f"over {len(rates)} seeds.")
            lines.append("")
    figure = plot_runs({run.name: read_metrics(run) for run in runs}, TRAIN_RUNS / "runs.png",
                       "kept training runs, side by side")
    if figure is not None:
        lines += ["![kept training runs side by side](docs/train/runs.png)", ""]
    for run in runs:
        if (run / "curves.png").is_file():
            lines += [f"![{run.name}](docs/train/{run.name}/curves.png)", ""]
    notes = [run / "NOTE.md" for run in runs if (run / "NOTE.md").is_file()]
    for note in notes:
        lines += [f"**{note.parent.name}**: " + note.read_text().strip(), ""]
    return lines


def refresh_training_runs(path: Path) -> int:
    """Replace the training-runs list of section (g) in ``path`` (from ``### Training runs``
    to the section's timing line) with :func:`training_runs_lines`, and say so under the
    section's heading. Measures nothing: the runs are what ``docs/train/`` holds."""
    lines = path.read_text().splitlines()
    try:
        head = lines.index("## (g) Training throughput (MAPPO)")
        start = lines.index("### Training runs", head)
    except ValueError:
        print(f"{path}: no section (g) with a training-runs list to refresh", file=sys.stderr)
        return 2
    end = next((i for i in range(start, len(lines)) if lines[i].startswith("*(section g")
                or (i > start and lines[i].startswith("## "))), len(lines))
    when = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    note = (f"*The training-runs list below was refreshed from `docs/train/` on {when} "
            "(`scripts/bench.py --runs-only`); the throughput table is from the run named before it.*")
    body = lines[head + 1:start]
    body = [ln for ln in body if not ln.startswith("*The training-runs list below was refreshed")]
    new = lines[:head + 1] + ["", note] + [ln for ln in body if ln or True] + training_runs_lines() + lines[end:]
    # collapse the blank lines the splice may double
    out = [ln for i, ln in enumerate(new) if ln or i == 0 or new[i - 1]]
    path.write_text("\n".join(out).rstrip() + "\n")
    print(f"refreshed the training runs of section (g) in {path}")
    return 0


def section_h(cfg, results) -> list[str]:
    """Rendering speed (mysim_jax/bench/render.py): a capture run seen by an onboard and an
    observer camera, and ground only, at 1920 x 1080 and 640 x 360."""
    import cv2

    from mysim_jax.bench.render import capture_run, example_image, measure

    t0 = time.perf_counter()
    config, columns = capture_run(t_end=1.6)
    sim_s = time.perf_counter() - t0
    wait_for_quiet(cfg.max_wait_s, "h")
    rows, frames = measure(config, columns, repeats=3 if cfg.quick else 7, section="h")
    results["h"] = {f"{r.view} {r.width}x{r.height}": r.fps for r in rows}
    picture = cfg.plots_dir / "render_example.png"
    cv2.imwrite(str(picture), cv2.cvtColor(example_image(frames), cv2.COLOR_RGB2BGR))
    onboard = frames["onboard"]
    lines = [
        "## (h) Rendering (camera images)",
        "",
        f"`Renderer.render` (mysim_jax/perception/render.py) on `{CAPTURE_FALLING.relative_to(ROOT)}` with a "
        f"camera `cam0` on uav0 (yawed to the net, pitched 35° down), simulated 1.6 s ({sim_s:.0f} s, compile "
        f"included). Views at t = {onboard.t:.2f} s (the row where cam0 sees the most of the target, all of it in the image): "
        "**onboard** (cam0), **observer** (a free camera 8 m from the net: four UAVs, net, tethers, target) and "
        "**ground** (the observer turned away: ground and sky only). One call = inputs checked, ground, objects, "
        f"compositing, target boxes; median of the counted rounds, timed round-robin "
        f"(mysim_jax/bench/render.py). {contention_note('h', 3 if cfg.quick else 7)}",
        "",
        "| view | image | ms per frame | frames/s | object pixels | target pixels | spread |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r.view} | {r.width} × {r.height} | {1e3 * median(r.times):.0f} | {r.fps:.1f} | "
                     f"{r.object_px:,} | {r.target_px:,} | {spread(r.times)} |")
    small = [r for r in rows if (r.width, r.height) == (640, 360)]
    slowest = min(small, key=lambda r: r.fps)
    lines += ["", f"A 30 s flight at 20 Hz (600 frames) at 640 × 360 takes ~{600 / slowest.fps / 60:.1f} min "
              f"at the slowest view's rate ({slowest.view}).", "",
              f"![rendered frames](docs/bench/{picture.name})", ""]
    return lines


@dataclass
class BenchConfig:
    quick: bool
    sections: tuple[str, ...]
    out: Path
    plots_dir: Path
    repeats: int
    env_steps_per_call: float
    accuracy_repeats: int
    accuracy_time_budget: float
    max_wait_s: float = 60.0
    cases: tuple[str, ...] = ()       # (d): only these accuracy cases (empty: all)
    capture_steps: int = 2            # (a): env steps per call of the capture-scene rollout
    env_batches: tuple[int, ...] = (1, 16, 64, 256, 1024, 4096)   # (e)
    env_repeats: int = 3              # (e): timed calls per row (a row at B = 4096 takes ~1 min a call)
    env_first_max_batch: int = 1024   # (e): largest batch also timed with jax.vmap (batch first)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smoke test: fewer repeats, points and variants")
    parser.add_argument("--only", default=",".join(SECTIONS),
                        help=f"comma-separated sections to run, from {','.join(SECTIONS)} (default: all)")
    parser.add_argument("--out", default=None, help="markdown file to write (default BENCHMARKS.md for a full run, "
                        "docs/bench/partial/BENCHMARKS.md with --quick/--only)")
    parser.add_argument("--update", action="store_true", help="with --only: replace those sections in the "
                        "existing output file (default BENCHMARKS.md) and keep the others from its earlier run")
    parser.add_argument("--cases", default="", help="section (d) only: comma-separated accuracy cases to run "
                        "(rope_net, rope_net_slack, collision_light, collision_heavy, capture_falling; default: all)")
    parser.add_argument("--runs-only", action="store_true", help="refresh only the training-runs list of section "
                        "(g) in BENCHMARKS.md from docs/train/ (no measuring; the throughput table is kept)")
    args = parser.parse_args(argv)
    if args.runs_only:
        return refresh_training_runs(Path(args.out) if args.out else ROOT / "BENCHMARKS.md")
    sections = tuple(s.strip().lower() for s in args.only.split(",") if s.strip())
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        parser.error(f"--only: unknown section(s) {unknown}; choose from {','.join(SECTIONS)}")
    cases = tuple(c.strip() for c in args.cases.split(",") if c.strip())
    known_cases = [c.name for c in accuracy_cases(False)]
    if any(c not in known_cases for c in cases):
        parser.error(f"--cases: unknown case(s) {[c for c in cases if c not in known_cases]}; choose from "
                     f"{','.join(known_cases)}")
    partial = args.quick or set(sections) != set(SECTIONS) or bool(cases)
    if args.update and (args.quick or cases):
        parser.error("--update splices full-size sections into BENCHMARKS.md: not with --quick or --cases")
    if args.update and args.out is None:
        out = ROOT / "BENCHMARKS.md"
    elif args.out is not None:
        out = Path(args.out)
    elif partial:
        out = ROOT / "docs" / "bench" / "partial" / "BENCHMARKS.md"
    else:
        out = ROOT / "BENCHMARKS.md"
    # a partial run (--quick, --only, --cases) never overwrites the plots BENCHMARKS.md links to
    plots_dir = ROOT / "docs" / "bench" / ("partial" if partial and not args.update else "")
    plots_dir.mkdir(parents=True, exist_ok=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    cfg = BenchConfig(
        quick=args.quick, sections=sections, out=out, plots_dir=plots_dir,
        repeats=3 if args.quick else 7,
        env_steps_per_call=2.5e5 if args.quick else 1.0e6,
        accuracy_repeats=1 if args.quick else 3,
        accuracy_time_budget=5.0 if args.quick else 10.0,
        max_wait_s=15.0 if args.quick else 60.0,
        cases=cases,
        capture_steps=1 if args.quick else 2,
        env_batches=(1, 16, 64) if args.quick else (1, 16, 64, 256, 1024, 4096),
        env_repeats=2 if args.quick else 3,
        env_first_max_batch=16 if args.quick else 1024,
    )

    started = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    load_start = load_average()
    t_start = time.perf_counter()
    results: dict[str, Any] = {}
    body: list[str] = []
    runners = {"a": section_a, "b": section_b, "c": section_c, "d": section_d, "e": section_e, "f": section_f,
               "g": section_g, "h": section_h, "i": section_i, "j": section_j}
    order = [s for s in SECTIONS if s in sections]
    for s in tqdm(order, desc="bench sections", unit="section"):
        t0 = time.perf_counter()
        body += runners[s](cfg, results)
        body.append(f"*(section {s}: {time.perf_counter() - t0:.0f} s)*")
        body.append("")
    plot_throughput(results, plots_dir)
    wall = time.perf_counter() - t_start

    text = header_lines(args, started, load_start, load_average(), wall) + summary_lines(results) + body
    if args.update and out.exists():
        text = splice_sections(out.read_text().splitlines(), text, order)
    # plot links are relative to the repository root; fix them up for other output folders
    rel = os.path.relpath(plots_dir, out.parent)
    text = [ln.replace("](docs/bench/", f"]({rel}/" if rel != "docs/bench" else "](docs/bench/") for ln in text]
    out.write_text("\n".join(text).rstrip() + "\n")
    print(f"wrote {out} ({wall / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
