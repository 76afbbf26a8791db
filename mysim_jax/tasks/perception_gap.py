"""The perception gap: a team's capture success on true states minus on perceived states.

Two steps, both on files the other scripts write:

* :func:`perception_block` turns measured estimation errors (the ``error_model`` of
  ``scripts/perceive.py``'s ``metrics.json``: a first-order Gauss-Markov fit of each
  estimate's unaligned error) into an ``env.perception`` block
  (:class:`mysim_jax.config.env.PerceptionConfig`): the UAVs' position and velocity
  errors from their visual-inertial odometry, the target's from the team's fused
  localisation. Several UAVs' fits combine into one (``sigma``: the RMS over UAVs;
  correlation time: their mean).
* :func:`compare_evaluations` reads two ``scripts/evaluate.py`` folders, one on true states
  and one with ``--perception``, checks that they ran the same episodes (same scene, policy,
  seed and episode count: episode ``i`` is drawn from its own key in both,
  :mod:`mysim_jax.tasks.evaluate`, whatever ``--batch``), pairs them by episode number, and returns both
  success rates with 95 % Wilson intervals and their paired difference with Newcombe's
  interval (:func:`mysim_jax.tasks.sweep.paired_difference_interval`).

NumPy only; no JAX.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from mysim_jax.core.config_base import ConfigError, read_text_file, read_yaml_file
from mysim_jax.tasks.sweep import paired_difference_interval, wilson_interval

_FIELDS = {"position_m": "position", "velocity_m_s": "velocity"}


class GapError(ValueError):
    """The inputs cannot be compared or combined; the message says why and how to fix it."""


def read_error_model(path, key: str = "error_model") -> dict:
    """The ``key`` block of a ``scripts/perceive.py`` ``metrics.json``. Raises
    :class:`~mysim_jax.core.config_base.ConfigError` naming the file when it cannot be read,
    :class:`GapError` when it is not JSON or has no such block."""
    text = read_text_file(path, "file (a perceive.py metrics.json)")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise GapError(f"{path}: not JSON: {err}") from None
    model = data.get(key) if isinstance(data, dict) else None
    if not isinstance(model, dict):
        raise GapError(f"{path}: no '{key}' block (write it with scripts/perceive.py)")
    return model


def read_perception_block(path) -> dict:
    """The ``env.perception`` mapping in the YAML file ``path`` (``scripts/perception_gap.py
    fit`` writes one), for ``scripts/evaluate.py --perception``. Raises
    :class:`~mysim_jax.core.config_base.ConfigError` naming the file; the block's fields are
    checked where the scene takes it (:class:`mysim_jax.config.env.PerceptionConfig`)."""
    block = read_yaml_file(path, "file (--perception)")
    if not isinstance(block, dict):
        raise ConfigError(f"--perception {path}: expected a mapping of uav_position, uav_velocity, target_position, "
                          "target_velocity to {sigma, correlation_time}")
    return block


def _combine(fits: list[dict], what: str) -> dict:
    pooled = []
    for i, fit in enumerate(fits):
        try:
            pooled.append(fit["pooled"])
            float(fit["pooled"]["sigma"]), float(fit["pooled"]["correlation_time_s"])
        except (KeyError, TypeError, ValueError):
            raise GapError(f"{what} #{i}: not a gauss_markov_fit result (needs pooled.sigma and "
                           "pooled.correlation_time_s)") from None
    sigma = math.sqrt(float(np.mean([p["sigma"] ** 2 for p in pooled])))
    taus = [p["correlation_time_s"] for p in pooled]
    if not all(math.isfinite(t) for t in taus):
        raise GapError(f"{what}: an error with an infinite correlation time (a constant offset) cannot be "
                       "replayed as a Gauss-Markov process; fit a longer run")
    return {"sigma": sigma, "correlation_time": float(np.mean(taus))}


def perception_block(uav_models: list[dict], target_model: dict) -> dict:
    """The ``env.perception`` block of measured error models.

    ``uav_models``: the ``error_model`` dicts of ``scripts/perceive.py`` VIO runs (one per
    UAV), each with ``position_m`` and ``velocity_m_s`` fits; ``target_model``: the same
    two fits of the team's fused target estimate."""
    if not uav_models:
        raise GapError("perception_block: no UAV error model given")
    block = {}
    for who, models in (("uav", uav_models), ("target", [target_model])):
        for key, name in _FIELDS.items():
            fits = []
            for i, m in enumerate(models):
                if not isinstance(m, dict) or key not in m:
                    raise GapError(f"{who} error model #{i}: no '{key}' fit (the error_model block of "
                                   "scripts/perceive.py's metrics.json)")
                fits.append(m[key])
            block[f"{who}_{name}"] = _combine(fits, f"{who} {name}")
    return block


def _read(folder: Path) -> tuple[dict, dict[int, bool]]:
    metrics_path, episodes_path = folder / "metrics.json", folder / "episodes.csv"
    for path in (metrics_path, episodes_path):
        if not path.is_file():
            raise GapError(f"{folder}: no {path.name}; pass folders written by scripts/evaluate.py")
    metrics = json.loads(metrics_path.read_text())
    success = {}
    with episodes_path.open() as f:
        for row in csv.DictReader(f):
            success[int(float(row["episode"]))] = bool(int(float(row["success"])))
    return metrics, success


def compare_evaluations(true_dir, perceived_dir) -> dict:
    """Success on true states, on perceived states, and the paired gap (module docstring)."""
    (m_true, s_true), (m_perc, s_perc) = _read(Path(true_dir)), _read(Path(perceived_dir))
    for key in ("scene", "policy", "episodes", "seed"):
        if m_true.get(key) != m_perc.get(key):
            raise GapError(f"the two evaluations differ in {key} ({m_true.get(key)!r} and {m_perc.get(key)!r}): "
                           "run both with the same scene, policy, --episodes and --seed")
    if m_true.get("perception") is not None:
        raise GapError(f"{true_dir}: evaluated with --perception; the first folder must be on true states")
    if m_perc.get("perception") is None:
        raise GapError(f"{perceived_dir}: evaluated on true states; the second folder must use --perception")
    episodes = sorted(s_true)
    if sorted(s_perc) != episodes:
        raise GapError("the two evaluations' episodes.csv hold different episodes")
    a = np.array([s_true[i] for i in episodes])
    b = np.array([s_perc[i] for i in episodes])
    n = len(episodes)
    d, lo, hi = paired_difference_interval(a, b)

    def rate(x):
        k = int(x.sum())
        return {"count": k, "rate": k / n, "interval95": list(wilson_interval(k, n))}

    return {
        "scene": m_true["scene"], "policy": m_true["policy"], "episodes": n, "seed": m_true["seed"],
        "perception": m_perc["perception"],
        "true_states": rate(a), "perceived_states": rate(b),
        "gap": {"points": 100 * d, "interval95_points": [100 * lo, 100 * hi],
                "method": "paired difference, Newcombe's hybrid score interval",
                "caught_only_on_true": int(np.sum(a & ~b)), "caught_only_on_perceived": int(np.sum(~a & b))},
    }
