"""The benchmark's timing harness: repeats, round-robin timing, CPU contention, AOT compiles.

``scripts/bench.py`` (and anything else that times the library) uses these:

* :func:`time_round_robin` times several variants one call of each in turn, so that a
  busy machine slows all of them alike; rounds during which other processes used
  ``QUIET_SHARE`` or more of the CPU (:class:`CpuMonitor`, from /proc) are discarded and
  redone, and :func:`contention_note` says how busy the machine was.
* :func:`aot_compile` / :func:`compile_batched` compile ahead of time (``.lower().compile()``)
  so compilation is timed separately and never inside a timed call.
* medians and spreads of repeats, and the machine facts a report's header needs.
"""

from __future__ import annotations

import os
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.core import batching
from mysim_jax.sim import step

ROOT = Path(__file__).resolve().parents[2]


def median(xs) -> float:
    return float(np.median(np.asarray(xs, dtype=float)))


def spread(xs) -> str:
    """Relative spread of repeats, (max - min) / median, as a percentage string."""
    xs = np.asarray(xs, dtype=float)
    return f"{100.0 * (xs.max() - xs.min()) / np.median(xs):.0f}%"


class CpuMonitor:
    """CPU time taken by *other* processes, from /proc/stat and /proc/self/stat (Linux).

    The benchmark machine may be shared (e.g. someone running pytest); their load slows
    every timing here. ``share(a, b)`` is the fraction of the whole machine's CPU capacity
    that other processes used between two samples.
    """

    def __init__(self):
        self.available = Path("/proc/stat").exists() and Path("/proc/self/stat").exists()

    def sample(self):
        if not self.available:
            return None
        with open("/proc/stat") as f:
            vals = [int(v) for v in f.readline().split()[1:9]]
        with open("/proc/self/stat") as f:
            text = f.read()
        rest = text[text.rfind(")") + 2:].split()
        own = int(rest[11]) + int(rest[12])          # utime + stime of all our threads
        return sum(vals), vals[3] + vals[4], own     # total, idle + iowait, own (clock ticks)

    @staticmethod
    def share(a, b) -> float:
        if a is None or b is None or b[0] <= a[0]:
            return float("nan")
        total = b[0] - a[0]
        busy = total - (b[1] - a[1])
        return max(0.0, busy - (b[2] - a[2])) / total


CPU = CpuMonitor()
QUIET_SHARE = 0.10          # a timing round counts as quiet if others used < 10% of the machine
_CONTENTION: dict[str, list[float]] = {}   # section -> others' share per timed round


def wait_for_quiet(max_wait_s: float, label: str) -> float:
    """Wait (up to ``max_wait_s``) until other processes leave the machine idle for 2 s."""
    if not CPU.available:
        return 0.0
    t0 = time.perf_counter()
    quiet = 0
    while time.perf_counter() - t0 < max_wait_s:
        a = CPU.sample()
        time.sleep(0.5)
        if CPU.share(a, CPU.sample()) < QUIET_SHARE:
            quiet += 1
            if quiet >= 2:
                break
        else:
            quiet = 0
    waited = time.perf_counter() - t0
    _CONTENTION.setdefault(label + ":waited", []).append(waited)
    return waited


def time_round_robin(calls: dict[str, Callable[[], Any]], repeats: int, bar=None,
                     section: str = "", max_rounds: int | None = None) -> dict[str, list[float]]:
    """Warm each call up once, then time rounds of one call of each, in turn.

    A round during which other processes took more than ``QUIET_SHARE`` of the machine
    is recorded but not counted; rounds continue until ``repeats`` quiet rounds or
    ``max_rounds`` rounds (default 2 × repeats + 1). Returns the times of the quiet rounds
    if there are at least ``min_quiet(repeats)`` of them, else of all rounds (the section's
    contention note then says so).
    """
    for fn in calls.values():
        jax.block_until_ready(fn())
        if bar is not None:
            bar.update(1)
    max_rounds = max_rounds or 2 * repeats + 1
    all_times: dict[str, list[float]] = {k: [] for k in calls}
    quiet_times: dict[str, list[float]] = {k: [] for k in calls}
    shares = []
    for _ in range(max_rounds):
        start = CPU.sample()
        round_times = {}
        for key, fn in calls.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            round_times[key] = time.perf_counter() - t0
        share = CPU.share(start, CPU.sample())
        shares.append(share)
        for key, t in round_times.items():
            all_times[key].append(t)
            if not share >= QUIET_SHARE:          # nan (no /proc) counts as quiet
                quiet_times[key].append(t)
        n_quiet = len(next(iter(quiet_times.values())))
        if bar is not None and (n_quiet <= repeats):
            bar.update(len(calls) if not share >= QUIET_SHARE else 0)
        if n_quiet >= repeats:
            break
    _CONTENTION.setdefault(section, []).extend(shares)
    n_quiet = len(next(iter(quiet_times.values())))
    return quiet_times if n_quiet >= min_quiet(repeats) else all_times


def min_quiet(repeats: int) -> int:
    """Fewest quiet rounds whose median is used instead of the median of all rounds."""
    return min(repeats, max(3, (repeats + 1) // 2))


def contention_note(section: str, repeats: int) -> str:
    """One sentence on how busy the machine was during a section's timed rounds."""
    shares = [x for x in _CONTENTION.get(section, []) if np.isfinite(x)]
    waited = sum(_CONTENTION.get(section + ":waited", []))
    if not shares:
        return "(CPU contention not measured: no /proc on this system.)"
    quiet = sum(x < QUIET_SHARE for x in shares)
    if quiet >= min_quiet(repeats):
        used = f"only the {quiet} quiet rounds are counted"
    else:
        used = (f"**fewer than {min_quiet(repeats)} rounds were quiet, so all rounds are counted and the "
                "numbers are depressed by the other load**")
    return (f"Machine contention: other processes used a median {100 * median(shares):.0f}% (max "
            f"{100 * max(shares):.0f}%) of the machine's CPU during the {len(shares)} timed rounds; {quiet} were "
            f"quiet (< {100 * QUIET_SHARE:.0f}%) and {used}"
            + (f"; the section first waited {waited:.0f} s for a quiet machine." if waited > 2.5 else ".")
            )


def broadcast(tree, batch: int):
    """Stack ``batch`` identical copies of a single-env pytree (leading axis)."""
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), tree)


@dataclass
class Compiled:
    """An ahead-of-time compiled batched rollout, ready to be timed."""

    label: str
    batch: int
    n_steps: int
    call: Callable[[], Any]
    compile_s: float
    memory: Any                   # jax CompiledMemoryStats (or None)
    hlo_text: str = ""

    def bytes_per_env(self) -> float:
        m = self.memory
        if m is None:
            return float("nan")
        total = m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes - m.alias_size_in_bytes
        return total / self.batch


@dataclass
class ThroughputRow:
    """One timed row of a throughput table: ``batch`` environments, ``n_steps`` steps per
    call, the counted calls' ``times`` [s], compile seconds and memory per environment."""

    label: str
    batch: int
    n_steps: int
    times: list[float]
    compile_s: float
    bytes_per_env: float

    @property
    def env_steps_per_s(self) -> float:
        return self.batch * self.n_steps / median(self.times)


def compile_batched(label: str, run_env: Callable, params, state, batch: int, n_steps: int,
                    batch_params: bool = False, chunk: int | None = None, keep_hlo: bool = False,
                    vmap: Callable = batching.vmap, compiler_options: dict | None = None) -> Compiled:
    """``jit(vmap(run_env))`` over a batch of ``batch`` copies of ``state``; ``vmap`` is
    the library's ``mysim_jax.core.batching.vmap`` (batch axis last, the default) or
    ``jax.vmap`` (batch axis first).

    ``run_env(params, state) -> state`` runs one env for ``n_steps`` steps. Params are
    shared by all envs (``in_axes=None``) unless ``batch_params``. With ``chunk``, the batch
    is split into ``batch // chunk`` chunks run one after another by ``lax.map`` (each a
    vmap of ``chunk`` envs), so one chunk's state stays in cache for all its steps.
    """
    in_axes = (0 if batch_params else None, 0)
    vmapped = vmap(run_env, in_axes=in_axes)
    if chunk is None:
        fn = jax.jit(vmapped)
    else:
        n_chunks = batch // chunk

        def chunked(p, s):
            split = jax.tree.map(lambda x: x.reshape((n_chunks, chunk) + x.shape[1:]), s)
            if batch_params:
                ps = jax.tree.map(lambda x: x.reshape((n_chunks, chunk) + x.shape[1:]), p)
                out = jax.lax.map(lambda ab: vmapped(ab[0], ab[1]), (ps, split))
            else:
                out = jax.lax.map(lambda c: vmapped(p, c), split)
            return jax.tree.map(lambda x: x.reshape((batch,) + x.shape[2:]), out)

        fn = jax.jit(chunked)
    pb = broadcast(params, batch) if batch_params else params
    sb = broadcast(state, batch)
    compiled, compile_s, memory = aot_compile(fn, pb, sb, compiler_options=compiler_options)
    return Compiled(label, batch, n_steps, lambda: compiled(pb, sb), compile_s, memory,
                    compiled.as_text() if keep_hlo else "")


def aot_compile(fn, *args, compiler_options: dict | None = None):
    """``(compiled, compile seconds, memory stats or None)`` of a jitted ``fn`` on ``args``;
    ``compiler_options`` (XLA debug options by name) override ``XLA_FLAGS`` for this
    program only."""
    jax.block_until_ready(args)
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile(compiler_options=compiler_options)
    compile_s = time.perf_counter() - t0
    try:
        memory = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - not every backend reports it
        memory = None
    return compiled, compile_s, memory


def library_run_env(scene, n_steps: int) -> Callable:
    """One env, ``n_steps`` library steps in a ``lax.scan`` (the state is the carry)."""
    def run_env(params, state):
        def body(s, _):
            return step(scene, params, s), None
        return jax.lax.scan(body, state, None, length=n_steps)[0]
    return run_env


def steps_for_batch(batch: int, env_steps_per_call: float) -> int:
    """Scan length K so that one call does about ``env_steps_per_call`` env-steps."""
    k = int(round(env_steps_per_call / batch / 50.0)) * 50
    return int(min(20_000, max(100, k)))


def git_revision() -> str:
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                             text=True, check=True).stdout.strip()
        # the benchmark's own outputs (this file, its plots, section g's plot of the kept
        # training runs) do not count as changed code
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                                ":(exclude)BENCHMARKS.md", ":(exclude)docs/bench",
                                ":(exclude)docs/train/runs.png"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
        return rev + (" (with uncommitted changes)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def load_average() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def record_contention(section: str, shares) -> None:
    """Add others' CPU shares of timed rounds (or runs) to ``section``'s record."""
    _CONTENTION.setdefault(section, []).extend(shares)


def contention_shares(section: str) -> list[float]:
    """Others' CPU share of every timed round recorded for ``section`` (finite values)."""
    return [x for x in _CONTENTION.get(section, []) if np.isfinite(x)]
