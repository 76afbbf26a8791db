"""PNG plots of trajectories (the paper's position / velocity / acceleration figures)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

_QUANTITIES = (("", "position", "m"), ("v", "velocity", "m/s"), ("a", "acceleration", "m/s²"))


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
        for ax, axis in zip(axes, "xyz"):
            col = f"{name}_{key}{axis}"
            ax.plot(t, columns[col], lw=1.2, label="mysim_jax")
            if reference is not None and col in reference:
                ax.plot(reference["time"], reference[col], "--", lw=1.0, label=ref_label)
            ax.set_ylabel(f"{axis} [{unit}]")
            ax.grid(alpha=0.3)
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
