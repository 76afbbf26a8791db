"""Accuracy against cost (BENCHMARKS.md (d)): every method of every scene against a reference.

For each :class:`~mysim_jax.bench.accuracy_cases.AccuracyCase`, :func:`reference_solution`
runs the tight reference setting (float64, cached per case), :func:`run_method` runs each
method on the same output grid, AOT-compiled, and times it while the machine is quiet, and
:func:`section_d` writes the table, a log-log plot of error against wall time per simulated
second, the highlights (cheapest run within a tolerance; for the contact scenes how far the
fast fixed-step paths get before they drift), the observed order of the fixed-step methods
(:func:`observed_orders`) and the adaptive solvers' step statistics.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
from tqdm.auto import tqdm

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mysim_jax.bench.accuracy_cases import AccuracyCase, AccuracyRow, Method, accuracy_cases  # noqa: E402
from mysim_jax.bench.report import ROOT  # noqa: E402
from mysim_jax.bench.timing import CPU, QUIET_SHARE, contention_shares, median, record_contention  # noqa: E402
from mysim_jax.build import build  # noqa: E402
from mysim_jax.config.scene import ConfigError, load_config  # noqa: E402
from mysim_jax.dynamics.integrators import FIXED_STEP  # noqa: E402
from mysim_jax.driver import output_times, steps_per_output  # noqa: E402
from mysim_jax.sim import has_step_updates, rollout, solve_adaptive  # noqa: E402


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
    return scene, compile_run(scene, params, state, config.run_settings(), policy)


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


def compile_run(scene, params, state, run_settings, policy=None) -> _Run:
    """AOT-compile the whole run of a scene to ``t_end`` on its output grid (one env).

    Stepped (fixed-step integrators, and every scene with quadrotors or effects, whose
    controller and effect updates act once per env step ``dt``): one ``rollout`` scan saving
    every ``output_dt``, asking ``policy`` (if given) for the control of every step; an
    adaptive integrator then solves each env step with diffrax. Otherwise adaptive: the
    library's ``solve_adaptive`` over the whole run, saving at the grid. These are the
    computations ``mysim_jax.driver.simulate`` does, minus its
    host-side chunking and the acceleration pass.
    """
    times = output_times(run_settings)
    if scene.integrator in FIXED_STEP or has_step_updates(scene):
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
    """(d) Accuracy against cost: every case of :func:`accuracy_cases` (those named in
    ``cfg.cases`` if any) against its reference, its table, plot and findings."""
    lines = ["## (d) Accuracy against cost", ""]
    all_rows = []
    for case in accuracy_cases(cfg.quick):
        if cfg.cases and case.name not in cfg.cases:
            continue
        ref_wall, ref_qs, rows = _run_case(cfg, case)
        all_rows += rows
        plot = plot_accuracy(case, rows, cfg.plots_dir)
        lines += _case_intro(cfg, case, ref_wall, ref_qs, results) + _case_table(case, rows)
        lines += ["", f"![accuracy {case.name}](docs/bench/{plot.name})", ""]
        lines += _case_findings(case, rows, results) + _adaptive_table(case)
        lines += [accuracy_contention_note(), ""]
    if not cfg.quick and not any(r.method.integrator == "kvaerno5" for r in all_rows):
        lines += ["kvaerno5 was not run.", ""]
    results["d"] = all_rows
    return lines


def _run_case(cfg, case: AccuracyCase):
    """The case's reference and every one of its methods: ``(reference wall time [s], the
    reference's quantities (the case's and its extras'), rows)``."""
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
    return ref_wall, ref_qs, rows


def _case_intro(cfg, case: AccuracyCase, ref_wall: float, ref_qs, results) -> list[str]:
    """A case's heading, how error and cost are measured, its notes, and the reference's own
    error (its distance to ``case.reference_check``, when set)."""
    what = case.quantity_label.split(" [")[0]
    measure = (f"the 3-D distance |{what} − reference| (the largest over the points)" if case.vector
               else f"|{what} − reference|")
    lines = [
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
    return lines


def _case_table(case: AccuracyCase, rows: list[AccuracyRow]) -> list[str]:
    """A case's table: one row per method (with the drift column when the case has a
    ``drift_tolerance``)."""
    lines = []
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
    return lines


def _case_findings(case: AccuracyCase, rows: list[AccuracyRow], results) -> list[str]:
    """A case's highlights (its own, or the contact or rope-net ones) and observed orders."""
    tol = case.drift_tolerance
    lines = []
    if case.highlights is not None:
        lines += case.highlights(case, rows)
    else:
        lines += accuracy_highlights(rows) if tol is None else contact_highlights(case, rows)
    if case.order_note:
        orders = observed_orders(rows)
        results.setdefault("orders", {})[case.name] = orders
        lines += order_lines(case, orders)
    return lines


def _adaptive_table(case: AccuracyCase) -> list[str]:
    """Accepted and rejected steps of the case's adaptive methods over the first 0.25 s."""
    lines = []
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
    return lines


def contact_highlights(case: AccuracyCase, rows: list[AccuracyRow]) -> list[str]:
    """The contact scenes: which path is fastest for equal accuracy, and how far the fast fixed-step
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
    """The observed orders of :func:`observed_orders` as markdown lines."""
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
    """How busy the machine was during the timed runs of section (d)."""
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
    """The cheapest run within each of three tolerances, and the runs that failed."""
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
    """``accuracy_<case>.png`` in ``plots_dir``: error against wall time per simulated second,
    log-log, one line per integrator and precision, each point labelled with its setting."""
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
