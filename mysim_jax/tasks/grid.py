"""A robustness / sensitivity sweep: one or two capture teams evaluated over a grid of scene
overrides, on the same episodes at every grid point (``scripts/sweep.py``).

**The grid.** Each axis is ``KEY=v1,v2,...`` (``--vary``): a dotted scene key (as ``--set``
takes it) and a list of YAML values, split on the commas outside brackets, braces and
quotes (:func:`split_values`), so ``{low: 0.1, high: 0.1}`` or ``[1, 0, 0]`` is one value.
The key ``seed`` is not a scene value: it is the evaluation's seed, so varying it draws
other episodes. ``level`` picks a fidelity level of the scene, as ``--set level=NAME``
does. The grid is the cartesian product of the axes, the first axis varying slowest;
a point's overrides are applied after ``--set``'s.

**Checked before anything compiles** (:func:`plan_sweep`): ``--set`` alone, each axis value
alone (so an error names the value that causes it), then every point's whole override
list is loaded and validated (:func:`~mysim_jax.config.scene.load_config`); an override of
a value a per-episode draw replaces is an error
(:func:`~mysim_jax.config.env.drawn_value_problems`); every point must be a capture scene
(net, target, quadrotors) of one precision; the output folder is checked. Then
(:func:`run_sweep`) each distinct scene's environment is made and both teams made and
traced on it (``make_policy``, e.g. :func:`mysim_jax.mappo.policies.make_checked_policy`),
still before the first compilation. Errors are :class:`~mysim_jax.core.config_base.ConfigError`,
:class:`~mysim_jax.io.output.OutputError` or :class:`SweepError`, each one line.

**Same episodes.** Episode ``i`` of a point seeded ``S`` is drawn from
``jax.random.PRNGKey(S)`` exactly as :func:`~mysim_jax.tasks.evaluate.run_episodes` and
:func:`~mysim_jax.tasks.evaluate.run_two_teams` draw it (the same
:class:`~mysim_jax.tasks.evaluate.Evaluator` program with the same policy wrappers), for
both teams: points with one seed fly the same episodes, and a point's numbers are those a
``scripts/evaluate.py`` run of its scene and seed gives. Points of one scene (a repeated
value, or the ``seed`` axis) share one compiled evaluator; every other scene compiles its
own (its parameters are constants of the compiled program).

**Outputs** (:func:`write_sweep`, through :func:`~mysim_jax.io.output.staged_output`: all
files or none): ``sweep.csv`` (one row per point and team: the varied values as typed,
seed, team, outcome counts and rates with 95 % Wilson intervals, mean length and return,
and on the policy's row the paired difference policy - compare with its 95 % interval),
``sweep.json`` (the same rows and the run's record) and ``success_<key>.png`` per axis.

**Resuming** (:func:`resume_folder`): while a sweep runs, each point's evaluation of each
team saves its progress every few minutes into ``.<out name>.resume/`` beside the output
folder (:class:`~mysim_jax.tasks.evaluate.Checkpoint`), and a run of the same sweep that
was stopped goes on from there, with the same numbers an uninterrupted run gives; a point
saved by other code (the package's source), other team files or another batch starts
again. The folder is removed once the outputs are written.
"""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

from mysim_jax.config.env import FAILURES, drawn_value_problems  # noqa: E402
from mysim_jax.config.overrides import override_list  # noqa: E402
from mysim_jax.config.scene import ConfigError, dump_config, load_config  # noqa: E402
from mysim_jax.core.config_base import parse_yaml  # noqa: E402
from mysim_jax.core.machine import machine  # noqa: E402
from mysim_jax.io.output import check_output_dir, staged_output  # noqa: E402
from mysim_jax.tasks.capture import make_env  # noqa: E402
from mysim_jax.tasks.evaluate import Checkpoint, Evaluator, files_digest, source_digest  # noqa: E402
from mysim_jax.tasks.sweep import paired_difference_interval, wilson_interval  # noqa: E402

SEED_KEY = "seed"
TEAMS = ("policy", "compare")
# columns of every row besides the varied keys; a varied key may not take one of these names
FIXED_COLUMNS = ("point", SEED_KEY, "team", "spec", "episodes", "successes", "success_rate", "success_low95",
                 "success_high95", "timeout_rate", *(f"failure_{f}" for f in FAILURES), "mean_length_steps",
                 "mean_return", "difference", "difference_low95", "difference_high95", "wall_s")


class SweepError(ValueError):
    """A grid point cannot be evaluated: its environment cannot be made, or a team cannot
    fly it. The message names the point."""


@dataclass(frozen=True)
class Axis:
    """One ``--vary`` axis: a dotted key and its values, as typed and parsed (YAML)."""

    key: str
    texts: tuple[str, ...]
    values: tuple


@dataclass(frozen=True)
class GridPoint:
    """One point of the grid: which value of each axis (``indices``, one per axis), the
    scene overrides that make it (``KEY=VALUE``, ``--set``'s not included), its seed, its
    validated config and ``scene_id`` (the resolved config's YAML: equal for equal scenes)."""

    index: int
    indices: tuple[int, ...]
    overrides: tuple[str, ...]
    seed: int
    config: object
    scene_id: str


@dataclass(frozen=True)
class SweepPlan:
    """Everything a sweep needs, checked (:func:`plan_sweep`)."""

    scene: str                      # the scene file's path
    sets: tuple[str, ...]           # --set overrides, KEY=VALUE, applied at every point
    axes: tuple[Axis, ...]
    points: tuple[GridPoint, ...]   # the grid in order, the first axis varying slowest
    episodes: int                   # per point and team
    batch: int                      # environment slots side by side, at most ``episodes``
    policy: str                     # the team specs (scripted, random, a policy folder, a .py file)
    compare: str | None
    out: Path                       # the checked output folder
    env_note: str | None            # set when the scene had no env: block (evaluated with env: {})
    precision: str                  # float32 or float64, one for every point

    def label(self, point: GridPoint, with_seed: bool = True) -> str:
        """``key=value, ...`` of a point (the seed last, or left out)."""
        parts = [f"{a.key}={a.texts[i]}" for a, i in zip(self.axes, point.indices) if a.key != SEED_KEY]
        return ", ".join(parts + ([f"seed {point.seed}"] if with_seed else [])) or "the scene"


def one_line(message: str) -> str:
    """A possibly multi-line error message (a validation report) on one line."""
    lines = [line.strip() for line in str(message).splitlines() if line.strip()]
    if len(lines) < 2:
        return lines[0] if lines else ""
    return lines[0].rstrip(":") + ": " + "; ".join(lines[1:])


def split_values(text: str, where: str = "--vary") -> list[str]:
    """The comma-separated values of ``text``, split only on the commas outside brackets,
    braces, parentheses and quotes, each stripped: ``"{a: 1, b: 2},[1, 2],x"`` gives
    ``["{a: 1, b: 2}", "[1, 2]", "x"]``. ConfigError on unbalanced brackets or quotes."""
    values, depth, quote, start = [], 0, None, 0
    for i, ch in enumerate(text):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "[{(":
            depth += 1
        elif ch in "]})":
            depth -= 1
            if depth < 0:
                raise ConfigError(f"{where}: '{text}': '{ch}' closes a bracket that was not opened")
        elif ch == "," and depth == 0:
            values.append(text[start:i].strip())
            start = i + 1
    if quote or depth:
        raise ConfigError(f"{where}: '{text}': unbalanced {'quote' if quote else 'brackets'}")
    values.append(text[start:].strip())
    return values


def parse_axis(text: str) -> Axis:
    """One ``--vary KEY=v1,v2,...`` (module docstring). ConfigError naming what is wrong:
    no ``=``, an empty key, no values, an empty value, broken YAML, a seed that is not a
    non-negative integer."""
    key, sep, rest = text.partition("=")
    key = ".".join(p for p in key.strip().split(".") if p)
    if not sep or not key:
        raise ConfigError(f"--vary '{text}': expected KEY=v1,v2,... (e.g. --vary env.policy_rate=10,25)")
    if not rest.strip():
        raise ConfigError(f"--vary {key}: no values; give them as {key}=v1,v2,...")
    texts = split_values(rest, f"--vary {key}")
    if "" in texts:
        raise ConfigError(f"--vary {key}={rest}: value {texts.index('') + 1} is empty (write null for YAML's null)")
    if key in FIXED_COLUMNS and key != SEED_KEY:
        raise ConfigError(f"--vary {key}: '{key}' is a column of sweep.csv, not a scene key")
    values = tuple(parse_yaml(t, f"--vary {key}", "value") for t in texts)
    if key == SEED_KEY:
        bad = [t for t, v in zip(texts, values) if isinstance(v, bool) or not isinstance(v, int) or v < 0]
        if bad:
            raise ConfigError(f"--vary seed={rest}: '{bad[0]}' is not a seed (a non-negative integer)")
    return Axis(key, tuple(texts), values)


def _load(scene: str, overrides, where: str):
    """The validated config of ``scene`` with ``overrides``; ConfigError prefixed ``where``."""
    try:
        return load_config(scene, list(overrides))
    except ConfigError as err:
        raise ConfigError(f"{where}{one_line(err)}") from None


def _capture_problem(config, scene: str) -> str | None:
    missing = [b for b, v in (("net", config.net), ("target", config.target), ("quadrotors", config.quadrotors))
               if not v]
    return f"{scene}: not a capture scene: it has no {' and no '.join(missing)} block" if missing else None


def _check_axes(scene: str, sets, axes) -> None:
    """Each axis value alone over ``--set`` loads, so an error names the value causing it."""
    keys = [a.key for a in axes]
    repeated = sorted({k for k in keys if keys.count(k) > 1})
    if repeated:
        raise ConfigError(f"--vary {repeated[0]}: given twice; list all its values in one --vary")
    set_keys = {".".join(p for p in s.partition("=")[0].split(".") if p): s for s in sets}
    for axis in axes:
        if axis.key in set_keys:
            raise ConfigError(f"--vary {axis.key}: also set by --set {set_keys[axis.key]}; give it in one place")
        if axis.key == SEED_KEY:
            continue
        for text in dict.fromkeys(axis.texts):
            _load(scene, [*sets, f"{axis.key}={text}"], f"--vary {axis.key}={text}: ")


def _grid_point(scene: str, sets, axes, index: int, indices, seed: int) -> tuple[GridPoint, bool]:
    """One checked point, and whether its scene had no env: block (evaluated with ``env: {}``)."""
    overrides = tuple(f"{a.key}={a.texts[i]}" for a, i in zip(axes, indices) if a.key != SEED_KEY)
    seed = next((a.values[i] for a, i in zip(axes, indices) if a.key == SEED_KEY), seed)
    where = f"--vary point {', '.join(overrides)}: " if overrides else ""
    config = _load(scene, [*sets, *overrides], where)
    problems = drawn_value_problems(config, sets, "--set") + drawn_value_problems(config, overrides, "--vary")
    if problems:
        raise ConfigError("; ".join(problems))
    capture = _capture_problem(config, scene)
    if capture:
        raise ConfigError(f"{where}{capture}")
    no_env = config.env is None
    if no_env:
        config = _load(scene, override_list([*sets, *overrides], first=["env={}"]), where)
    return GridPoint(index, tuple(indices), overrides, int(seed), config, dump_config(config)), no_env


def plan_sweep(scene: str, sets, vary, *, seed: int | None, episodes: int, batch: int, policy: str,
               compare: str | None, out) -> SweepPlan:
    """Parse the axes, load and check ``--set`` and every grid point, and check ``out``
    (module docstring). ``seed``: the evaluation seed when ``seed`` is not an axis (None:
    0). No JAX work. Raises ConfigError or OutputError (one line each)."""
    sets = tuple(sets)
    base = _load(scene, sets, "")
    problems = drawn_value_problems(base, sets, "--set")
    if problems:
        raise ConfigError("; ".join(problems))
    if _capture_problem(base, scene):
        raise ConfigError(_capture_problem(base, scene))
    axes = tuple(parse_axis(v) for v in vary)
    if not axes:
        raise ConfigError("--vary: give at least one axis, e.g. --vary env.policy_rate=10,25")
    if seed is not None and any(a.key == SEED_KEY for a in axes):
        raise ConfigError(f"--seed {seed} and --vary seed=...: give the seeds in one place")
    _check_axes(scene, sets, axes)
    points, no_env = [], False
    grid = itertools.product(*(range(len(a.texts)) for a in axes))
    for index, indices in enumerate(grid):
        point, missing_env = _grid_point(scene, sets, axes, index, indices, 0 if seed is None else seed)
        points.append(point)
        no_env |= missing_env
    precisions = sorted({p.config.sim.precision for p in points})
    if len(precisions) > 1:
        raise ConfigError(f"--vary: the points run at {' and '.join(precisions)} precision; JAX runs one precision "
                          "per process, so sweep each precision separately")
    out = check_output_dir(out)
    note = (f"note: {scene} has no env: block; evaluating with the defaults (env: {{}})" if no_env else None)
    return SweepPlan(scene, sets, axes, tuple(points), episodes, min(batch, episodes), policy, compare, out, note,
                     precisions[0])


def _prepare(plan: SweepPlan, make_policy) -> dict:
    """``scene_id -> (env, params, policy, other)`` for every distinct scene of the grid,
    each team made and checked on its environment (no compilation). SweepError naming
    the point when the environment cannot be made or a team cannot fly it."""
    prepared = {}
    for point in plan.points:
        if point.scene_id in prepared:
            continue
        where = plan.label(point, with_seed=False)
        try:
            env, params = make_env(point.config)
        except ValueError as err:                  # ConfigError too: the scene cannot be an environment
            raise SweepError(f"{plan.scene} at {where}: {one_line(err)}") from None
        teams = []
        for spec, flag in ((plan.policy, "--policy"), (plan.compare, "--compare")):
            try:
                teams.append(None if spec is None else make_policy(env, params, spec, flag))
            except ValueError as err:              # PolicyError: the team cannot fly this scene
                raise SweepError(f"at {where}: {one_line(err)}") from None
        prepared[point.scene_id] = (env, params, *teams)
    return prepared


def _team_call(policy, other):
    """The policy the evaluator runs, ``(key, obs, state, params, args)``: ``policy`` alone
    as :func:`~mysim_jax.tasks.evaluate.run_episodes` wraps it, or with ``other`` both
    teams' actions and ``args`` (a bool) picking one, as
    :func:`~mysim_jax.tasks.evaluate.run_two_teams` does."""
    if other is None:
        return lambda k, obs, state, p, args: policy(k, obs, state, p)

    def either(k, obs, state, p, use_other):
        return jnp.where(use_other, other(k, obs, state, p), policy(k, obs, state, p))
    return either


@dataclass
class PointResult:
    """One point's outcome: each team's EpisodeStats (``base`` None without a compared
    team) and the wall time of its evaluation [s] (compilation included where it compiled;
    a resumed evaluation's includes the earlier runs' time)."""

    point: GridPoint
    stats: object
    base: object
    wall_s: float


def resume_folder(plan: SweepPlan) -> Path:
    """Where a running sweep saves its points' progress: ``.<out name>.resume`` beside ``out``."""
    return plan.out.parent / f".{plan.out.name}.resume"


def _checkpoint(plan: SweepPlan, point: GridPoint, team: str) -> Checkpoint:
    """The progress file of one team at one point; its fingerprint names the scene (its
    resolved YAML, hashed), the seed, both teams' specs and files, and the package's source,
    so a point resumes only with the same code and teams."""
    what = json.dumps({"scene": hashlib.sha256(point.scene_id.encode()).hexdigest(), "seed": point.seed,
                       "team": team, "policy": plan.policy, "compare": plan.compare,
                       "files": [files_digest(s) for s in (plan.policy, plan.compare) if s],
                       "code": source_digest()})
    return Checkpoint(resume_folder(plan) / f"point{point.index}_{team}.npz", what)


def _run_points(plan: SweepPlan, prepared: dict, progress: bool) -> list[PointResult]:
    """Evaluate every point in grid order, one compiled evaluator per distinct scene,
    dropped after its last point; a summary line per point as it finishes. Each team's
    evaluation of a point saves its progress as it goes (:class:`Checkpoint`) and resumes
    from what an earlier run saved (:func:`resume_folder`)."""
    last = {p.scene_id: p.index for p in plan.points}
    evaluators, results = {}, []
    bar = tqdm(plan.points, desc="grid points", unit="point")
    for point in bar:
        env, params, policy, other = prepared[point.scene_id]
        t0 = time.perf_counter()
        if point.scene_id not in evaluators:
            evaluators[point.scene_id] = Evaluator(env, params, _team_call(policy, other), plan.batch)
        evaluator = evaluators[point.scene_id]
        key = jax.random.PRNGKey(point.seed)
        if other is None:
            stats = evaluator(key, plan.episodes, None, progress=progress,
                              checkpoint=_checkpoint(plan, point, "policy"))
            base = None
        else:
            stats = evaluator(key, plan.episodes, jnp.bool_(False), progress=progress, desc="episodes",
                              checkpoint=_checkpoint(plan, point, "policy"))
            base = evaluator(key, plan.episodes, jnp.bool_(True), progress=progress, desc="compared team",
                             checkpoint=_checkpoint(plan, point, "compare"))
        if last[point.scene_id] == point.index:
            del evaluators[point.scene_id]
        # a resumed evaluation adds what the earlier runs spent on it
        earlier = sum(r.extra.get("resumed_wall_s", 0.0) for r in (stats, base) if r is not None)
        results.append(PointResult(point, stats, base, time.perf_counter() - t0 + earlier))
        bar.write(point_line(plan, results[-1]))
    bar.close()
    return results


def _team_row(plan: SweepPlan, point: GridPoint, team: str, stats, wall_s: float) -> dict:
    """One row of sweep.csv (module docstring); the difference columns are filled by the caller."""
    k, n = int(np.sum(stats.success)), stats.n
    low, high = wilson_interval(k, n)
    row = {"point": point.index}
    row.update({a.key: a.texts[i] for a, i in zip(plan.axes, point.indices) if a.key != SEED_KEY})
    row.update({SEED_KEY: point.seed, "team": team, "spec": plan.policy if team == "policy" else plan.compare,
                "episodes": n, "successes": k, "success_rate": k / n, "success_low95": low, "success_high95": high,
                "timeout_rate": float(np.mean(stats.timeout))})
    row.update({f"failure_{f}": int(np.sum(stats.failures[f])) for f in FAILURES})
    row.update({"mean_length_steps": float(np.mean(stats.length)), "mean_return": float(np.mean(stats.returns))})
    if plan.compare is not None:
        row.update({"difference": None, "difference_low95": None, "difference_high95": None})
    row["wall_s"] = wall_s
    return row


def sweep_rows(plan: SweepPlan, results: list[PointResult]) -> list[dict]:
    """The rows of sweep.csv: per point the policy's row, then the compared team's; the
    policy's row carries the paired difference policy - compare (same episodes)."""
    rows = []
    for r in results:
        row = _team_row(plan, r.point, "policy", r.stats, r.wall_s)
        rows.append(row)
        if r.base is not None:
            d, low, high = paired_difference_interval(r.stats.success, r.base.success)
            row.update({"difference": d, "difference_low95": low, "difference_high95": high})
            rows.append(_team_row(plan, r.point, "compare", r.base, r.wall_s))
    return rows


def columns(plan: SweepPlan) -> list[str]:
    """sweep.csv's columns: ``point``, each varied scene key, ``seed``, then the outcomes."""
    keys = [a.key for a in plan.axes if a.key != SEED_KEY]
    fixed = [c for c in FIXED_COLUMNS if plan.compare is not None or not c.startswith("difference")]
    return fixed[:1] + keys + fixed[1:]


def point_line(plan: SweepPlan, result: PointResult) -> str:
    """One terminal line: the point, each team's success rate with its interval, and the
    paired difference when two teams flew."""
    def rate(stats, spec):
        k = int(np.sum(stats.success))
        low, high = wilson_interval(k, stats.n)
        return f"'{spec}' {k / stats.n:.1%} (95 % {low:.0%}-{high:.0%})"

    line = (f"[{result.point.index + 1}/{len(plan.points)}] {plan.label(result.point)}: "
            f"{rate(result.stats, plan.policy)}")
    if result.base is not None:
        d, low, high = paired_difference_interval(result.stats.success, result.base.success)
        line += (f" vs {rate(result.base, plan.compare)}: difference {100 * d:+.1f} points "
                 f"(95 % {100 * low:+.1f} to {100 * high:+.1f})")
    return line + f"; {result.wall_s:.1f} s"


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def plot_axis(plan: SweepPlan, rows: list[dict], axis_index: int, path) -> Path:
    """``success_<key>.png``: success rate (Wilson 95 % error bars) against axis
    ``axis_index``'s values (a numeric x axis when they are all numbers, else, and for
    seeds, one category per value, labelled with the value), one line per combination of the other
    axes' values; with a compared team the same colour per combination, solid for the
    policy and dashed for the compared team (shifted a little sideways to keep the bars apart)."""
    axis = plan.axes[axis_index]
    numeric = axis.key != SEED_KEY and all(_is_number(v) for v in axis.values)
    xs = np.asarray(axis.values if numeric else range(len(axis.values)), float)
    span = float(np.ptp(xs)) or 1.0
    by_point = {(r["point"], r["team"]): r for r in rows}
    combos = {}
    for p in plan.points:
        rest = tuple(i for j, i in enumerate(p.indices) if j != axis_index)
        combos.setdefault(rest, {})[p.indices[axis_index]] = p
    teams = [t for t in TEAMS if t == "policy" or plan.compare is not None]
    n_lines = len(combos) * len(teams)
    step = min(0.02, 0.25 / n_lines) * span         # the sideways shift between neighbouring lines
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    colours = plt.get_cmap("tab10")
    for c, (rest, points) in enumerate(combos.items()):
        other_axes = [a for j, a in enumerate(plan.axes) if j != axis_index]
        others = [f"{a.key}={a.texts[i]}" for a, i in zip(other_axes, rest)]
        for t, team in enumerate(teams):
            order = sorted(points)
            r = [by_point[(points[i].index, team)] for i in order]
            y = np.array([row["success_rate"] for row in r])
            err = np.array([[row["success_rate"] - row["success_low95"] for row in r],
                            [row["success_high95"] - row["success_rate"] for row in r]])
            shift = step * (c * len(teams) + t - (n_lines - 1) / 2)
            spec = plan.policy if team == "policy" else plan.compare
            ax.errorbar(xs[order] + shift, y, yerr=err, color=colours(c % 10), ls="-" if team == "policy" else "--",
                        marker="o", capsize=3, label=", ".join(others + [f"{team} '{spec}'"]))
    if not numeric:
        ax.set_xticks(xs, [t if len(t) <= 24 else t[:22] + "..." for t in axis.texts], rotation=15)
    ax.set_xlabel(axis.key)
    ax.set_ylabel("success rate (95 % Wilson interval)")
    ax.set_ylim(-0.03, 1.03)
    ax.set_title(f"{plan.points[0].config.name}: {plan.episodes} episodes per point", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_name(key: str) -> str:
    """The file name of an axis's plot: ``success_<key, dots replaced by _>.png``."""
    return f"success_{key.replace('.', '_')}.png"


def write_sweep(plan: SweepPlan, rows: list[dict], record: dict) -> dict:
    """Write sweep.csv, sweep.json (``record`` with the rows and the plots' names) and
    one plot per axis into ``plan.out``, all or none; returns the JSON record."""
    with staged_output(plan.out) as tmp:
        with (tmp / "sweep.csv").open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=columns(plan))
            writer.writeheader()
            writer.writerows(rows)
        plots = [plot_axis(plan, rows, j, tmp / plot_name(a.key)).name for j, a in enumerate(plan.axes)]
        record = {**record, "plots": plots, "rows": rows}
        (tmp / "sweep.json").write_text(json.dumps(record, indent=2, default=str))
    return record


def run_sweep(plan: SweepPlan, make_policy, *, progress: bool = True, command: str = "",
              extra: dict | None = None) -> dict:
    """Make every distinct scene's environment and both teams (``make_policy(env, params,
    spec, flag) -> policy``, raising ValueError for a team that cannot fly there), then
    evaluate every point and write the outputs (module docstring). ``progress``: the
    per-point episode bars (the bar over points is always shown). Returns sweep.json's
    record. SweepError (before anything compiles) when a point cannot be evaluated."""
    t0 = time.perf_counter()
    source_digest()                     # the source this process runs, read before anything compiles
    prepared = _prepare(plan, make_policy)
    if plan.env_note:
        print(plan.env_note, file=sys.stderr)
    results = _run_points(plan, prepared, progress)
    rows = sweep_rows(plan, results)
    record = {
        "command": command,
        "scene": plan.scene,
        "scene_name": plan.points[0].config.name,
        "sets": list(plan.sets),
        "env_block": "defaults" if plan.env_note else "file",
        "axes": [{"key": a.key, "values": list(a.texts), "parsed": list(a.values)} for a in plan.axes],
        "seeds": sorted({p.seed for p in plan.points}),
        "episodes": plan.episodes,
        "batch": plan.batch,
        "policy": plan.policy,
        "compare": plan.compare,
        "same_episodes": "episode i of every point with seed S is drawn from jax.random.PRNGKey(S) as "
                         "scripts/evaluate.py draws it, for both teams",
        "points": [{"point": p.index, "overrides": list(p.overrides), "seed": p.seed} for p in plan.points],
        "wall_s": time.perf_counter() - t0,
        "machine": machine(),
        **(extra or {}),
    }
    record = write_sweep(plan, rows, record)
    shutil.rmtree(resume_folder(plan), ignore_errors=True)
    return record
