"""Plots and an animation of a capture run (paper Figs. results_capture_passive (c)-(d),
results_capture_active (c)), drawn from the trajectory columns of :mod:`mysim_jax.io.trajectory`.

* ``capture_top.png`` — top view (x-y) of the UAV and target paths, with the net at the end;
* ``capture_side.png`` — side view (x-z) of the same;
* ``capture_distances.png`` — distance of every UAV to the target over time;
* ``capture_tensions.png`` — tension in every tether (at its knot) over time;
* ``capture.gif`` — the capture seen from the top and from the side (at most
  ``max_frames`` frames).

:func:`capture_report` writes all of them and returns the verdict and summary numbers
that ``scripts/simulate.py`` puts in ``metrics.json`` under ``capture``.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FuncAnimation, PillowWriter  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from mysim_jax.tasks.outcome import capture_outcome, tether_tensions, thrust_fraction, uav_target_distances

COLORS = plt.rcParams["axes.prop_cycle"].by_key()["color"]


def _xyz(columns, name):
    return np.stack([columns[f"{name}_{a}"] for a in "xyz"], axis=-1)


def net_lines(columns, config):
    """Polylines ``[(n_out, n_i, 3), ...]`` of every net edge and tether, through its masses."""
    net = config.net
    lines = [np.stack([_xyz(columns, n) for n in names], axis=1) for names in net.edge_chains()]
    if net.tethers is not None:
        for n, (uav, knot) in enumerate(zip(net.tethers.uavs, net.tether_knots())):
            names = [net.knot_name(*knot)] + [f"{net.name}_t{n}_{m}" for m in range(net.tethers.n_masses)] + [uav]
            lines.append(np.stack([_xyz(columns, x) for x in names], axis=1))
    return lines


def _view(ax, columns, config, axes, row, lines):
    a, b = axes
    for k, q in enumerate(config.quadrotors):
        p = _xyz(columns, q.body)
        ax.plot(p[:, a], p[:, b], color=COLORS[k % len(COLORS)], lw=1.2, label=q.body)
        ax.plot(p[row, a], p[row, b], "o", color=COLORS[k % len(COLORS)], ms=5)
    t = _xyz(columns, config.target.name)
    ax.plot(t[:, a], t[:, b], "k--", lw=1.2, label=config.target.name)
    ax.plot(t[row, a], t[row, b], "ko", ms=6)
    for line in lines:
        ax.plot(line[row, :, a], line[row, :, b], color="0.6", lw=0.6)
    ax.set_xlabel("xyz"[a] + " [m]")
    ax.set_ylabel("xyz"[b] + " [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)


def plot_capture(columns, config, out_dir, tensions=None, distances=None) -> list[Path]:
    """Write the four capture figures into ``out_dir``; returns their paths."""
    out_dir = Path(out_dir)
    lines = net_lines(columns, config)
    time = columns["time"]
    paths = []
    for name, axes, title in (("capture_top.png", (0, 1), "top view (net at the end)"),
                              ("capture_side.png", (0, 2), "side view (net at the end)")):
        fig, ax = plt.subplots(figsize=(6.5, 5.5))
        _view(ax, columns, config, axes, -1, lines)
        ax.set_title(f"{config.name}: {title}")
        ax.legend(fontsize=8, loc="best")
        fig.tight_layout()
        fig.savefig(out_dir / name, dpi=110)
        plt.close(fig)
        paths.append(out_dir / name)
    for name, series, ylabel, title in (("capture_distances.png", distances, "distance to target [m]",
                                         "UAV-target distances"),
                                        ("capture_tensions.png", tensions, "tether tension [N]",
                                         "tether tensions (at the knot)")):
        if not series:
            continue
        fig, ax = plt.subplots(figsize=(7, 4))
        for k, (label, values) in enumerate(series.items()):
            ax.plot(time, values, color=COLORS[k % len(COLORS)], lw=1.2, label=label)
        ax.set_xlabel("time [s]")
        ax.set_ylabel(ylabel)
        ax.set_title(f"{config.name}: {title}")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out_dir / name, dpi=110)
        plt.close(fig)
        paths.append(out_dir / name)
    return paths


def animate_capture(columns, config, path, max_frames: int = 90, fps: int = 15) -> Path:
    """Write a GIF of the capture (top and side views side by side). The artists are made
    once and updated per frame (the net's lines as one LineCollection per view)."""
    lines = net_lines(columns, config)
    time = columns["time"]
    rows = np.unique(np.linspace(0, len(time) - 1, min(max_frames, len(time))).round().astype(int))
    everything = np.concatenate([ln.reshape(-1, 3) for ln in lines]
                                + [_xyz(columns, q.body) for q in config.quadrotors]
                                + [_xyz(columns, config.target.name)], axis=0)
    lo, hi = everything.min(axis=0) - 0.3, everything.max(axis=0) + 0.3
    uavs = [_xyz(columns, q.body) for q in config.quadrotors]
    target = _xyz(columns, config.target.name)
    fig, (top, side) = plt.subplots(1, 2, figsize=(10, 4.6))
    views = []
    for ax, (a, b) in ((top, (0, 1)), (side, (0, 2))):
        net = LineCollection([], colors="0.55", linewidths=0.6)
        ax.add_collection(net)
        paths = [ax.plot([], [], color=COLORS[n % len(COLORS)], lw=0.8)[0] for n in range(len(uavs))]
        dots = [ax.plot([], [], "o", color=COLORS[n % len(COLORS)], ms=6)[0] for n in range(len(uavs))]
        t_path = ax.plot([], [], "k--", lw=0.8)[0]
        ball = plt.Circle((0.0, 0.0), config.target.radius, color="k")
        ax.add_patch(ball)
        ax.set_xlim(lo[a], hi[a])
        ax.set_ylim(lo[b], hi[b])
        ax.set_aspect("equal")
        ax.set_xlabel("xyz"[a] + " [m]")
        ax.set_ylabel("xyz"[b] + " [m]")
        views.append((a, b, net, paths, dots, t_path, ball))
    side.set_title("side")
    fig.tight_layout()

    def draw(k):
        row = rows[k]
        for a, b, net, paths, dots, t_path, ball in views:
            net.set_segments([line[row][:, [a, b]] for line in lines])
            for p, path, dot in zip(uavs, paths, dots):
                path.set_data(p[: row + 1, a], p[: row + 1, b])
                dot.set_data([p[row, a]], [p[row, b]])
            t_path.set_data(target[: row + 1, a], target[: row + 1, b])
            ball.center = (target[row, a], target[row, b])
        top.set_title(f"top, t = {time[row]:.2f} s")
        return []

    anim = FuncAnimation(fig, draw, frames=len(rows), blit=False)
    anim.save(path, writer=PillowWriter(fps=fps))
    plt.close(fig)
    return Path(path)


def capture_report(columns, scene, params, config, out_dir, animate: bool = True) -> dict:
    """Verdict (:func:`~mysim_jax.tasks.outcome.capture_outcome`), UAV–target distances,
    tether tensions and lift use of a capture run, with its figures and GIF (unless
    ``animate`` is False) written into ``out_dir``; returns the summary dict (``plots``
    lists the files written)."""
    out_dir = Path(out_dir)
    outcome = capture_outcome(columns, config)
    tensions = tether_tensions(columns, scene, params, config)
    distances = uav_target_distances(columns, config)
    paths = plot_capture(columns, config, out_dir, tensions=tensions, distances=distances)
    if animate:
        paths.append(animate_capture(columns, config, out_dir / "capture.gif"))
    return {
        **outcome.summary(),
        "min_uav_target_distance_m": float(min(d.min() for d in distances.values())),
        "peak_tether_tension_n": float(max(t.max() for t in tensions.values())) if tensions else 0.0,
        "thrust_fraction_last_1s": thrust_fraction(columns, scene, params, config),
        "plots": [p.name for p in paths],
    }
