"""Outputs of an evaluation of a capture team (``scripts/evaluate.py``): the per-episode
table and the figures, from an :class:`~mysim_jax.tasks.evaluate.EpisodeStats` (NumPy and
matplotlib only).

* ``outcomes.png`` — success, every failure and timeout rate, with 95 % Wilson intervals;
* ``reward_terms.png`` — mean episode sum of every weighted reward term (±1 s.d. over episodes);
* ``lengths.png`` — histogram of episode lengths, stacked by outcome;
* ``returns.png`` — every episode's return against its length, coloured by outcome;
* ``episode_rewards.png`` — the recorded episode's cumulative weighted terms over time
  (from :func:`~mysim_jax.tasks.episode.step_columns`).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from mysim_jax.config.env import FAILURES, REWARD_TERMS  # noqa: E402

SUCCESS_COLOR, FAILURE_COLOR, TIMEOUT_COLOR = "tab:green", "tab:red", "0.55"


def outcome_labels(stats) -> np.ndarray:
    """Per episode: ``success``, its first failure (FAILURES order), or ``timeout``."""
    labels = np.full(stats.n, "timeout", dtype=object)
    for f in reversed(FAILURES):
        labels[stats.failures[f]] = f
    labels[stats.success] = "success"
    return labels


def episode_columns(stats, policy_dt: float) -> dict[str, np.ndarray]:
    """The ``episodes.csv`` columns, one row per episode (flags 0 / 1): ``episode``,
    ``slot``, ``success``, ``failure_NAME`` for every failure, ``timeout``,
    ``length_steps``, ``length_s``, ``return`` (mean over agents) and ``term_NAME``
    (episode sum of the weighted term, mean over agents) for every reward term."""
    columns = {"episode": np.arange(stats.n), "slot": stats.slot, "success": stats.success.astype(int)}
    columns.update({f"failure_{f}": stats.failures[f].astype(int) for f in FAILURES})
    columns.update({"timeout": stats.timeout.astype(int), "length_steps": stats.length,
                    "length_s": stats.length * policy_dt, "return": stats.returns})
    columns.update({f"term_{t}": stats.terms[t] for t in REWARD_TERMS})
    return columns


def _save(fig, path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_outcomes(stats, path, title: str = "") -> Path:
    """Bars of the success, failure and timeout rates with their 95 % Wilson intervals."""
    summary = stats.summary()
    rows = [("success", summary["success"], SUCCESS_COLOR)]
    rows += [(f.replace("_", " "), summary["failures"][f], FAILURE_COLOR) for f in FAILURES]
    rows.append(("timeout", summary["timeout"], TIMEOUT_COLOR))
    rates = np.array([r["rate"] for _, r, _ in rows])
    lo = np.array([r["interval95"][0] for _, r, _ in rows])
    hi = np.array([r["interval95"][1] for _, r, _ in rows])
    fig, ax = plt.subplots(figsize=(8, 4.2))
    x = np.arange(len(rows))
    ax.bar(x, rates, color=[c for _, _, c in rows], alpha=0.85)
    ax.errorbar(x, rates, yerr=np.stack([rates - lo, hi - rates]), fmt="none", ecolor="k", capsize=4, lw=1)
    for xi, (_, r, _) in zip(x, rows):
        ax.text(xi, min(r["interval95"][1] + 0.02, 1.02), f"{r['count']}/{stats.n}", ha="center", va="bottom",
                fontsize=8)
    ax.set_xticks(x, [name for name, _, _ in rows], rotation=30, ha="right")
    ax.set_ylim(0.0, 1.1)
    ax.set_ylabel("rate")
    ax.set_title(f"{title}: outcomes of {stats.n} episodes (bars: 95 % Wilson interval)".lstrip(": "))
    ax.grid(True, axis="y", alpha=0.3)
    return _save(fig, path)


def plot_reward_terms(stats, path, title: str = "") -> Path:
    """Mean episode sum of every weighted reward term (mean over agents), ±1 s.d. over episodes."""
    means = np.array([np.mean(stats.terms[t]) for t in REWARD_TERMS])
    spread = np.array([np.std(stats.terms[t]) for t in REWARD_TERMS])
    fig, ax = plt.subplots(figsize=(7, 4.2))
    y = np.arange(len(REWARD_TERMS))
    ax.barh(y, means, xerr=spread, color=[SUCCESS_COLOR if m > 0 else FAILURE_COLOR for m in means], alpha=0.85,
            error_kw={"ecolor": "k", "capsize": 3, "lw": 1})
    ax.axvline(0.0, color="k", lw=0.8)
    ax.set_yticks(y, REWARD_TERMS)
    ax.invert_yaxis()
    ax.set_xlabel("episode sum of the weighted term (mean over agents)")
    ax.set_title(f"{title}: reward terms, mean return {np.mean(stats.returns):.3g}".lstrip(": "))
    ax.grid(True, axis="x", alpha=0.3)
    return _save(fig, path)


def _groups(stats):
    labels = outcome_labels(stats)
    failed = ~np.isin(labels, ["success", "timeout"])
    return [("success", labels == "success", SUCCESS_COLOR), ("failure", failed, FAILURE_COLOR),
            ("timeout", labels == "timeout", TIMEOUT_COLOR)]


def plot_lengths(stats, path, policy_dt: float, title: str = "") -> Path:
    """Histogram of episode lengths [s], stacked by outcome (success, any failure, timeout)."""
    seconds = stats.length * policy_dt
    groups = [(name, seconds[mask], color) for name, mask, color in _groups(stats)]
    hi = max(float(seconds.max()), policy_dt)
    bins = np.linspace(0.0, hi + policy_dt, min(30, int(round(hi / policy_dt)) + 1) + 1)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.hist([g[1] for g in groups], bins=bins, stacked=True, color=[g[2] for g in groups],
            label=[f"{g[0]} ({len(g[1])})" for g in groups])
    ax.set_xlabel("episode length [s]")
    ax.set_ylabel("episodes")
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_title(f"{title}: episode lengths".lstrip(": "))
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)
    return _save(fig, path)


def plot_returns(stats, path, policy_dt: float, title: str = "") -> Path:
    """Every episode's return (mean over agents) against its length, coloured by outcome."""
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, mask, color in _groups(stats):
        if mask.any():
            ax.scatter(stats.length[mask] * policy_dt, stats.returns[mask], s=14, color=color, alpha=0.7,
                       label=f"{name} ({mask.sum()})")
    ax.set_xlabel("episode length [s]")
    ax.set_ylabel("return (mean over agents)")
    ax.set_title(f"{title}: return against length".lstrip(": "))
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    return _save(fig, path)


def plot_episode_rewards(steps, path, title: str = "") -> Path:
    """Cumulative weighted terms (mean over agents) of one recorded episode, with the
    steps after which the target was held shaded; ``steps`` from :func:`~mysim_jax.tasks.episode.step_columns`."""
    time = np.concatenate([[0.0], np.asarray(steps["time"], float)])
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    held = np.asarray(steps["target_held"], bool)
    for t0, t1 in zip(time[:-1][held], time[1:][held]):
        ax.axvspan(t0, t1, color="gold", alpha=0.25, lw=0)
    total = np.zeros(len(time))
    for k, t in enumerate(REWARD_TERMS):
        values = np.concatenate([[0.0], np.asarray(steps[f"term_{t}"], float)])
        total += values
        if np.any(values != 0.0):
            ax.plot(time, np.cumsum(values), lw=1.2, label=t, color=plt.cm.tab10(k % 10))
    ax.plot(time, np.cumsum(total), "k", lw=2, label="return")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("cumulative reward (mean over agents)")
    ax.set_title(f"{title}: recorded episode, cumulative reward terms (shaded: target held)".lstrip(": "))
    ax.legend(fontsize=8, ncol=2)
    ax.grid(True, alpha=0.3)
    return _save(fig, path)


def evaluation_plots(stats, out_dir, policy_dt: float, title: str = "") -> list[Path]:
    """Write ``outcomes.png``, ``reward_terms.png``, ``lengths.png`` and ``returns.png``."""
    out_dir = Path(out_dir)
    return [plot_outcomes(stats, out_dir / "outcomes.png", title),
            plot_reward_terms(stats, out_dir / "reward_terms.png", title),
            plot_lengths(stats, out_dir / "lengths.png", policy_dt, title),
            plot_returns(stats, out_dir / "returns.png", policy_dt, title)]
