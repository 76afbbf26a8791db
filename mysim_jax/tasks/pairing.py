"""Teams compared on the same episodes after the fact: the outcomes kept in
``scripts/evaluate.py`` folders, paired episode by episode.

An evaluation draws episode ``i`` from its own key (:mod:`mysim_jax.tasks.evaluate`), so two
evaluations of one scene with the same ``--seed`` and ``--episodes`` fly the same episodes
whatever team, ``--batch`` or ``--perception`` they used. :func:`pair_outcomes` reads such
folders and pairs the first with each of the others: both success rates with their 95 %
Wilson intervals and the paired difference with Newcombe's interval
(:func:`mysim_jax.tasks.sweep.paired_difference_interval`). A new team is then judged
against teams already flown without flying them again.

A folder is named as ``DIR`` (the team of its ``--policy``) or ``DIR:compare`` (the team of
its ``--compare``, read from ``comparison_episodes.csv``). The folders must agree in what
draws the episodes: the scene's name, the seed, the episode count, the policy period and
episode length, and the scene's ``env:`` block as it ran (the folder's ``config.yaml``) apart
from what changes what a team sees or how its actions are flown, not what is drawn
(:data:`SEEN_NOT_DRAWN`: ``perception``, ``observe_top_thrust``, ``fault_failsafe``). What else differs (the
policy, ``--set`` overrides such as the controller's allocation, ``--perception``) is what
is being compared, and the result lists it per folder.

NumPy only; no JAX.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from mysim_jax.tasks.sweep import paired_difference_interval, wilson_interval

# what draws the episodes: the folders must agree on these metrics.json entries
SAME_EPISODES = ("scene", "seed", "episodes", "policy_dt", "max_steps")
# env: keys that change what a team observes or how its actions are flown, not the episodes' draws
SEEN_NOT_DRAWN = ("perception", "observe_top_thrust", "fault_failsafe")


class PairingError(ValueError):
    """The folders cannot be paired; the message says why and how to fix it."""


@dataclass(frozen=True)
class TeamOutcomes:
    """One team's outcomes on an evaluation's episodes."""

    label: str              # the folder as given (``DIR`` or ``DIR:compare``)
    team: str               # the policy that flew (metrics.json's ``policy`` or ``compare``)
    metrics: dict           # the folder's metrics.json
    env: dict               # the scene's env: block as it ran, without SEEN_NOT_DRAWN
    success: np.ndarray     # (episodes,) bool, episode i at index i


def read_outcomes(spec: str | Path) -> TeamOutcomes:
    """The outcomes of the team ``spec`` names (module docstring)."""
    spec = str(spec)
    folder, side = (spec[: -len(":compare")], "compare") if spec.endswith(":compare") else (spec, "policy")
    folder = Path(folder)
    metrics_path = folder / "metrics.json"
    if not metrics_path.is_file():
        raise PairingError(f"{folder}: no metrics.json; pass folders written by scripts/evaluate.py")
    metrics = json.loads(metrics_path.read_text())
    config_path = folder / "config.yaml"
    if not config_path.is_file():
        raise PairingError(f"{folder}: no config.yaml; pass folders written by scripts/evaluate.py")
    env = (yaml.safe_load(config_path.read_text()) or {}).get("env") or {}
    if side == "policy":
        path, column, team = folder / "episodes.csv", "success", str(metrics.get("policy"))
    else:
        path, column = folder / "comparison_episodes.csv", "outcome_compare"
        if not path.is_file():
            raise PairingError(f"{folder}: no comparison_episodes.csv; ':compare' needs a folder evaluated "
                               "with scripts/evaluate.py --compare")
        if not (folder / "comparison.json").is_file():
            raise PairingError(f"{folder}: no comparison.json; pass folders written by scripts/evaluate.py --compare")
        team = str(json.loads((folder / "comparison.json").read_text()).get("compare"))
    if not path.is_file():
        raise PairingError(f"{folder}: no {path.name}; pass folders written by scripts/evaluate.py")
    outcomes: dict[int, bool] = {}
    with path.open() as f:
        for row in csv.DictReader(f):
            value = row[column]
            outcomes[int(float(row["episode"]))] = (value == "success") if side == "compare" else bool(int(float(value)))
    episodes = sorted(outcomes)
    if episodes != list(range(len(episodes))):
        raise PairingError(f"{path}: episodes are not 0 .. n-1; the file is not one evaluation's")
    return TeamOutcomes(spec, team, metrics, {k: v for k, v in env.items() if k not in SEEN_NOT_DRAWN},
                        np.array([outcomes[i] for i in episodes], bool))


def _episode_key(team: TeamOutcomes) -> dict:
    return {**{k: team.metrics.get(k) for k in SAME_EPISODES}, "env": team.env}


def _rate(success: np.ndarray) -> dict:
    k, n = int(success.sum()), len(success)
    return {"count": k, "rate": k / n, "interval95": list(wilson_interval(k, n))}


def pair_outcomes(specs: list[str | Path]) -> dict:
    """The first team of ``specs`` paired with each of the others (module docstring)."""
    if len(specs) < 2:
        raise PairingError("pairing needs at least two evaluation folders")
    teams = [read_outcomes(s) for s in specs]
    first = teams[0]
    ref = _episode_key(first)
    for t in teams[1:]:
        other = _episode_key(t)
        for k in ref:
            if ref[k] != other[k]:
                if k == "env":
                    keys = sorted(set(ref[k]) | set(other[k]))
                    shown = " (" + ", ".join(f"env.{e}" for e in keys if ref[k].get(e) != other[k].get(e)) + ")"
                else:
                    shown = f" ({ref[k]!r} and {other[k]!r})"
                raise PairingError(f"{first.label} and {t.label} differ in {k}{shown}: "
                                   "their episodes are not the same; evaluate both on one scene with the same "
                                   "--seed and --episodes")
    rows = []
    for t in teams:
        row = {"folder": t.label, "team": t.team, "overrides": t.metrics.get("overrides") or [],
               "perception": t.metrics.get("perception") is not None, "success": _rate(t.success)}
        if t is not first:
            d, lo, hi = paired_difference_interval(first.success, t.success)
            row["difference_first_minus_this"] = {
                "points": 100 * d, "interval95_points": [100 * lo, 100 * hi],
                "only_first": int(np.sum(first.success & ~t.success)),
                "only_this": int(np.sum(t.success & ~first.success))}
        rows.append(row)
    return {"scene": ref["scene"], "seed": ref["seed"], "episodes": ref["episodes"],
            "method": "paired difference by episode, Newcombe's hybrid score interval", "teams": rows}


def pairing_table(result: dict) -> str:
    """A Markdown table of :func:`pair_outcomes`' result."""
    lines = ["| folder | team | success (95 %) | first − this [points] (95 %) | caught by the first only / this only |",
             "|---|---|---:|---:|---:|"]
    for row in result["teams"]:
        s = row["success"]
        rate = f"{100 * s['rate']:.1f} % ({100 * s['interval95'][0]:.1f}–{100 * s['interval95'][1]:.1f})"
        d = row.get("difference_first_minus_this")
        diff = (f"{d['points']:+.1f} ({d['interval95_points'][0]:+.1f} to {d['interval95_points'][1]:+.1f})"
                if d else "–")
        only = f"{d['only_first']} / {d['only_this']}" if d else "–"
        lines.append(f"| {row['folder']} | {row['team']} | {rate} | {diff} | {only} |")
    return "\n".join(lines)
