"""PNG plots of trajectories (the paper's position / velocity / acceleration figures)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

_QUANTITIES = (("", "position", "m"), ("v", "velocity", "m/s"), ("a", "acceleration", "m/s²"))
# A panel's y-range spans at least this fraction of the largest range of the three axes:
# an axis that only carries round-off (1e-12 m beside 0.5 m) shows as a flat line instead
# of being auto-scaled into noise that looks like motion.
_MIN_RELATIVE_SPAN = 1e-3


def plot_kinematics(columns: dict[str, np.ndarray], name: str, out_dir: str | Path,
                    reference: dict[str, np.ndarray] | None = None, ref_label: str = "reference") -> list[Path]:
    """Write ``NAME_position.png``, ``NAME_velocity.png``, ``NAME_acceleration.png``.

    Each figure has one panel per axis (x, y, z) against time. ``reference`` (same column
    names) is drawn dashed on top when given.
    """
    out_dir = Path(out_dir)
    t = columns["time"]
    written = []
    for key, label, unit in _QUANTITIES:
        fig, axes = plt.subplots(3, 1, figsize=(7, 6.5), sharex=True)
        spans = [np.ptp(columns[f"{name}_{key}{axis}"]) for axis in "xyz"]
        min_span = _MIN_RELATIVE_SPAN * max(max(spans), 1e-12)
        for ax, axis in zip(axes, "xyz"):
            col = f"{name}_{key}{axis}"
            ax.plot(t, columns[col], lw=1.2, label="mysim_jax")
            if reference is not None and col in reference:
                ax.plot(reference["time"], reference[col], "--", lw=1.0, label=ref_label)
            ax.set_ylabel(f"{axis} [{unit}]")
            ax.grid(alpha=0.3)
            low, high = ax.get_ylim()
            if high - low < min_span:
                mid = 0.5 * (low + high)
                ax.set_ylim(mid - 0.5 * min_span, mid + 0.5 * min_span)
        axes[0].set_title(f"{name}: {label}")
        axes[-1].set_xlabel("time [s]")
        if reference is not None:
            axes[0].legend(loc="best", fontsize=8)
        fig.tight_layout()
        path = out_dir / f"{name}_{label}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written


def plot_path(columns: dict[str, np.ndarray], name: str, out_dir: str | Path) -> Path:
    """Write ``NAME_path.png``: reference (dashed) against actual path, top view (x-y) and
    side view (x-z), and the position error against time. Needs ``NAME_ref_x/y/z``."""
    out_dir = Path(out_dir)
    t = columns["time"]
    pos = np.stack([columns[f"{name}_{a}"] for a in "xyz"], axis=-1)
    ref = np.stack([columns[f"{name}_ref_{a}"] for a in "xyz"], axis=-1)
    err = np.linalg.norm(pos - ref, axis=-1)
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    for ax, (i, j), title in zip(axes[:2], ((0, 1), (0, 2)), ("top view", "side view")):
        ax.plot(ref[:, i], ref[:, j], "--", lw=1.2, color="0.4", label="reference")
        ax.plot(pos[:, i], pos[:, j], lw=1.2, label="actual")
        ax.plot(pos[0, i], pos[0, j], "o", ms=4, color="C0")
        ax.set_xlabel(f"{'xyz'[i]} [m]")
        ax.set_ylabel(f"{'xyz'[j]} [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(f"{name}: {title}")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    axes[2].plot(t, err * 1e3, lw=1.0)
    axes[2].set_xlabel("time [s]")
    axes[2].set_ylabel("|position error| [mm]")
    rms = float(np.sqrt(np.mean(err ** 2)))
    axes[2].set_title(f"RMS {rms * 1e3:.3g} mm, max {err.max() * 1e3:.3g} mm")
    axes[2].grid(alpha=0.3)
    fig.tight_layout()
    path = out_dir / f"{name}_path.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
