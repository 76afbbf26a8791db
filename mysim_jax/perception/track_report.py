"""Metrics and plots of a tracking run: gimbal pointing, target localisation, size-range fits.

:func:`write_tracking_report` is what ``scripts/perceive.py --track`` writes into its
output folder (see there for the files).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mysim_jax.perception.localize import (METHODS, PoseNoise, box_size_px, box_touches_border, localize_record,
                                           size_range_fits, sphere_range)
from mysim_jax.perception.metrics import gauss_markov_fit
from mysim_jax.perception.pose_bias import TeamRanging, localize_self_calibrated
from mysim_jax.perception.target_filter import target_filter
from mysim_jax.perception.track import TrackingRecord, target_moving, tracking_metrics


def size_range_data(record: TrackingRecord, min_visible: float = 0.95) -> dict:
    """Per detection with a whole box (not cut by the image border) of a target at least
    ``min_visible`` visible (no net line or UAV in front: the relation between size and
    range, not occlusion, is what is fitted): the area fraction ``alpha = w h / (W H)``
    (paper), the size-corrected pinhole range (m) and the true distance from the optical
    centre to the target's centre (m)."""
    intr = record.intr
    box = record.det_box.reshape(-1, 4)
    ok = np.all(np.isfinite(box), axis=1) & (record.visible_fraction.reshape(-1) >= min_visible)
    box = box[ok]
    whole = ~box_touches_border(intr, box)
    box = box[whole]
    dist = np.linalg.norm(record.target_pos[:, None, :] - record.camera_p, axis=-1).reshape(-1)[ok][whole]
    w, h = box[:, 2] - box[:, 0], box[:, 3] - box[:, 1]
    return {"alpha": w * h / (intr.width * intr.height),
            "pinhole_range": sphere_range(box_size_px(intr, box), record.target_radius, intr.fx),
            "distance": dist}


def _plot_pointing(record: TrackingRecord, path: Path) -> None:
    err = record.pixel_error()
    inview = record.in_view()
    fig, ax = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for g, name in enumerate(record.cameras):
        ax[0].plot(record.t, err[:, g], lw=1, label=name)
        ax[1].plot(record.t, inview[:, g] + 0.02 * g, lw=1, drawstyle="steps-post", label=name)
    half = np.hypot(record.intr.cx, record.intr.cy)
    ax[0].axhline(record.intr.cy, color="k", ls=":", lw=0.8, label="half image height")
    ax[0].set_ylim(0, min(np.nanmax(err) * 1.05 if np.isfinite(err).any() else half, 2 * half))
    ax[0].set_ylabel("target centre from image centre [px]")
    ax[0].legend(fontsize=8, ncol=3)
    ax[0].set_title(f"gimbal tracking: {record.intr.width} x {record.intr.height} px, "
                    f"{len(record.t)} frames per camera")
    ax[1].set_ylabel("target in view")
    ax[1].set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_localisation(loc, path_err: Path, path_paths: Path) -> None:
    errors = loc.errors()
    fig, ax = plt.subplots(figsize=(9, 4.5))
    for m in errors:
        e = errors[m]
        ok = np.isfinite(e)
        label = (f"{m}: mean {e[ok].mean():.3f} m, p95 {np.percentile(e[ok], 95):.3f} m" if ok.any()
                 else f"{m}: no estimate")
        ax.plot(loc.t, e, lw=1, label=label)
    ax.set_yscale("log")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("target position error [m]")
    ax.set_title("fused target position error per method")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path_err, dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(1, 2, figsize=(11, 4.8))
    ax[0].plot(loc.truth[:, 0], loc.truth[:, 1], "k-", lw=2, label="true")
    for m in ("triples_median", "all_ls"):
        if m in loc.estimates:
            ax[0].plot(loc.estimates[m][:, 0], loc.estimates[m][:, 1], ".", ms=3, label=m)
            ax[1].plot(loc.t, loc.estimates[m][:, 2], ".", ms=3, label=m)
    ax[0].set_aspect("equal", adjustable="datalim")
    ax[0].set_xlabel("x [m]")
    ax[0].set_ylabel("y [m]")
    ax[0].set_title("top view")
    ax[0].legend(fontsize=8)
    ax[1].plot(loc.t, loc.truth[:, 2], "k-", lw=2, label="true")
    ax[1].set_xlabel("time [s]")
    ax[1].set_ylabel("z [m]")
    ax[1].set_title("height")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path_paths, dpi=110)
    plt.close(fig)


def _plot_size_range(data: dict, fits: dict, path: Path) -> None:
    a, d = data["alpha"], data["distance"]
    xs = np.geomspace(a.min(), a.max(), 100)
    fig, ax = plt.subplots(figsize=(6.5, 4.8))
    ax.loglog(a, d, ".", ms=3, color="0.5", label="detections (true distance)")
    for key, style in (("paper_inverse_area", "r-"), ("pinhole_inverse_sqrt_area", "b-"), ("free_exponent", "g--")):
        f = fits[key]
        ax.loglog(xs, f["constant"] * xs ** f["exponent"], style,
                  label=f"{key}: k = {f['exponent']:.3f}, rel. err mean {100 * f['relative_error_mean']:.1f} %")
    ax.set_xlabel("box area fraction alpha = w h / (W H)")
    ax.set_ylabel("distance to target [m]")
    ax.set_title("range = c alpha^k")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


TEAM_METHOD = "triples_weighted"     # the fusion whose estimate the team's target track filters
# With camera poses that carry errors (a team's poses always do: each UAV's VIO), the team's
# track filters TEAM_METHOD's fusion of the rays corrected by the self-calibrated pose biases
# (:mod:`mysim_jax.perception.pose_bias`); with the true poses there is nothing to calibrate
# and it filters the plain fusion. ``error_model_plain`` / ``error_model_draws_plain`` keep
# the plain fusion's track beside it.
SELF_CALIBRATED = "self_calibrated"
# m/s^3: the net stops a falling target from ~6 m/s within ~0.1 s; a smaller value lags
# behind that (velocity RMS error on the falling gimbal run, VIO-like pose noise: 1.1,
# 0.71, 0.55, 0.47, 0.41 m/s for 5, 20, 50, 100, 200), a larger one is noisier in the fall
TEAM_JERK_SIGMA = 100.0


def target_error_model(record: TrackingRecord, loc, poses: str = "true", method: str = TEAM_METHOD,
                       position_sigma: float = 0.05, jerk_sigma: float = TEAM_JERK_SIGMA) -> dict:
    """The team's target track and its errors: the fused positions of ``method`` filtered
    over time (:func:`mysim_jax.perception.target_filter.target_filter`) into a position and
    velocity estimate, and a Gauss-Markov fit of each one's error against the true target
    (:func:`mysim_jax.perception.metrics.gauss_markov_fit`), from the first fix on: the
    ``error_model`` that ``scripts/perception_gap.py fit --target`` reads."""
    p, v = target_filter(loc.t, loc.estimates[method], position_sigma=position_sigma, jerk_sigma=jerk_sigma)
    ok = np.all(np.isfinite(p), axis=1)
    if ok.sum() < 3:
        return {"skipped": f"{int(ok.sum())} frames with a target track; the fit needs >= 3"}
    first = int(np.argmax(ok))
    t = loc.t[first:]
    p_err = np.linalg.norm(p[first:] - record.target_pos[first:], axis=1)
    name = f"{TEAM_METHOD}, pose biases self-calibrated" if method == SELF_CALIBRATED else method
    return {"method": name, "camera_poses": poses,
            "filter": {"kind": "constant acceleration", "position_sigma_m": position_sigma,
                       "jerk_sigma_m_s3": jerk_sigma},
            "first_fix_s": float(loc.t[first]),
            "position_error_mean_m": float(p_err.mean()),
            "position_error_p95_m": float(np.percentile(p_err, 95)),
            "velocity_error_mean_m_s": float(np.linalg.norm(v[first:] - record.target_vel[first:], axis=1).mean()),
            "position_m": gauss_markov_fit(t, p[first:] - record.target_pos[first:]),
            "velocity_m_s": gauss_markov_fit(t, v[first:] - record.target_vel[first:])}


def _error_stats(loc, method: str) -> tuple[float, float]:
    """Mean and p95 (m) of ``method``'s error over the frames it has an estimate in."""
    e = np.linalg.norm(loc.estimates[method] - loc.truth, axis=1)
    e = e[np.isfinite(e)]
    return float(e.mean()), float(np.percentile(e, 95))


def _draw_summary(stats: list) -> dict:
    means, p95s = [m for m, _ in stats], [p for _, p in stats]
    return {"error_mean_m": float(np.mean(means)), "error_p95_m": float(np.mean(p95s)),
            "draw_mean_range_m": [min(means), max(means)], "draw_means_m": means}


def pose_noise_seeds(record: TrackingRecord, pose_noise: PoseNoise, seeds: int, range_sigma: float,
                     method: str = TEAM_METHOD, first_seed: int = 0, ranging: TeamRanging | None = None) -> dict:
    """The fused target error (``method``) with ``seeds`` draws of ``pose_noise`` (seeds
    ``first_seed``, ``first_seed + 1``, ...), from the run's detections and, in the same
    frames, from the renderer's true boxes: what the camera-pose errors alone cost, whatever
    the detector. Per kind of box: the error mean and p95 (m) averaged over the draws, and
    the smallest and largest draw's mean, and each draw's mean (``draw_means_m``);
    ``self_calibrated``: the same with the cameras' pose biases calibrated from the target's
    rays (:mod:`mysim_jax.perception.pose_bias`, assuming ``pose_noise``'s spreads;
    ``true_poses``: with the true poses, the cost of calibrating what is not there);
    ``error_model``: the team track's error model pooled over the draws
    (:func:`pooled_error_model`), the track filtering the self-calibrated fusion, and
    ``error_model_plain`` the same of the plain fusion's track. With ``ranging`` (the
    distances between the cameras, a draw of its own per seed), also
    ``self_calibrated_ranging`` and ``error_model_ranging``: the calibration that uses them."""
    truth = dataclasses.replace(record, det_box=np.where(np.isfinite(record.det_box), record.true_box, np.nan))
    out = {"seeds": seeds, "first_seed": first_seed, "method": method}
    kinds = {"": None} if ranging is None else {"": None, "_ranging": ranging}
    calibrated = {kind: {} for kind in kinds}
    models = {"_plain": [], **{kind: [] for kind in kinds}}
    for name, rec in (("detections", record), ("true_boxes", truth)):
        plain, cal = [], {kind: [] for kind in kinds}
        for seed in range(first_seed, first_seed + seeds):
            noise = dataclasses.replace(pose_noise, seed=seed)
            loc = localize_record(rec, pose_noise=noise, methods=(method,), range_sigma=range_sigma)
            plain.append(_error_stats(loc, method))
            if name == "detections":
                models["_plain"].append(target_error_model(record, loc, poses="perturbed", method=method))
            for kind, rg in kinds.items():
                loc_cal = localize_self_calibrated(rec, noise, range_sigma=range_sigma, method=method,
                                                   ranging=None if rg is None else dataclasses.replace(rg, seed=seed))
                cal[kind].append(_error_stats(loc_cal, SELF_CALIBRATED))
                if name == "detections":
                    models[kind].append(target_error_model(record, loc_cal, poses="perturbed", method=SELF_CALIBRATED))
        out[name] = _draw_summary(plain)
        for kind in kinds:
            calibrated[kind][name] = _draw_summary(cal[kind])
    for kind, rg in kinds.items():
        loc = localize_self_calibrated(record, pose_sigma=(pose_noise.position_m, pose_noise.rotation_rad),
                                       correlation_time=pose_noise.correlation_time, range_sigma=range_sigma,
                                       method=method, ranging=rg)
        mean, p95 = _error_stats(loc, "self_calibrated")
        out["self_calibrated" + kind] = {**calibrated[kind], "true_poses": {"error_mean_m": mean, "error_p95_m": p95}}
    if ranging is not None:
        out["self_calibrated_ranging"]["ranging"] = {"sigma_m": ranging.sigma_m, "bias_m": ranging.bias_m}
    for kind, fitted in models.items():
        out["error_model" + kind] = pooled_error_model(fitted)
    if ranging is not None:
        out["error_model_ranging"]["method"] += " with the team's ranges"
    return out


def pooled_error_model(models: list[dict]) -> dict:
    """One error model from :func:`target_error_model` results of several pose-noise draws:
    per quantity, the Gauss-Markov σ pooled as the root mean square of the draws' pooled σ
    and the correlation time as their mean (the shape ``scripts/perception_gap.py fit``
    reads, with ``--target-block error_model_draws``)."""
    fitted = [m for m in models if "position_m" in m]
    if not fitted:
        return {"skipped": "no draw had a target track to fit"}
    out = {"method": fitted[0]["method"], "camera_poses": f"perturbed, {len(fitted)} draws pooled"}
    for key in ("position_m", "velocity_m_s"):
        pooled = [m[key]["pooled"] for m in fitted]
        out[key] = {"pooled": {"sigma": float(np.sqrt(np.mean([p["sigma"] ** 2 for p in pooled]))),
                               "correlation_time_s": float(np.mean([p["correlation_time_s"] for p in pooled]))},
                    "draws": [{"sigma": p["sigma"], "correlation_time_s": p["correlation_time_s"]} for p in pooled]}
    for key in ("position_error_mean_m", "position_error_p95_m", "velocity_error_mean_m_s"):
        out[key] = float(np.mean([m[key] for m in fitted]))
    return out


def write_tracking_report(record: TrackingRecord, out: Path, pose_noise: PoseNoise | None = None,
                          extra: dict | None = None, progress: bool = True, range_sigma: float = 0.05,
                          pose_seeds: int = 0, first_pose_seed: int = 0, ranging: TeamRanging | None = None) -> dict:
    """Write ``metrics.json``, ``tracking.npz``, ``localisation.csv`` and the plots into ``out``;
    returns the metrics. ``range_sigma``: the relative range noise the fusion assumes;
    ``pose_seeds``: with ``pose_noise``, also :func:`pose_noise_seeds` over that many draws
    from seed ``first_pose_seed`` (``localisation.perturbed_poses_draws``, and the pooled
    ``error_model_draws``; with ``ranging``, ``error_model_draws_ranging`` too). With
    ``pose_noise`` the team's track (``error_model``) filters the self-calibrated fusion
    (``error_model_plain``: the plain one's; see SELF_CALIBRATED above)."""
    out = Path(out)
    metrics = {"tracking": tracking_metrics(record)}
    loc = localize_record(record, progress=progress, range_sigma=range_sigma)
    moving = target_moving(record)
    metrics["localisation"] = {"range_sigma": range_sigma, "true_poses": loc.metrics(),
                               "true_poses_target_moving": {"frames": int(moving.sum()), **loc.metrics(moving)}}
    if pose_noise is not None:
        noisy = localize_record(record, pose_noise=pose_noise, progress=progress, range_sigma=range_sigma)
        metrics["localisation"]["perturbed_poses"] = {
            "position_sigma_m": pose_noise.position_m, "rotation_sigma_rad": pose_noise.rotation_rad,
            "correlation_time_s": pose_noise.correlation_time,
            **noisy.metrics()}
        if pose_seeds:
            draws = pose_noise_seeds(record, pose_noise, pose_seeds, range_sigma, first_seed=first_pose_seed,
                                     ranging=ranging)
            for kind in ("", "_plain", "_ranging"):
                if "error_model" + kind in draws:
                    metrics["error_model_draws" + kind] = draws.pop("error_model" + kind)
            metrics["localisation"]["perturbed_poses_draws"] = draws
        cal = localize_self_calibrated(record, pose_noise, range_sigma=range_sigma)
        metrics["error_model"] = target_error_model(record, cal, poses="perturbed", method=SELF_CALIBRATED)
        metrics["error_model_plain"] = target_error_model(record, noisy, poses="perturbed")
    else:
        metrics["error_model"] = target_error_model(record, loc, poses="true")
    n_det = loc.n_detecting
    metrics["localisation"]["detecting_cameras_histogram"] = {str(k): int((n_det == k).sum())
                                                              for k in range(len(record.cameras) + 1)}
    data = size_range_data(record)
    plots = ["pointing.png", "localisation_error.png", "localisation_paths.png"]
    n, span = len(data["alpha"]), (data["distance"].max() / data["distance"].min() if len(data["alpha"]) else 1.0)
    if n < 10 or span < 1.5:
        metrics["size_range"] = {"skipped": f"{n} whole, unoccluded boxes over distances spanning a factor "
                                            f"{span:.2f}; the fits need >= 10 over a factor >= 1.5"}
    else:
        fits = size_range_fits(data["alpha"], data["distance"])
        fits["distance_range_m"] = [float(data["distance"].min()), float(data["distance"].max())]
        rel = np.abs(data["pinhole_range"] / data["distance"] - 1)
        fits["sphere_pinhole_formula"] = {"relative_error_mean": float(rel.mean()),
                                          "relative_error_p95": float(np.percentile(rel, 95)),
                                          "note": "rho = r sqrt(1 + (2 f / s)^2), s = sqrt(w h) cos^1.5(gamma); "
                                                  "no fitted constant"}
        metrics["size_range"] = fits
        _plot_size_range(data, fits, out / "size_range.png")
        plots.append("size_range.png")
    _plot_pointing(record, out / "pointing.png")
    _plot_localisation(loc, out / "localisation_error.png", out / "localisation_paths.png")
    metrics["plots"] = plots
    if extra:
        metrics.update(extra)
    record.save_npz(out / "tracking.npz")
    header = ["t", "true_x", "true_y", "true_z", "detecting"] + [f"{m}_{a}" for m in METHODS for a in "xyz"]
    table = np.column_stack([loc.t, loc.truth, loc.n_detecting] + [loc.estimates[m] for m in METHODS])
    np.savetxt(out / "localisation.csv", table, delimiter=",", header=",".join(header), comments="", fmt="%.6g")
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics


def _team_track_line(model: dict) -> str:
    """One summary line of a team-track error model (:func:`target_error_model`, or
    :func:`pooled_error_model` over pose-noise draws)."""
    pp, vp = model["position_m"]["pooled"], model["velocity_m_s"]["pooled"]
    return (f"  team track ({model['camera_poses']} poses, {model['method']}, filtered): position error mean "
            f"{model['position_error_mean_m']:.4f} m, p95 {model['position_error_p95_m']:.4f} m (Gauss-Markov sigma "
            f"{pp['sigma']:.4f} m, {pp['correlation_time_s']:.2f} s); velocity error mean "
            f"{model['velocity_error_mean_m_s']:.3f} m/s (sigma {vp['sigma']:.3f} m/s, {vp['correlation_time_s']:.2f} s)")


def tracking_summary_lines(scene: str, record, metrics: dict, frame_rate: float, wall: float, out) -> list[str]:
    """What ``scripts/perceive.py --track`` prints: how often the target was in view and
    detected, the pointing error, the localisation errors, the size-range fits."""
    lines = []
    tr = metrics["tracking"]["all"]
    lines.append(f"{scene}: {len(record.cameras)} gimbal cameras x {len(record.t)} frames at {frame_rate:g} Hz "
                 f"in {wall:.1f} s; wrote {out}/")
    lines.append(f"  target in view {100 * tr['in_view_fraction']:.1f} % of frames, detected {100 * tr['detected_fraction']:.1f} %; "
                 f"centre from image centre: mean {tr['pixel_error_mean_px']:.1f} px, p95 {tr['pixel_error_p95_px']:.1f} px")
    for m, e in metrics["localisation"]["true_poses"].items():
        if e["error_mean_m"] is not None:
            lines.append(f"  {m}: error mean {e['error_mean_m']:.4f} m, p95 {e['error_p95_m']:.4f} m "
                         f"({100 * e['coverage']:.0f} % of frames)")
    noisy = metrics["localisation"].get("perturbed_poses")
    if noisy is not None:
        e = noisy[TEAM_METHOD]
        if e["error_mean_m"] is not None:
            lines.append(f"  {TEAM_METHOD}, camera poses perturbed ({1000 * noisy['position_sigma_m']:.0f} mm, "
                         f"{1000 * noisy['rotation_sigma_rad']:.1f} mrad, {noisy['correlation_time_s']:g} s): error mean "
                         f"{e['error_mean_m']:.4f} m, p95 {e['error_p95_m']:.4f} m")
    draws = metrics["localisation"].get("perturbed_poses_draws")
    if draws is not None:
        d, tb = draws["detections"], draws["true_boxes"]
        lines.append(f"  {draws['method']} over {draws['seeds']} pose-noise draws: error mean {d['error_mean_m']:.4f} m "
                     f"(draws {d['draw_mean_range_m'][0]:.4f}-{d['draw_mean_range_m'][1]:.4f}), p95 "
                     f"{d['error_p95_m']:.4f} m; from the true boxes in the same frames: mean {tb['error_mean_m']:.4f} m, "
                     f"p95 {tb['error_p95_m']:.4f} m")
        for kind, what in (("self_calibrated", "self-calibrated"),
                           ("self_calibrated_ranging", "self-calibrated with the team's ranges")):
            sc = draws.get(kind)
            if sc is None:
                continue
            d, tb, tp = sc["detections"], sc["true_boxes"], sc["true_poses"]
            rg = sc.get("ranging")
            lines.append(f"  the same with the cameras' pose biases {what}"
                         + (f" ({1000 * rg['sigma_m']:.0f} mm noise, {1000 * rg['bias_m']:.0f} mm pair biases)" if rg else "")
                         + f": error mean {d['error_mean_m']:.4f} m "
                         f"(draws {d['draw_mean_range_m'][0]:.4f}-{d['draw_mean_range_m'][1]:.4f}), p95 "
                         f"{d['error_p95_m']:.4f} m; true boxes: mean {tb['error_mean_m']:.4f} m, p95 "
                         f"{tb['error_p95_m']:.4f} m; true poses: mean {tp['error_mean_m']:.4f} m, p95 "
                         f"{tp['error_p95_m']:.4f} m")
    for key in ("error_model", "error_model_plain", "error_model_draws", "error_model_draws_plain",
                "error_model_draws_ranging"):
        if "position_m" in metrics.get(key, {}):
            lines.append(_team_track_line(metrics[key]))
    dt = metrics.get("detection_time")
    if dt is not None:
        lines.append(f"  detection: {dt['all']['frames_per_s']:.1f} frames/s over the camera frames looked at "
                     f"({dt['region']['calls']} around the expected target, {dt['region+full']['calls']} there then "
                     f"the whole image, {dt['full']['calls']} the whole image; {dt['skipped']} not looked at: the "
                     f"target expected outside the image)")
    if "skipped" in metrics.get("size_range", {}):
        lines.append(f"  size-range fits skipped: {metrics['size_range']['skipped']}")
    elif "size_range" in metrics:
        f = metrics["size_range"]
        lines.append(f"  range from box area: paper (k = -1) rel. error mean {100 * f['paper_inverse_area']['relative_error_mean']:.1f} %, "
                     f"pinhole (k = -1/2) {100 * f['pinhole_inverse_sqrt_area']['relative_error_mean']:.1f} %, "
                     f"free fit k = {f['free_exponent']['exponent']:.3f}")
    return lines
