"""Measure the gradient map of a capture scene at several fidelity levels and write it
(``scripts/gradmap.py``; the measurement is :mod:`mysim_jax.grad.gradmap`).

Into a folder:

* ``gradmap.json`` — the settings, the objective's weights, the team's parameters, the
  machine, the wall time and every row (level, segment, horizon, kind, fix, statistics);
* ``gradmap.csv`` — the rows as a table;
* ``gradmap.md`` — the rows without a fix as a markdown table per level;
* ``gradmap_norm.png`` and ``gradmap_cosine.png`` — the gradient's norm (with the
  smoothing estimate's) and its cosine with the smoothing estimate (with the cosine's
  ceiling for that many samples) against the horizon, per segment, one panel per level
  and kind.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

from mysim_jax.core.machine import cpu_model, usable_cores  # noqa: E402
from mysim_jax.grad.engine import GradientEngine  # noqa: E402
from mysim_jax.grad.gradmap import KINDS, MapSettings, horizon_steps, level_settings, measure_level  # noqa: E402
from mysim_jax.grad.objective import ObjectiveWeights  # noqa: E402
from mysim_jax.io.output import staged_output  # noqa: E402
from mysim_jax.tasks.capture import make_env  # noqa: E402

COLUMNS = ("level", "segment", "horizon_s", "steps", "kind", "fix", "windows", "episodes", "nonfinite", "nan",
           "start_mean_s", "after_contact", "objective_mean", "norm_mean", "norm_median", "norm_max", "cv",
           "norm_cv", "zo_norm_mean", "cosine_mean", "cosine_median", "cosine_linear", "growth_per_s")


def run_gradmap(configs: dict, settings: MapSettings, out_dir: Path, source: str, caps: dict | None = None,
                weights: ObjectiveWeights = ObjectiveWeights(), progress: bool = True, log=print) -> dict:
    """Measure the map on every level of ``configs`` (``{level: SceneConfig}``, each a
    capture environment) with ``settings`` (horizons above ``caps[level]`` seconds left
    out on that level) and write the folder (module docstring). Returns the JSON's dict."""
    caps = caps or {}
    t0 = time.perf_counter()
    envs = {level: make_env(config) for level, config in configs.items()}
    plans = {level: level_settings(settings, caps.get(level)) for level in configs}
    total = sum(len(plans[lv].segments) * len(horizon_steps(plans[lv].horizons, env.policy_dt))
                for lv, (env, _) in envs.items())
    rows, team = [], None
    with tqdm(total=total, desc="gradient map", unit="window", disable=not progress) as bar:
        for level, (env, params) in envs.items():
            engine = GradientEngine(env, params, weights)
            team = engine.problem.team
            bar.set_postfix_str(level)
            rows += measure_level(engine, plans[level], level, progress=bar.update)
    result = {"config": source, "levels": list(configs), "settings": _jsonable(settings), "caps_s": caps,
              "weights": dataclasses.asdict(weights), "team_parameters": list(team.names),
              "team_nominal": list(team.nominal), "machine": {"cpu": cpu_model(), "cores": usable_cores()},
              "wall_time_s": time.perf_counter() - t0,
              "rows": rows}
    with staged_output(out_dir) as out:
        (out / "gradmap.json").write_text(json.dumps(result, indent=2))
        (out / "gradmap.csv").write_text(csv_text(rows))
        (out / "gradmap.md").write_text(markdown_tables(rows))
        plot_map(rows, out / "gradmap_norm.png", "norm")
        plot_map(rows, out / "gradmap_cosine.png", "cosine")
    log(f"gradient map of {source} in {result['wall_time_s']:.0f} s; wrote {out_dir}/gradmap.json, gradmap.csv, "
        "gradmap.md, gradmap_norm.png, gradmap_cosine.png")
    return result


def _jsonable(settings: MapSettings) -> dict:
    return dataclasses.asdict(settings)


def csv_text(rows, columns=COLUMNS) -> str:
    """The rows (dicts) as CSV with ``columns`` (:data:`COLUMNS` by default; a missing
    value is empty, a float written with 6 significant digits)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()


def _fmt(v, spec=".3g"):
    return "–" if v is None else format(v, spec)


def markdown_tables(rows) -> str:
    """One markdown table per level and kind: segment, horizon, episodes, norm (median,
    max), spread, cosine (mean, median, ceiling), smoothing norm; then the truncated rows."""
    lines = []
    head = ("| segment | horizon [s] | episodes (non-finite) | ‖g‖ median | ‖g‖ max | cv | cos mean | cos median "
            "| cos ceiling | ‖g_ZO‖ mean | growth [1/s] |\n|---|---|---|---|---|---|---|---|---|---|---|")
    for level in dict.fromkeys(r["level"] for r in rows):
        for kind in KINDS:
            for fix in dict.fromkeys(r["fix"] for r in rows):
                sel = [r for r in rows if r["level"] == level and r["kind"] == kind and r["fix"] == fix]
                if not sel:
                    continue
                title = f"{level}, gradient w.r.t. the {'team parameters' if kind == 'team' else 'actions'}"
                lines += [f"#### {title}" + ("" if fix == "none" else f", backward pass {fix}"), "", head]
                for r in sel:
                    lines.append(
                        f"| {r['segment']} | {r['horizon_s']:g} | {r.get('episodes', 0)} ({r.get('nonfinite', 0)}) "
                        f"| {_fmt(r.get('norm_median'))} | {_fmt(r.get('norm_max'))} | {_fmt(r.get('cv'), '.2f')} "
                        f"| {_fmt(r.get('cosine_mean'), '.2f')} | {_fmt(r.get('cosine_median'), '.2f')} "
                        f"| {_fmt(r.get('cosine_linear'), '.2f')} | {_fmt(r.get('zo_norm_mean'))} "
                        f"| {_fmt(r.get('growth_per_s'), '.0f')} |")
                lines.append("")
    return "\n".join(lines)


def plot_map(rows, path: Path, what: str) -> None:
    """``what`` ``norm`` or ``cosine`` against the horizon (log axes; cosine on a linear
    axis), one line per segment, a panel per level and kind; rows without a fix."""
    levels = list(dict.fromkeys(r["level"] for r in rows))
    fig, axes = plt.subplots(len(KINDS), len(levels), figsize=(5.2 * len(levels), 7), squeeze=False)
    for j, level in enumerate(levels):
        for i, kind in enumerate(KINDS):
            ax = axes[i, j]
            for c, segment in enumerate(dict.fromkeys(r["segment"] for r in rows)):
                sel = [r for r in rows if (r["level"], r["kind"], r["segment"], r["fix"]) == (level, kind, segment, "none")
                       and r.get("episodes", 0) > 0]
                if not sel:
                    continue
                h = [r["horizon_s"] for r in sel]
                if what == "norm":
                    ax.loglog(h, [r["norm_median"] for r in sel], "o-", color=f"C{c}", label=f"{segment}: autodiff")
                    ax.loglog(h, [r["zo_norm_mean"] for r in sel], "x--", color=f"C{c}", alpha=0.7,
                              label=f"{segment}: smoothing")
                else:
                    ax.semilogx(h, [r["cosine_mean"] for r in sel], "o-", color=f"C{c}", label=f"{segment}")
                    ax.semilogx(h, [r["cosine_linear"] for r in sel], ":", color=f"C{c}", alpha=0.7)
            ax.set_title(f"{level}: w.r.t. {'team parameters' if kind == 'team' else 'actions'}")
            ax.set_xlabel("horizon [s]")
            ax.set_ylabel("|grad J| (median over episodes)" if what == "norm" else "cosine(autodiff, smoothing)")
            if what == "cosine":
                ax.set_ylim(-1.05, 1.05)
                ax.axhline(0.0, color="0.6", lw=0.8)
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=7)
    note = "dotted: the cosine an exactly linear objective gives with the same samples" if what == "cosine" else ""
    fig.suptitle(f"gradient map: {'norm' if what == 'norm' else 'cosine with the smoothing estimate'}  {note}",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
