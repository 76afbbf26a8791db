"""Tune a scene's PID gains and write the results (``scripts/tune_pid.py``).

Into a folder: ``gains.yaml`` (``simulate.py SCENE --gains``), ``tuned_config.yaml`` (the
scene with the tuned gains), ``loss_curve.png``, ``metrics.json`` (tracking errors before
and after on the scene and on held-out scenes), ``config.yaml`` and, with a horizon study,
``horizon_study.json`` / ``.md``. The optimisation itself is :func:`mysim_jax.tuning.gains.tune`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import jax
import numpy as np
import yaml
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mysim_jax.build import build
from mysim_jax.config.scene import ConfigError, SceneConfig, dump_config
from mysim_jax.io.output import staged_output
from mysim_jax.tuning.gains import gains_to_dict, horizon_study, tune, with_gains
from mysim_jax.tuning.tracking import evaluate_tracking


@dataclass(frozen=True)
class TuneSettings:
    iterations: int = 40           # Adam steps
    lr: float = 0.05               # on log-gains
    clip: float = 1.0              # global-norm gradient clip
    horizon: float | None = None   # s, the loss horizon (None: the scene's sim.t_end)
    every: int = 10                # steps between loss samples / checkpoints
    checkpoint: bool = False       # rematerialise chunks of ``every`` steps in the backward pass
    study_horizons: tuple[float, ...] = field(default_factory=tuple)   # s; empty: no horizon study
    progress: bool = True


def tune_scene(config: SceneConfig, heldout: list[tuple[str, SceneConfig]], out_dir: Path,
               settings: TuneSettings, source: str, log=print) -> dict:
    """Tune ``config`` (read from ``source``)'s gains, evaluate before and after (also on the
    ``heldout`` ``(path, config)`` scenes), write the folder. Raises ConfigError when a scene does not build or a held-out scene has another
    number of quadrotors. Returns ``metrics.json``'s dict."""
    scene, params, state = build(config)
    held = [build(c) for _, c in heldout]
    for (hs, _, _), (path, _) in zip(held, heldout):
        if hs.quadrotor.n_quads != scene.quadrotor.n_quads:
            raise ConfigError(f"{path}: has {hs.quadrotor.n_quads} quadrotors, {source} has "
                              f"{scene.quadrotor.n_quads}")
    s = settings
    horizon = config.sim.t_end if s.horizon is None else s.horizon
    n_steps = max(1, int(round(horizon / scene.dt / s.every))) * s.every
    t0 = time.perf_counter()
    result = tune(scene, params, state, n_steps, iterations=s.iterations, learning_rate=s.lr, clip_norm=s.clip,
                  every=s.every, remat=s.checkpoint, progress=s.progress)
    wall = time.perf_counter() - t0
    tuned = jax.tree.map(lambda a, ref: jax.numpy.asarray(a, dtype=ref.dtype), result.gains, params.controller.gains)
    per_quad = [gains_to_dict(result.gains, q) for q in range(scene.quadrotor.n_quads)]
    metrics = {
        "scene": config.name, "horizon_s": n_steps * scene.dt, "iterations": s.iterations,
        "learning_rate": s.lr, "clip_norm": s.clip, "wall_time_s": wall,
        "loss_initial_m2": result.initial_loss, "loss_best_m2": result.best_loss,
        "best_iteration": result.best_iteration, "tuned_gains": per_quad, "evaluation": {},
    }
    with staged_output(out_dir) as out:
        (out / "config.yaml").write_text(dump_config(config))
        _write_gains(out, out_dir, config, per_quad, source, horizon, s)
        for cfg, (sc, pa, st) in [(config, (scene, params, state))] + [(c, h) for (_, c), h in zip(heldout, held)]:
            metrics["evaluation"][cfg.name] = _before_after(cfg.name, sc, pa, st, cfg.run_settings(), tuned, log)
        plot_losses(result, out / "loss_curve.png", config.name)
        if s.study_horizons:
            rows = horizon_study(scene, params, state, list(s.study_horizons), every=s.every, progress=s.progress)
            metrics["horizon_study"] = rows
            (out / "horizon_study.json").write_text(json.dumps(rows, indent=2))
            (out / "horizon_study.md").write_text(study_table(rows))
            log(study_table(rows))
        (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    log(f"{config.name}: tuned in {wall:.1f} s (compile included); best RMS {np.sqrt(result.best_loss):.4g} m "
        f"(from {np.sqrt(result.initial_loss):.4g} m, sampled every {s.every} steps) at iteration "
        f"{result.best_iteration}; wrote {out_dir}/gains.yaml, tuned_config.yaml, loss_curve.png, metrics.json")
    return metrics


def _write_gains(out: Path, out_dir: Path, config: SceneConfig, per_quad: list[dict], source: str, horizon: float,
                 s: TuneSettings) -> None:
    """``gains.yaml`` (one controller, or one per quadrotor) and ``tuned_config.yaml``."""
    doc = {"controller": per_quad[0]} if len(per_quad) == 1 else {"quadrotors": [{"controller": g} for g in per_quad]}
    header = (f"# PID gains tuned by scripts/tune_pid.py on {source} ({horizon:g} s horizon, "
              f"{s.iterations} Adam steps, lr {s.lr:g}).\n# Use: python scripts/simulate.py SCENE "
              f"--gains {out_dir / 'gains.yaml'}\n")
    (out / "gains.yaml").write_text(header + yaml.safe_dump(doc, sort_keys=False))
    quads = [q.model_copy(update={"controller": q.controller.model_copy(update={
        "position": q.controller.position.model_validate(g["position"]),
        "attitude": q.controller.attitude.model_validate(g["attitude"])})})
        for q, g in zip(config.quadrotors, per_quad)]
    (out / "tuned_config.yaml").write_text(dump_config(config.model_copy(update={"quadrotors": quads})))


def _before_after(name: str, scene, params, state, run, tuned, log) -> dict:
    """Tracking errors of every quadrotor with the scene's gains and with ``tuned``."""
    before = evaluate_tracking(scene, params, state, run)
    after = evaluate_tracking(scene, with_gains(params, tuned), state, run)
    rows = {}
    for body in before:
        b, a = before[body]["rms_position_error_m"], after[body]["rms_position_error_m"]
        rows[body] = {"before": before[body], "after": after[body], "rms_reduction": 1.0 - a / b}
        log(f"{name} {body}: RMS {b:.4g} m -> {a:.4g} m ({100 * (1 - a / b):+.1f} % reduction), "
            f"max {before[body]['max_position_error_m']:.4g} m -> {after[body]['max_position_error_m']:.4g} m")
    return rows


def plot_losses(result, path: Path, name: str) -> None:
    """RMS tracking error and gradient norm per iteration."""
    it = np.arange(len(result.losses))
    fig, (a, b) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    a.semilogy(it, np.sqrt(result.losses) * 1e3, lw=1.3)
    a.axvline(result.best_iteration, ls="--", color="0.5", lw=0.8)
    a.set_ylabel("RMS tracking error [mm]")
    a.set_title(f"{name}: gradient-based PID tuning (Adam on log-gains)")
    a.grid(alpha=0.3, which="both")
    b.semilogy(it, result.grad_norms, lw=1.0, color="C1")
    b.set_ylabel("|∇θ loss| (before clipping)")
    b.set_xlabel("iteration")
    b.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def study_table(rows) -> str:
    """The horizon study as a markdown table."""
    lines = [
        "| horizon [s] | RMS [m] | ‖∇L‖ | ‖∇L‖ / L | finite | truncated (1 s windows): cosine, norm ratio "
        "| checkpointed: max rel. diff | grad time plain / ckpt [s] | compile plain / ckpt [s] "
        "| XLA temp plain / ckpt [MB] |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['horizon_s']:g} | {r['rms_m']:.4g} | {r['grad_norm']:.3g} | {r['grad_norm'] / r['loss_m2']:.3g} "
            f"| {r['finite']} | {r['truncated_cosine']:.3f}, {r['truncated_norm_ratio']:.3f} "
            f"| {r['checkpointed_max_rel_diff']:.1e} "
            f"| {r['plain_grad_time_s']:.2f} / {r['checkpointed_grad_time_s']:.2f} "
            f"| {r['plain_compile_s']:.1f} / {r['checkpointed_compile_s']:.1f} "
            f"| {r['plain_temp_mb']:.1f} / {r['checkpointed_temp_mb']:.2f} |"
        )
    return "\n".join(lines) + "\n"
