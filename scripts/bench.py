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
  k  target detection: frames per second of the learned detector at 640 x 360 on the whole
     image and in region mode (what gimbal tracking runs), side by side
     (mysim_jax/bench/detect.py).

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
import datetime as _dt
import sys
import time
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

from mysim_jax.bench import accuracy, detect, environment, levels, mujoco_compare, render, throughput, training
from mysim_jax.bench.accuracy_cases import accuracy_cases
from mysim_jax.bench.report import ROOT, SECTIONS, BenchConfig, header_lines, output_paths, summary_lines, write_report
from mysim_jax.bench.timing import load_average

RUNNERS = {"a": throughput.section_a, "b": throughput.section_b, "c": mujoco_compare.section_c,
           "d": accuracy.section_d, "e": environment.section_e, "f": throughput.section_f,
           "g": training.section_g, "h": render.section_h, "i": levels.section_i, "j": throughput.section_j,
           "k": detect.section_k}


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (the documented-commands test parses with it)."""
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
    return parser


def _config(parser, args) -> BenchConfig:
    """The run's settings from its options; makes the output and plot folders."""
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
    out, plots_dir = output_paths(args.out, args.update, partial)
    return BenchConfig(
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


def main(argv=None) -> int:
    """Run the sections asked for and write the report (or refresh the training runs only)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.runs_only:
        return training.refresh_training_runs(Path(args.out) if args.out else ROOT / "BENCHMARKS.md")
    cfg = _config(parser, args)
    started = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    load_start = load_average()
    t_start = time.perf_counter()
    results: dict[str, Any] = {}
    body: list[str] = []
    order = [s for s in SECTIONS if s in cfg.sections]
    for s in tqdm(order, desc="bench sections", unit="section"):
        t0 = time.perf_counter()
        body += RUNNERS[s](cfg, results)
        body.append(f"*(section {s}: {time.perf_counter() - t0:.0f} s)*")
        body.append("")
    throughput.plot_throughput(results, cfg.plots_dir)
    wall = time.perf_counter() - t_start

    text = (header_lines(args, started, load_start, load_average(), wall, mujoco_compare.MUJOCO_VERSION)
            + summary_lines(results) + body)
    write_report(text, cfg.out, cfg.plots_dir, args.update, order)
    print(f"wrote {cfg.out} ({wall / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
