"""A declared stress suite: a capture team flown under one-factor shifts beyond its
training ranges, paired against another team on the same episodes.

A stress file (``configs/stress/*.yaml``, :class:`StressConfig`) names the team's scene,
the team (``policy``) and the team it is compared with (``compare``), the fidelity level,
the episodes and their seed, and the factors. Each factor is one quantity the episodes
draw, shifted one at a time with every other draw at its training range:

* ``draw``: a per-episode draw of ``env.randomize`` (:class:`~mysim_jax.config.env.RandomizeConfig`)
  fixed at each value, ``{low: v, high: v}`` (target mass, the evader's top speed, ...);
* ``box``: a box draw of ``env.randomize`` (the wind force) widened to ``±v`` on the
  factor's ``axes``: ``{low: -v axes, high: v axes}``;
* ``perception_scale``: the team flies on perceived states, ``env.perception`` set to the
  stress file's ``perception`` block (a fitted error model, ``scripts/perception_gap.py
  fit``) with every ``sigma`` multiplied by ``v`` (0: true states, the nominal);
* ``latency``: the target estimate is ``v`` seconds old (``env.perception.target_latency``,
  true states otherwise; at most one policy period);
* ``thrust_loss``: one UAV (drawn per episode) loses the fraction ``v`` of its maximum
  thrust at a time drawn from the factor's ``fault_time`` (``env.randomize.thrust_loss``;
  1: its rotors stop).

The nominal point is the scene as the team trained on it (every draw at its training
range, true states), with the file's ``set`` overrides if it has any: they apply to every
point (e.g. another motor-saturation handling of the controller,
``quadrotors.N.controller.saturation``). Every point flies the same episodes (episode
``i`` of seed ``seed``, as ``scripts/evaluate.py --seed`` draws it), so a point differs from
the other team only in what was shifted (:mod:`mysim_jax.tasks.grid` runs the points).

The file also states the criterion a shift is judged by, at the value ``judged_at`` of
each factor: the policy's success at least ``fraction_of_nominal`` of its own nominal
success, its paired difference to the compared team at least ``lead_points``, and that
difference's 95 % interval's lower end at least ``lead_low95_points`` (each optional).

The file's model lives in :mod:`mysim_jax.config.stress` (validating a file imports no
JAX); :func:`plan_stress` then checks every point's scene and the output folder before
anything compiles.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mysim_jax.config.overrides import override_list  # noqa: E402
from mysim_jax.config.scene import load_config  # noqa: E402
from mysim_jax.config.stress import (NOMINAL, StressConfig, factor_override, load_stress,  # noqa: E402
                                     perception_block, training_range)
from mysim_jax.core.config_base import ConfigError  # noqa: E402
from mysim_jax.io.output import check_output_dir  # noqa: E402
from mysim_jax.tasks.grid import SweepError, plan_sweep, run_sweep  # noqa: E402

__all__ = ["NOMINAL", "StressConfig", "StressPlan", "factor_override", "load_stress", "perception_block",
           "plan_stress", "plot_stress", "run_stress", "stress_rows", "table_markdown", "training_range",
           "write_stress"]


@dataclass(frozen=True)
class StressPlan:
    """The checked plan: the stress file, its sweeps (the nominal first, then one per
    factor, in the file's order) and the output folder."""

    config: StressConfig
    source: str
    sweeps: tuple                                # (name, SweepPlan)
    out: Path
    ranges: dict                                 # factor name -> training range or None


def plan_stress(path, out, episodes: int | None = None) -> StressPlan:
    """Load the stress file and plan its sweeps (every point's scene loaded and checked,
    the output folders checked); ``episodes`` overrides the file's (a smaller run). No JAX
    work. ConfigError or OutputError, one line each."""
    cfg = load_stress(path)
    n = cfg.episodes if episodes is None else episodes
    if n < 1:
        raise ConfigError(f"episodes {n}: must be at least 1")
    out = check_output_dir(out)
    sets = [*cfg.set, *override_list(level=cfg.level)]
    base = load_config(cfg.scene, sets)
    if getattr(base, "env", None) is None:
        raise ConfigError(f"{cfg.scene}: a stress suite needs a capture scene with an env: block")
    block = perception_block(cfg.perception) if cfg.perception is not None else None
    common = dict(seed=None, episodes=n, batch=cfg.batch, policy=cfg.policy, compare=cfg.compare)
    sweeps = [(NOMINAL, plan_sweep(cfg.scene, sets, [f"seed={cfg.seed}"], **common, out=out / NOMINAL))]
    ranges = {}
    for f in cfg.factors:
        ranges[f.name] = training_range(base, f)
        if ranges[f.name] is None:
            raise ConfigError(f"{path}: factor {f.name}: {cfg.scene} does not draw env.randomize.{f.draw}, so it has "
                              "no training range to shift beyond")
        texts = [factor_override(f, v, block).partition("=")[2] for v in f.values]
        key = factor_override(f, f.values[0], block).partition("=")[0]
        sweep = plan_sweep(cfg.scene, sets, [f"{key}={','.join(texts)}"], seed=cfg.seed, episodes=n,
                           batch=cfg.batch, policy=cfg.policy, compare=cfg.compare, out=out / f.name)
        sweeps.append((f.name, sweep))
    return StressPlan(cfg, str(path), tuple(sweeps), out, ranges)


# --- results ---------------------------------------------------------------------------


def _below(x: float, bound: float, digits: int, sign: str) -> str:
    """``x`` (which is below ``bound``) with ``digits`` decimals, or as many more (up to 6)
    as it takes for the shown value to be below ``bound`` too: a lower end of -1.048 against
    -1 reads -1.05, not -1.0."""
    while digits < 6 and float(f"{x:{sign}.{digits}f}") >= bound:
        digits += 1
    return f"{x:{sign}.{digits}f}"


def _pair(rows: list[dict], point: int) -> tuple[dict, dict]:
    mine = [r for r in rows if r["point"] == point]
    return next(r for r in mine if r["team"] == "policy"), next(r for r in mine if r["team"] == "compare")


def stress_rows(plan: StressPlan, records: dict) -> list[dict]:
    """One row per point (the nominal first): factor, value, both teams' success with
    intervals, the paired difference with its interval, the policy's success as a fraction
    of its nominal, and at each factor's ``judged_at`` whether the criterion holds.
    ``records``: sweep name -> the sweep's record (its ``rows``)."""
    c = plan.config
    nominal_p, nominal_c = _pair(records[NOMINAL]["rows"], 0)
    out = []

    def row(factor, value, p, q, judged):
        frac = p["success_rate"] / nominal_p["success_rate"] if nominal_p["success_rate"] > 0 else math.nan
        r = {"factor": factor, "value": value, "episodes": p["episodes"],
             "policy_success": p["success_rate"], "policy_low95": p["success_low95"],
             "policy_high95": p["success_high95"],
             "compare_success": q["success_rate"], "compare_low95": q["success_low95"],
             "compare_high95": q["success_high95"],
             "difference_points": 100 * p["difference"], "difference_low95_points": 100 * p["difference_low95"],
             "difference_high95_points": 100 * p["difference_high95"], "fraction_of_nominal": frac,
             "judged": judged, "passes": None, "failing": ""}
        if judged:
            failing = []
            k = c.criterion
            if k.fraction_of_nominal is not None and not frac >= k.fraction_of_nominal:
                failing.append(f"{_below(frac, k.fraction_of_nominal, 2, '')} of nominal < {k.fraction_of_nominal:g}")
            if k.lead_points is not None and not r["difference_points"] >= k.lead_points:
                failing.append(f"difference {_below(r['difference_points'], k.lead_points, 1, '+')} < "
                               f"{k.lead_points:+g} points")
            if k.lead_low95_points is not None and not r["difference_low95_points"] >= k.lead_low95_points:
                failing.append(f"difference's lower end {_below(r['difference_low95_points'], k.lead_low95_points, 1, '+')}"
                               f" < {k.lead_low95_points:+g} points")
            r["passes"] = not failing
            r["failing"] = "; ".join(failing)
        return r

    out.append(row(NOMINAL, None, nominal_p, nominal_c, False))
    for f in c.factors:
        rows = records[f.name]["rows"]
        for i, v in enumerate(f.values):
            p, q = _pair(rows, i)
            out.append(row(f.name, v, p, q, v == f.judged_at))
    return out


STRESS_COLUMNS = ("factor", "value", "episodes", "policy_success", "policy_low95", "policy_high95",
                  "compare_success", "compare_low95", "compare_high95", "difference_points",
                  "difference_low95_points", "difference_high95_points", "fraction_of_nominal", "judged", "passes",
                  "failing")


def table_markdown(plan: StressPlan, rows: list[dict]) -> str:
    """The results as a Markdown table (the docs' table): per point both teams' success
    with intervals, the paired difference, the fraction of nominal, the verdict where judged."""
    c = plan.config
    labels = {f.name: f.label for f in c.factors}
    lines = [f"Every point with {', '.join(f'`{x}`' for x in c.set)}.", ""] if c.set else []
    lines += [f"| shift | value | training range | '{c.policy}' | '{c.compare}' | difference [points] | "
             "of nominal | judged |", "|---|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        if r["factor"] == NOMINAL:
            shift, value, rng = "nominal (training ranges)", "–", "–"
        else:
            lo_hi = plan.ranges[r["factor"]]
            shift, value, rng = labels[r["factor"]], f"{r['value']:g}", f"{lo_hi[0]:g}–{lo_hi[1]:g}"
        verdict = "" if not r["judged"] else ("**meets**" if r["passes"] else f"**fails**: {r['failing']}")
        lines.append(f"| {shift} | {value} | {rng} | {r['policy_success']:.1%} ({r['policy_low95']:.1%}–"
                     f"{r['policy_high95']:.1%}) | {r['compare_success']:.1%} ({r['compare_low95']:.1%}–"
                     f"{r['compare_high95']:.1%}) | {r['difference_points']:+.1f} ({r['difference_low95_points']:+.1f}"
                     f" to {r['difference_high95_points']:+.1f}) | {r['fraction_of_nominal']:.2f} | {verdict} |")
    return "\n".join(lines) + "\n"


def plot_stress(plan: StressPlan, rows: list[dict], path) -> Path:
    """One panel per factor: both teams' success (95 % Wilson bars) against the factor's
    value, the training range shaded, the nominal success as horizontal lines, the judged
    value marked."""
    c = plan.config
    nominal = rows[0]
    n = len(c.factors)
    cols = min(3, n)
    fig, axes = plt.subplots(math.ceil(n / cols), cols, figsize=(4.2 * cols, 3.3 * math.ceil(n / cols)),
                             squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    for ax, f in zip(axes.flat, c.factors):
        mine = [r for r in rows if r["factor"] == f.name]
        lo, hi = plan.ranges[f.name]
        xs = [lo if lo == hi else (lo + hi) / 2] + [r["value"] for r in mine]
        for team, colour, ls in (("policy", "C0", "-"), ("compare", "C1", "--")):
            pts = [nominal] + mine
            y = [r[f"{team}_success"] for r in pts]
            err = [[r[f"{team}_success"] - r[f"{team}_low95"] for r in pts],
                   [r[f"{team}_high95"] - r[f"{team}_success"] for r in pts]]
            ax.errorbar(xs, y, yerr=err, color=colour, ls=ls, marker="o", capsize=3,
                        label=f"{team} '{c.policy if team == 'policy' else c.compare}'")
            ax.axhline(nominal[f"{team}_success"], color=colour, lw=0.8, ls=":")
        if hi > lo:
            ax.axvspan(lo, hi, color="0.85", zorder=0, label="training range")
        ax.axvline(f.judged_at, color="0.4", lw=0.8, ls="-.")
        ax.set_xlabel(f.label)
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
    axes.flat[0].set_ylabel("success (95 % interval)")
    axes.flat[0].legend(fontsize=7, loc="lower left")
    fig.suptitle(f"{c.name}: {nominal['episodes']} episodes per point (seed {c.seed}, level {c.level}); "
                 "first point = nominal; dash-dot: judged value", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def write_stress(plan: StressPlan, records: dict, command: str = "") -> dict:
    """``stress.csv``, ``stress.json``, ``table.md`` and ``stress.png`` into the plan's
    folder (beside each sweep's own folder); returns the JSON record."""
    rows = stress_rows(plan, records)
    with (plan.out / "stress.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=STRESS_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    (plan.out / "table.md").write_text(table_markdown(plan, rows))
    plot_stress(plan, rows, plan.out / "stress.png")
    judged = [r for r in rows if r["judged"]]
    record = {"stress_file": plan.source, "command": command, "config": plan.config.model_dump(),
              "training_ranges": plan.ranges, "rows": rows,
              "judged": {"shifts": len(judged), "met": sum(bool(r["passes"]) for r in judged),
                         "failing": [r["factor"] for r in judged if not r["passes"]]},
              "wall_s": {name: records[name].get("wall_s") for name in records}}
    (plan.out / "stress.json").write_text(json.dumps(record, indent=2, default=str))
    return record


def written_sweep(sweep) -> dict | None:
    """The record of ``sweep`` already written in its folder with the same points, seeds,
    episodes and teams (an interrupted suite's finished factor), else None."""
    try:
        record = json.loads((sweep.out / "sweep.json").read_text())
    except (OSError, ValueError):
        return None
    same = (record.get("episodes") == sweep.episodes and record.get("policy") == sweep.policy
            and record.get("compare") == sweep.compare
            and [(p["overrides"], p["seed"]) for p in record.get("points", [])]
            == [(list(p.overrides), p.seed) for p in sweep.points])
    return record if same else None


def run_stress(plan: StressPlan, make_policy, *, progress: bool = True, command: str = "", log=print) -> dict:
    """Run every sweep of the plan in order (a finished one already written is read
    instead: :func:`written_sweep`), then write the suite's outputs (:func:`write_stress`)
    and return its record. ``make_policy``: as :func:`mysim_jax.tasks.grid.run_sweep`'s.
    SweepError (naming the factor) when a point cannot be evaluated."""
    records = {}
    for i, (name, sweep) in enumerate(plan.sweeps):
        head = f"[{i + 1}/{len(plan.sweeps)}] {name}:"
        done = written_sweep(sweep)
        if done is not None:
            log(f"{head} read {sweep.out / 'sweep.json'} (already run)")
            records[name] = done
            continue
        log(f"{head} {len(sweep.points)} point(s) x {sweep.episodes} episodes")
        try:
            records[name] = run_sweep(sweep, make_policy, progress=progress, command=command)
        except SweepError as err:
            raise SweepError(f"{name}: {err}") from None
    return write_stress(plan, records, command)
