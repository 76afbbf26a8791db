"""Learning curves of training runs, from their ``metrics.csv`` rows (dicts of strings, as
:func:`mysim_jax.mappo.run_files.read_metrics` reads them)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def column(rows: list[dict], key: str):
    def value(r):
        v = r.get(key, "")
        return float(v) if v not in ("", None) else np.nan

    return np.array([value(r) for r in rows])


def plot_curves(rows: list[dict], path: Path, title: str, best_iteration: int | None = None,
                time_guard: tuple[int, int] | None = None) -> Path | None:
    """Learning curves of ``metrics.csv`` rows: return, success rate (training episodes, and
    the deterministic policy on the selection episodes with the selected iteration
    marked), episode length, losses, entropy. ``time_guard`` = ``(iteration, planned)``
    when ``run.time_limit_min`` stopped the run before its step budget: the title says so
    and every panel marks where.

    Return, success and length are per episode: iterations in which no episode ended leave a
    gap rather than a zero.
    """
    if not rows:
        return None

    x = column(rows, "env_steps")
    panels = [("mean_return", "mean episode return"), ("success_rate", "success rate"),
              ("mean_length", "mean episode length [team steps]"), ("value_loss", "value loss"),
              ("policy_loss", "policy loss"), ("entropy", "policy entropy")]
    per_episode = {"mean_return", "success_rate", "mean_length"}
    episodes = column(rows, "episodes")
    ended = ~(episodes <= 0)
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5))
    for ax, (key, label) in zip(axes.ravel(), panels):
        y = column(rows, key)
        if key in per_episode:
            y = np.where(ended, y, np.nan)
        keep = np.isfinite(y)
        ax.plot(x[keep], y[keep], lw=1.2, marker="." if key in per_episode else None, ms=2,
                label="training episodes (exploring)" if key == "success_rate" else None)
        if key == "success_rate":
            sel = column(rows, "select_success")
            has = np.isfinite(sel)
            if has.any():
                ax.plot(x[has], sel[has], "o-", ms=4, lw=1.0, color="tab:green",
                        label="deterministic policy, selection episodes")
                if best_iteration is not None:
                    its = column(rows, "iteration")
                    at = np.flatnonzero(its == best_iteration)
                    if at.size:
                        ax.axvline(x[at[0]], color="tab:red", ls="--", lw=1.0,
                                   label=f"selected policy (iteration {best_iteration})")
            frac = column(rows, "curriculum_fraction")
            if np.isfinite(frac).any():
                has = np.isfinite(frac)
                ax.step(x[has], frac[has], where="post", color="tab:purple", lw=1.0,
                        label="curriculum: fraction of the target's full speed / jink / flee ranges")
            ax.set_ylim(-0.02, 1.02)
        if time_guard is not None:
            its = column(rows, "iteration")
            at = np.flatnonzero(its == time_guard[0])
            if at.size:
                ax.axvline(x[at[0]], color="black", ls=":", lw=1.2,
                           label="stopped by run.time_limit_min" if key == "success_rate" else None)
        if key == "success_rate":
            ax.legend(fontsize=7, loc="lower right")
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("team steps")
        ax.grid(alpha=0.3)
    if time_guard is not None:
        title = (f"{title}\nstopped by the time guard (run.time_limit_min) after iteration {time_guard[0]} of "
                 f"{time_guard[1]}: not the step budget")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_runs(runs: dict[str, list[dict]], path: Path, title: str) -> Path | None:
    """Several runs' ``metrics.csv`` rows side by side: the deterministic policy's success
    on the selection episodes (where the run had model selection) and the training
    episodes' success (exploration on), one colour per run, against the run's wall time
    (top row) and against the team steps it has simulated (bottom row): runs whose team
    steps cost differently (another algorithm, level or machine) compare on both."""
    if not runs:
        return None

    fig, axes = plt.subplots(2, 2, figsize=(12, 8), sharey=True)
    palette = plt.get_cmap("tab10" if len(runs) <= 10 else "tab20")
    styles = ("-", "--", ":")                 # past the palette's colours, the next line style
    handles = []
    for i, (name, rows) in enumerate(runs.items()):
        colour, ls = palette(i % palette.N), styles[(i // palette.N) % len(styles)]
        sel = column(rows, "select_success")
        has = np.isfinite(sel)
        train = np.where(column(rows, "episodes") > 0, column(rows, "success_rate"), np.nan)
        keep = np.isfinite(train)
        for row, x in ((axes[0], column(rows, "wall_s") / 60.0), (axes[1], column(rows, "env_steps"))):
            if has.any():
                row[0].plot(x[has], sel[has], "o", ls=ls, ms=4, lw=1.2, color=colour)
            row[1].plot(x[keep], train[keep], ls=ls, lw=1.0, color=colour)
        handles.append(plt.Line2D([], [], color=colour, ls=ls, lw=1.5, label=name))
    for row, xlabel in ((axes[0], "wall time of the run [min] (cloning, training, selection)"),
                        (axes[1], "team steps simulated in training")):
        row[0].set_title("deterministic policy, selection episodes", fontsize=10)
        row[1].set_title("training episodes (exploring)", fontsize=10)
        row[0].set_ylabel("success rate")
        for ax in row:
            ax.set_xlabel(xlabel)
            ax.set_ylim(-0.02, 1.02)
            ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    # one legend for the four panels, beside them
    fig.legend(handles=handles, loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=8, frameon=False)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
