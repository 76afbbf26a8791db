"""MuJoCo on the same rope net (BENCHMARKS.md (c)).

The float64 rope net is exported to MJCF (:func:`mysim_jax.io.mjcf.scene_to_mjcf`) and run
by MuJoCo with its Euler and RK4 integrators: their steps per second (one thread, timed
round-robin) and their payload height against the accuracy study's reference
(:func:`mysim_jax.bench.accuracy.reference_solution`), with our float64 semi-implicit Euler
on the same grid (the same discrete steps, so the two agree to round-off). With section (a)
in the same run, :func:`ratio_lines` compares our batched throughput with MuJoCo's.

MuJoCo is an optional dependency (the ``bench`` and ``test`` extras) and this is the only
module that imports it: without it the section says so and is skipped.
"""

from __future__ import annotations

import numpy as np
from tqdm.auto import tqdm

from mysim_jax.bench.accuracy import compile_run, precision_mode, reference_solution
from mysim_jax.bench.accuracy_cases import accuracy_cases
from mysim_jax.bench.report import HEADLINE_BATCH, ROPE_NET, TARGET_MUJOCO_RATIO
from mysim_jax.bench.timing import contention_note, median, spread, time_round_robin, wait_for_quiet
from mysim_jax.build import build
from mysim_jax.config.scene import load_config
from mysim_jax.io.mjcf import mujoco_point_positions, scene_to_mjcf

try:
    import mujoco
except ImportError:        # optional (the bench and test extras): section (c) is then skipped
    mujoco = None

MUJOCO_VERSION = mujoco.__version__ if mujoco is not None else "not installed"


def section_c(cfg, results) -> list[str]:
    """(c) MuJoCo's Euler and RK4 on the rope net: steps/s and payload error against the
    reference, beside our float64 semi-implicit Euler; the ours / MuJoCo ratio when (a) ran."""
    if mujoco is None:
        return ["## (c) MuJoCo", "", "MuJoCo is not installed (`pip install mujoco`); section skipped.", ""]

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
        ours_pos = np.asarray(compile_run(scene, params, state, config.run_settings()).call()[0])
        xml = scene_to_mjcf(scene, params, state, h)
    bar.update(1)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    every = int(round(case.reference_dt / h))

    euler = mujoco.mjtIntegrator.mjINT_EULER
    rk4 = mujoco.mjtIntegrator.mjINT_RK4
    mj_euler = _trajectory(model, data, euler, every, len(ref_times))
    mj_rk4 = _trajectory(model, data, rk4, every, len(ref_times))
    bar.update(1)

    n_time = int(round(case.t_end / h))

    wait_for_quiet(cfg.max_wait_s, "c")
    # the reset inside each call is < 1e-5 of the call's time
    timings = time_round_robin({"Euler": _timed_call(model, data, euler, n_time),
                                "RK4": _timed_call(model, data, rk4, n_time)}, cfg.repeats, bar, section="c")
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
    return lines + ratio_lines(results, sps["Euler"])


def _trajectory(model, data, integrator, every: int, n_out: int) -> np.ndarray:
    """Every point mass's position at ``n_out`` outputs ``every`` MuJoCo steps apart, from the
    model's keyframe: ``(n_out, n_points, 3)``."""
    model.opt.integrator = integrator
    mujoco.mj_resetDataKeyframe(model, data, 0)
    out = [mujoco_point_positions(model, data)]
    for _ in range(n_out - 1):
        mujoco.mj_step(model, data, nstep=every)
        out.append(mujoco_point_positions(model, data))
    return np.stack(out)


def _timed_call(model, data, integrator, n_time: int):
    """A call that runs ``n_time`` MuJoCo steps with ``integrator`` from the keyframe."""
    def call():
        model.opt.integrator = integrator
        mujoco.mj_resetDataKeyframe(model, data, 0)
        mujoco.mj_step(model, data, nstep=n_time)
    return call


def ratio_lines(results, mujoco_steps_per_s: float) -> list[str]:
    """Our throughput at :data:`HEADLINE_BATCH` (``results["ours_4096"]``, section (a)) over
    MuJoCo's single-thread steps/s against the target (setting ``results["ratio"]``), or a
    note that section (a) did not run."""
    sps = {"Euler": mujoco_steps_per_s}
    lines = []
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
