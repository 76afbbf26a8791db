#!/usr/bin/env python
"""Tune the quadrotor PID gains by gradient descent through the closed-loop simulation.

    python scripts/tune_pid.py configs/uav_track_large.yaml --out out/tune \\
        [--heldout configs/uav_track_heldout.yaml] [--iterations 40] [--checkpoint] [--horizon-study]

Differentiates the mean squared tracking error over the scene's run (or ``--horizon``
seconds) with respect to the log-gains (``gain = gain₀ exp(θ)``: positive, relative
steps; see mysim_jax/tuning/gains.py) and runs Adam (global-norm clipping, non-finite
updates skipped). Writes into OUT:

* ``gains.yaml`` — the tuned gains (``simulate.py SCENE --gains OUT/gains.yaml``);
* ``tuned_config.yaml`` — the scene with the tuned gains (``simulate.py`` runs it as is);
* ``loss_curve.png`` — RMS tracking error and gradient norm per iteration;
* ``metrics.json`` — RMS / max errors before and after, on the scene and on every
  ``--heldout`` scene (same evaluation as ``simulate.py``'s metrics.json);
* ``config.yaml`` — the resolved input scene;
* with ``--horizon-study``: ``horizon_study.json`` and ``horizon_study.md`` — gradient
  norm, truncation error, time and memory against the horizon.
"""

from __future__ import annotations

import argparse
import json
import sys
import time


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", help="YAML scene with controlled quadrotors")
    parser.add_argument("--out", required=True, help="output directory (created if missing)")
    parser.add_argument("--heldout", action="append", default=[], metavar="CONFIG",
                        help="scene to evaluate before/after, not tuned on (repeatable)")
    parser.add_argument("--iterations", type=int, default=40, help="optimiser steps (default 40)")
    parser.add_argument("--lr", type=float, default=0.05, help="Adam learning rate on log-gains (default 0.05)")
    parser.add_argument("--clip", type=float, default=1.0, help="global-norm gradient clip (default 1.0)")
    parser.add_argument("--horizon", type=float, default=None, help="loss horizon in s (default: sim.t_end)")
    parser.add_argument("--every", type=int, default=10, help="loss sample / checkpoint interval in steps")
    parser.add_argument("--checkpoint", action="store_true",
                        help="rematerialise chunks of --every steps in the backward pass (memory ~100x lower "
                             "on long horizons, compile ~2x slower; see --horizon-study)")
    parser.add_argument("--horizon-study", action="store_true",
                        help="also measure gradient norm, truncation error, time and memory against the horizon")
    parser.add_argument("--study-horizons", default="1,2.5,5,10,20", help="horizons (s) for --horizon-study")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value (repeatable)")
    parser.add_argument("--no-progress", action="store_true", help="hide progress bars")
    args = parser.parse_args(argv)
    if args.iterations < 0 or args.lr <= 0 or args.clip <= 0 or args.every < 1:
        print("error: --iterations >= 0, --lr > 0, --clip > 0, --every >= 1", file=sys.stderr)
        return 2

    from mysim_jax.config.scene import ConfigError, dump_config, load_config
    from mysim_jax.io.output import OutputError, check_output_dir, staged_output

    try:
        config = load_config(args.config, args.overrides)
        heldout = [load_config(path) for path in args.heldout]
        out_dir = check_output_dir(args.out)
    except (ConfigError, OutputError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for path, cfg in [(args.config, config)] + list(zip(args.heldout, heldout)):
        if not cfg.quadrotors or cfg.quadrotors[0].controller is None:
            print(f"error: {path}: quadrotors: the scene has no controlled quadrotor to tune", file=sys.stderr)
            return 2
    if args.horizon is not None and args.horizon <= 0:
        print("error: --horizon must be positive", file=sys.stderr)
        return 2

    import jax

    if any(c.sim.precision == "float64" for c in [config] + heldout):
        jax.config.update("jax_enable_x64", True)

    import numpy as np
    import yaml

    from mysim_jax.build import build
    from mysim_jax.tuning.tracking import evaluate_tracking
    from mysim_jax.tuning.gains import gains_to_dict, horizon_study, tune, with_gains

    try:
        scene, params, state = build(config)
        held = [build(c) for c in heldout]
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for (hs, hp, _), path in zip(held, args.heldout):
        if hs.quadrotor.n_quads != scene.quadrotor.n_quads:
            print(f"error: {path}: has {hs.quadrotor.n_quads} quadrotors, {args.config} has "
                  f"{scene.quadrotor.n_quads}", file=sys.stderr)
            return 2

    horizon = config.sim.t_end if args.horizon is None else args.horizon
    n_steps = max(1, int(round(horizon / scene.dt / args.every))) * args.every

    t0 = time.perf_counter()
    result = tune(scene, params, state, n_steps, iterations=args.iterations, learning_rate=args.lr,
                  clip_norm=args.clip, every=args.every, remat=args.checkpoint, progress=not args.no_progress)
    wall = time.perf_counter() - t0

    with staged_output(out_dir) as out:
        (out / "config.yaml").write_text(dump_config(config))
        tuned = jax.tree.map(lambda a, ref: jax.numpy.asarray(a, dtype=ref.dtype), result.gains,
                             params.controller.gains)
        n_quads = scene.quadrotor.n_quads
        per_quad = [gains_to_dict(result.gains, q) for q in range(n_quads)]
        gains_doc = {"controller": per_quad[0]} if n_quads == 1 else {"quadrotors": [{"controller": g} for g in per_quad]}
        header = (f"# PID gains tuned by scripts/tune_pid.py on {args.config} ({horizon:g} s horizon, "
                  f"{args.iterations} Adam steps, lr {args.lr:g}).\n# Use: python scripts/simulate.py SCENE "
                  f"--gains {out_dir / 'gains.yaml'}\n")
        (out / "gains.yaml").write_text(header + yaml.safe_dump(gains_doc, sort_keys=False))
        quads = [q.model_copy(update={"controller": q.controller.model_copy(update={
            "position": q.controller.position.model_validate(g["position"]),
            "attitude": q.controller.attitude.model_validate(g["attitude"])})})
            for q, g in zip(config.quadrotors, per_quad)]
        (out / "tuned_config.yaml").write_text(dump_config(config.model_copy(update={"quadrotors": quads})))

        metrics = {
            "scene": config.name,
            "horizon_s": n_steps * scene.dt,
            "iterations": args.iterations,
            "learning_rate": args.lr,
            "clip_norm": args.clip,
            "wall_time_s": wall,
            "loss_initial_m2": result.initial_loss,
            "loss_best_m2": result.best_loss,
            "best_iteration": result.best_iteration,
            "tuned_gains": per_quad,
            "evaluation": {},
        }

        def evaluate(name, sc, pa, st, run):
            before = evaluate_tracking(sc, pa, st, run)
            after = evaluate_tracking(sc, with_gains(pa, tuned), st, run)
            rows = {}
            for body in before:
                b, a = before[body]["rms_position_error_m"], after[body]["rms_position_error_m"]
                rows[body] = {"before": before[body], "after": after[body], "rms_reduction": 1.0 - a / b}
                print(f"{name} {body}: RMS {b:.4g} m -> {a:.4g} m ({100 * (1 - a / b):+.1f} % reduction), "
                      f"max {before[body]['max_position_error_m']:.4g} m -> {after[body]['max_position_error_m']:.4g} m")
            metrics["evaluation"][name] = rows

        evaluate(config.name, scene, params, state, config.run_settings())
        for cfg, (hs, hp, hst) in zip(heldout, held):
            evaluate(cfg.name, hs, hp, hst, cfg.run_settings())

        _plot_losses(result, out / "loss_curve.png", config.name)
        if args.horizon_study:
            horizons = [float(h) for h in args.study_horizons.split(",") if h.strip()]
            rows = horizon_study(scene, params, state, horizons, every=args.every, progress=not args.no_progress)
            metrics["horizon_study"] = rows
            (out / "horizon_study.json").write_text(json.dumps(rows, indent=2))
            (out / "horizon_study.md").write_text(_study_table(rows))
            print(_study_table(rows))
        (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    print(f"{config.name}: tuned in {wall:.1f} s (compile included); best RMS {np.sqrt(result.best_loss):.4g} m "
          f"(from {np.sqrt(result.initial_loss):.4g} m, sampled every {args.every} steps) at iteration "
          f"{result.best_iteration}; wrote {out_dir}/gains.yaml, tuned_config.yaml, loss_curve.png, metrics.json")
    return 0


def _plot_losses(result, path, name):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

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


def _study_table(rows) -> str:
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


if __name__ == "__main__":
    sys.exit(main())
