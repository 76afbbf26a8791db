"""Trajectory files and errors of estimated trajectories: TUM files, evo metrics, plots.

TUM format (one pose per line, space separated): ``t x y z qx qy qz qw`` with ``t`` in s,
the position in m (world) and the body -> world unit quaternion scalar-last, as the TUM
RGB-D benchmark and ``evo`` read it. In memory poses are
:class:`PoseTrack` (quaternions scalar-first, as everywhere in
this project).

Errors (:func:`trajectory_errors`) come from ``evo``'s Python API, after pairing the poses
of the estimate and the reference by time (``evo.core.sync.associate_trajectories``):

* ATE, the absolute trajectory error: the RMSE (and mean, median, max) of the position
  error, once as estimated (``ate_*``) and once after the rigid-body (SE(3), Umeyama)
  alignment that fits the estimate best to the reference (``ate_aligned_*``);
* RPE, the relative pose error over ``rpe_delta_m`` metres of the reference's path, all
  pairs of poses that far apart: the translation RMSE (m, and as a percentage of the
  distance) and the rotation RMSE (deg); undefined (None) on paths shorter than it;
* the distance flown (the reference's path length, m).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
import logging
import os
from pathlib import Path

from evo.core import metrics, sync
from evo.core.trajectory import PoseTrajectory3D
from evo.main_ape import ape
from evo.main_rpe import rpe
import numpy as np
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mysim_jax.perception.camera import PerceptionError


# --- TUM files -----------------------------------------------------------------------


@dataclass(frozen=True)
class PoseTrack:
    """Body poses over time (TUM files store these)."""

    t: np.ndarray           # (N,) s
    p: np.ndarray           # (N, 3) m, world
    q: np.ndarray           # (N, 4) scalar-first unit quaternions, body -> world

    def __len__(self) -> int:
        return len(self.t)


def write_tum(path: str | os.PathLike, traj: PoseTrack) -> None:
    """Write ``traj`` as a TUM trajectory file."""
    q = np.asarray(traj.q, dtype=float)
    data = np.column_stack([traj.t, traj.p, q[:, 1:], q[:, :1]])
    np.savetxt(path, data, fmt="%.9f", header="t x y z qx qy qz qw", comments="# ")


def read_tum(path: str | os.PathLike) -> PoseTrack:
    """Read a TUM trajectory file (comment lines start with #)."""
    try:
        data = np.loadtxt(path, comments="#", ndmin=2)
    except (OSError, ValueError) as exc:
        raise PerceptionError(f"{path}: not a readable TUM trajectory file ({exc})") from None
    if data.shape[1] != 8:
        raise PerceptionError(f"{path}: a TUM line has 8 numbers (t x y z qx qy qz qw), found {data.shape[1]}")
    return PoseTrack(t=data[:, 0], p=data[:, 1:4], q=np.column_stack([data[:, 7], data[:, 4:7]]))


# --- evo -----------------------------------------------------------------------------


def to_evo(traj: PoseTrack, name: str = ""):
    """The trajectory as an ``evo.core.trajectory.PoseTrajectory3D``."""
    return PoseTrajectory3D(positions_xyz=np.asarray(traj.p, dtype=float),
                            orientations_quat_wxyz=np.asarray(traj.q, dtype=float),
                            timestamps=np.asarray(traj.t, dtype=float), meta={"name": name})


def trajectory_errors(reference: PoseTrack, estimate: PoseTrack, rpe_delta_m: float = 10.0,
                      max_time_diff: float = 1e-3) -> dict:
    """Errors of ``estimate`` against ``reference`` (see the module doc); a JSON-ready dict.

    Poses are paired by time within ``max_time_diff`` seconds.
    """
    logging.getLogger("evo").setLevel(logging.WARNING)
    ref, est = sync.associate_trajectories(to_evo(reference, "reference"), to_evo(estimate, "estimate"),
                                           max_diff=max_time_diff)
    if ref.num_poses < 3:
        raise PerceptionError(f"only {ref.num_poses} poses of the estimate match the reference in time "
                              f"(within {max_time_diff} s); cannot compute errors")
    translation = metrics.PoseRelation.translation_part
    out: dict = {"n_poses": int(ref.num_poses), "distance_m": float(ref.path_length),
                 "duration_s": float(ref.timestamps[-1] - ref.timestamps[0])}
    for key, align in (("ate", False), ("ate_aligned", True)):
        stats = ape(copy.deepcopy(ref), copy.deepcopy(est), translation, align=align).stats
        for s in ("rmse", "mean", "median", "max"):
            out[f"{key}_{s}_m"] = float(stats[s])
    rot = ape(copy.deepcopy(ref), copy.deepcopy(est), metrics.PoseRelation.rotation_angle_deg, align=False).stats
    out["ate_rotation_rmse_deg"] = float(rot["rmse"])
    out["ate_final_m"] = float(np.linalg.norm(est.positions_xyz[-1] - ref.positions_xyz[-1]))
    out["rpe_delta_m"] = float(rpe_delta_m)
    out["rpe_translation_rmse_m"] = out["rpe_translation_rmse_percent"] = out["rpe_rotation_rmse_deg"] = None
    if ref.path_length >= 2 * rpe_delta_m:
        common = dict(delta=rpe_delta_m, delta_unit=metrics.Unit.meters, all_pairs=True, pairs_from_reference=True,
                      rel_delta_tol=0.1)
        rt = rpe(copy.deepcopy(ref), copy.deepcopy(est), translation, **common).stats
        rr = rpe(copy.deepcopy(ref), copy.deepcopy(est), metrics.PoseRelation.rotation_angle_deg, **common).stats
        out["rpe_translation_rmse_m"] = float(rt["rmse"])
        out["rpe_translation_rmse_percent"] = float(100.0 * rt["rmse"] / rpe_delta_m)
        out["rpe_rotation_rmse_deg"] = float(rr["rmse"])
    return out


def gauss_markov_fit(t: np.ndarray, error: np.ndarray) -> dict:
    """Fit a first-order Gauss-Markov (Ornstein-Uhlenbeck) process to an estimate's error.

    ``t`` ``(F,)`` s, uniformly spaced; ``error`` ``(F, k)`` estimate minus truth (e.g. a
    position error in m). Per axis: ``sigma`` = the RMS of the error (about zero: a constant
    offset is error too) and the lag-one autocorrelation ``rho = Σ e_i e_(i+1) / Σ e_i²``,
    whose process ``e' = rho e + sigma √(1 - rho²) ξ`` has the correlation time
    ``tau = -Δt / ln rho`` (0 for rho <= 0: white; ``inf`` for rho >= 1). ``pooled`` holds
    the same over all axes together (isotropic sigma = √(mean sigma²)). A simulator can then
    replay errors with these statistics (:class:`mysim_jax.config.env.PerceptionConfig`).
    """
    t = np.asarray(t, dtype=float)
    e = np.asarray(error, dtype=float).reshape(len(t), -1)
    if len(t) < 3:
        raise ValueError(f"gauss_markov_fit: need at least 3 samples, got {len(t)}")
    dt = float((t[-1] - t[0]) / (len(t) - 1))

    def fit(x):                       # x: (F, m), the axes pooled
        power = float(np.sum(x[:-1] * x[:-1]))
        rho = float(np.sum(x[:-1] * x[1:]) / power) if power > 0 else 0.0
        tau = 0.0 if rho <= 0 else (float("inf") if rho >= 1 else float(-dt / np.log(rho)))
        return {"sigma": float(np.sqrt(np.mean(x * x))), "rho": rho, "correlation_time_s": tau}

    axes = [fit(e[:, i:i + 1]) for i in range(e.shape[1])]
    pooled = fit(e)
    return {"dt_s": dt, "axes": axes, "pooled": pooled}


# --- plots ---------------------------------------------------------------------------


def position_error(reference: PoseTrack, estimate: PoseTrack) -> tuple[np.ndarray, np.ndarray]:
    """Times (s) and (unaligned) position errors (m) of the estimate's poses at the reference's times."""
    idx = np.searchsorted(reference.t, estimate.t).clip(0, len(reference.t) - 1)
    prev = (idx - 1).clip(0)
    idx = np.where(np.abs(reference.t[prev] - estimate.t) < np.abs(reference.t[idx] - estimate.t), prev, idx)
    return estimate.t, np.linalg.norm(estimate.p - reference.p[idx], axis=1)


def plot_estimates(reference: PoseTrack, estimates: dict[str, PoseTrack], out_dir: str | os.PathLike,
                   title: str = "", diagnostics=None) -> list[str]:
    """Estimated against true paths (top view and 3D) and position error over time.

    Writes ``estimation_paths.png`` and ``estimation_error.png`` (and ``vio_features.png``
    from per-frame ``diagnostics`` when given) into ``out_dir``; returns the file names.
    """
    out_dir = Path(out_dir)
    colours = {"true": "k"}
    palette = ["tab:blue", "tab:red", "tab:green", "tab:orange"]
    for i, name in enumerate(estimates):
        colours[name] = palette[i % len(palette)]
    fig = plt.figure(figsize=(12, 5.5))
    ax = fig.add_subplot(1, 2, 1)
    ax.plot(reference.p[:, 0], reference.p[:, 1], "-", color="k", lw=2.0, label="true")
    for name, est in estimates.items():
        ax.plot(est.p[:, 0], est.p[:, 1], "-", color=colours[name], lw=1.0, label=name)
    ax.plot(reference.p[0, 0], reference.p[0, 1], "o", color="k", ms=6)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title("top view")
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    ax3 = fig.add_subplot(1, 2, 2, projection="3d")
    ax3.plot(*reference.p.T, "-", color="k", lw=2.0, label="true")
    for name, est in estimates.items():
        ax3.plot(*est.p.T, "-", color=colours[name], lw=1.0, label=name)
    ax3.set_xlabel("x (m)")
    ax3.set_ylabel("y (m)")
    ax3.set_zlabel("z (m)")
    ax3.set_title("3D")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out_dir / "estimation_paths.png", dpi=120)
    plt.close(fig)
    names = ["estimation_paths.png"]

    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for name, est in estimates.items():
        t, e = position_error(reference, est)
        axes[0].plot(t, e, color=colours[name], label=name)
        axes[1].semilogy(t, np.maximum(e, 1e-6), color=colours[name], label=name)
    axes[0].set_ylabel("position error (m)")
    axes[1].set_ylabel("position error (m, log)")
    axes[1].set_xlabel("time (s)")
    axes[0].legend(loc="upper left", fontsize=8)
    for a in axes:
        a.grid(alpha=0.3)
    axes[0].set_title(title or "position error (not aligned)")
    fig.tight_layout()
    fig.savefig(out_dir / "estimation_error.png", dpi=120)
    plt.close(fig)
    names.append("estimation_error.png")

    if diagnostics is not None:
        d = diagnostics
        fig, ax = plt.subplots(figsize=(9, 3.5))
        kf = d.keyframe.astype(bool)
        ax.plot(d.t, d.n_features, label="features", lw=1)
        ax.plot(d.t[1:], d.n_inliers[1:], label="tracked inliers", lw=1)
        ax.plot(d.t[kf], d.n_landmarks[kf], label="landmarks observed (keyframes)", lw=1)
        ax.plot(d.t[kf], np.zeros(kf.sum()), "|", color="k", ms=6, label="keyframes")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("count")
        ax.legend(loc="lower right", fontsize=8)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out_dir / "vio_features.png", dpi=120)
        plt.close(fig)
        names.append("vio_features.png")
    return names
