"""Target localisation from several UAVs' cameras: bearings, ranges from box size, fusion.

Bearing. A box centre pixel ``(u, v)`` is the world direction ``b = R_c K⁻¹ (u, v, 1) / |.|``
from the camera's optical centre ``p_c`` (``R_c``: OpenCV camera frame -> world).

Range from size (pinhole). An object of size ``D`` (m) across the line of sight at depth
``Z`` spans ``s = f_px D / Z`` pixels, so ``Z ≈ f_px D / s``. For a sphere of radius ``r``
at distance ``ρ`` the silhouette's half angle is ``asin(r / ρ)``; on the optical axis its
image radius is ``f_px tan(asin(r / ρ)) = f_px r / sqrt(ρ² − r²)``, so with ``s`` the image
diameter ``ρ = r sqrt(1 + (2 f_px / s)²)`` (→ ``f_px 2r / s`` far away). Off the axis by an
angle ``γ`` the image is stretched by ``1 / cos γ`` across and ``1 / cos² γ`` along the
radial direction, so the size used is ``sqrt(w h) cos^{3/2} γ`` (``w, h``: box width and
height). A box touching the image border is cut, so it gives a bearing but no range.

The paper (Sec. 2.3) writes ``α = w h / (W H)`` and ``β ∝ 1 / α`` for the range β. The box
area goes as ``1 / ρ²``, so the range goes as ``α^{-1/2}``: the paper's exponent is wrong
by a factor two. :func:`size_range_fits` fits both (and a free exponent) to the same data.

Fusion. Each camera ``i`` gives a ray (``p_i``, ``b_i``) and, when its box is whole, a
range ``r_i``. The least-squares point of a set of cameras minimises

    Σ_i |P_i (x − p_i)|² / (σ_a r_i)² + (b_iᵀ (x − p_i) − r_i)² / (σ_r r_i)²,     P_i = I − b_i b_iᵀ

(the perpendicular miss weighted by the angular noise ``σ_a`` times the range, the range
miss by the relative range noise ``σ_r``): one 3 x 3 linear solve (:func:`fuse_rays`).
Without ranges the weights are equal and the range terms drop (triangulation).

Methods compared per frame (:func:`localize_record`):

* ``triples_median`` — the paper's scheme: the point of every triple of detecting UAVs
  (C(n, 3) of them), then the component-wise median of the triple points. A UAV with a
  wrong box (an occluded target: a short range and a shifted centre) spoils every triple
  it is in, C(n-1, 2) of the C(n, 3); the median ignores it only when the clean triples
  are a majority, (n - 3) / n > 1/2, i.e. from n = 7 UAVs on. With 4 UAVs only one triple
  of four is clean.
* ``triples_weighted`` — the same triples, averaged with weights
  1 / (trace(cov) max(χ²/ν, 1)): cov is the inverse of the triple's normal matrix, χ² its
  weighted residual and ν its degrees of freedom (6 with three ranges). A triple whose
  three rays disagree (a bad box) has χ²/ν ≫ 1 and drops out, so one bad UAV of four is
  ignored; when all agree this is the inverse-variance mean.
* ``all_ls`` — one least-squares point from all detecting UAVs at once (the
  maximum-likelihood point under the Gaussian model above).
* ``triangulation`` — all UAVs, bearings only (no ranges).
* ``single`` — the mean of the per-UAV points ``p_i + r_i b_i``.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
from tqdm.auto import tqdm

from mysim_jax.perception.camera import Intrinsics, PerceptionError

METHODS = ("triples_median", "triples_weighted", "all_ls", "triangulation", "single")


def pixel_bearings(intr: Intrinsics, R: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(..., 3) world unit bearings of pixels (..., 2) seen by cameras with rotations R (..., 3, 3)."""
    pixels = np.asarray(pixels, float)
    ray = np.stack([(pixels[..., 0] - intr.cx) / intr.fx, (pixels[..., 1] - intr.cy) / intr.fy,
                    np.ones(pixels.shape[:-1])], -1)
    b = np.einsum("...ij,...j->...i", np.asarray(R, float), ray)
    return b / np.linalg.norm(b, axis=-1, keepdims=True)


def box_size_px(intr: Intrinsics, boxes: np.ndarray) -> np.ndarray:
    """(...,) px: the size ``sqrt(w h) cos^{3/2} γ`` of boxes (..., 4), γ the centre's angle off the axis."""
    b = np.asarray(boxes, float)
    w, h = b[..., 2] - b[..., 0], b[..., 3] - b[..., 1]
    du = ((b[..., 0] + b[..., 2]) / 2 - intr.cx) / intr.fx
    dv = ((b[..., 1] + b[..., 3]) / 2 - intr.cy) / intr.fy
    cos_g = 1.0 / np.sqrt(1.0 + du * du + dv * dv)
    return np.sqrt(np.clip(w, 0, None) * np.clip(h, 0, None)) * cos_g ** 1.5


def sphere_range(size_px, radius: float, f_px: float) -> np.ndarray:
    """(...,) m: distance to the centre of a sphere of ``radius`` (m) whose image is ``size_px`` across."""
    s = np.asarray(size_px, float)
    with np.errstate(divide="ignore"):
        return radius * np.sqrt(1.0 + (2.0 * f_px / s) ** 2)


def sphere_size_px(distance, radius: float, f_px: float) -> np.ndarray:
    """(...,) px: the image size of a sphere of ``radius`` (m) at ``distance`` (m, > radius)
    from the camera; the inverse of :func:`sphere_range`."""
    d = np.asarray(distance, float)
    return 2.0 * f_px * radius / np.sqrt(d * d - radius * radius)


def box_touches_border(intr: Intrinsics, boxes: np.ndarray, margin_px: float = 1.0) -> np.ndarray:
    """(...,) bool: a box within ``margin_px`` of the image border (cut: its size is not the target's)."""
    b = np.asarray(boxes, float)
    return ((b[..., 0] <= -0.5 + margin_px) | (b[..., 1] <= -0.5 + margin_px)
            | (b[..., 2] >= intr.width - 0.5 - margin_px) | (b[..., 3] >= intr.height - 0.5 - margin_px))


# The relative range noise the fusion assumes for a target's box-size range, by how the
# target looks (:func:`~mysim_jax.perception.render_models.auto_target_style`). A sphere's silhouette
# gives its range to about one pixel of its box; a drone's box changes with its attitude and
# the view direction (docs/tracking.md, "Measured", gives how far the pinhole range from a
# drone's box is off on the evading-drone tracking run), so there the bearings carry the
# estimate.
RANGE_SIGMA = {"sphere": 0.05, "drone": 0.3}


def fuse_rays(origins, bearings, ranges=None, angle_sigma: float = 2e-3, range_sigma: float = 0.05):
    """Least-squares point (3,) and its covariance (3, 3) from rays (see the module doc).

    ``origins``: (n, 3) m; ``bearings``: (n, 3) unit; ``ranges``: (n,) m or None (bearings
    only, equal weights; NaN entries: that ray has no range). ``angle_sigma``: rad;
    ``range_sigma``: relative. Raises when the rays do not fix a point (fewer than two
    non-parallel rays without ranges).
    """
    p = np.asarray(origins, float).reshape(-1, 3)
    b = np.asarray(bearings, float).reshape(-1, 3)
    if len(p) != len(b) or len(p) == 0:
        raise PerceptionError(f"fuse_rays needs as many origins as bearings (>= 1), got {len(p)} and {len(b)}")
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    eye = np.eye(3)
    A = np.zeros((3, 3))
    rhs = np.zeros(3)
    r = None if ranges is None else np.asarray(ranges, float).reshape(-1)
    for i in range(len(p)):
        P = eye - np.outer(b[i], b[i])
        if r is None:
            w_perp, w_par, ri = 1.0, 0.0, 0.0
        elif np.isfinite(r[i]) and r[i] > 0:
            w_perp, w_par, ri = 1.0 / (angle_sigma * r[i]) ** 2, 1.0 / (range_sigma * r[i]) ** 2, r[i]
        else:
            # no range: the ray's weight at the range the others imply is unknown; use the
            # mean of the known ranges (or 1 m)
            known = r[np.isfinite(r) & (r > 0)]
            scale = known.mean() if known.size else 1.0
            w_perp, w_par, ri = 1.0 / (angle_sigma * scale) ** 2, 0.0, 0.0
        A += w_perp * P + w_par * np.outer(b[i], b[i])
        rhs += w_perp * P @ p[i] + w_par * np.outer(b[i], b[i]) @ (p[i] + ri * b[i])
    if np.linalg.cond(A) > 1e10:
        raise PerceptionError(f"the {len(p)} ray(s) do not fix a point (parallel bearings and no ranges)")
    x = np.linalg.solve(A, rhs)
    return x, np.linalg.inv(A)


def ray_chi2(x, origins, bearings, ranges, angle_sigma: float = 2e-3, range_sigma: float = 0.05) -> float:
    """Weighted squared residual of point ``x`` against rays with ranges (the sum :func:`fuse_rays`
    minimises; rays without a finite range contribute their perpendicular miss at the mean range)."""
    p = np.asarray(origins, float).reshape(-1, 3)
    b = np.asarray(bearings, float).reshape(-1, 3)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    r = np.asarray(ranges, float).reshape(-1)
    known = r[np.isfinite(r) & (r > 0)]
    scale = known.mean() if known.size else 1.0
    d = np.asarray(x, float) - p
    along = np.einsum("ij,ij->i", d, b)
    perp = np.linalg.norm(d - along[:, None] * b, axis=1)
    has = np.isfinite(r) & (r > 0)
    rr = np.where(has, r, scale)
    chi2 = (perp / (angle_sigma * rr)) ** 2
    chi2 = chi2 + np.where(has, ((along - np.where(has, r, 0.0)) / (range_sigma * rr)) ** 2, 0.0)
    return float(chi2.sum())


def triangulate_rays(origins, bearings) -> np.ndarray:
    """(3,) m: the point nearest (least squares) to rays (origins (n, 3), bearings (n, 3)), n >= 2."""
    return fuse_rays(origins, bearings)[0]


def triple_estimates(origins, bearings, ranges, **sigmas) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """Points (T, 3), covariance traces (T,) m², reduced residuals χ²/ν (T,) and the index
    triples of every C(n, 3) triple of rays."""
    n = len(origins)
    triples = list(combinations(range(n), 3))
    pts, tr, red = [], [], []
    for tri in triples:
        idx = list(tri)
        o, b, r = np.asarray(origins)[idx], np.asarray(bearings)[idx], np.asarray(ranges)[idx]
        x, cov = fuse_rays(o, b, r, **sigmas)
        dof = 2 * 3 + int(np.sum(np.isfinite(r) & (r > 0))) - 3
        pts.append(x)
        tr.append(np.trace(cov))
        red.append(ray_chi2(x, o, b, r, **sigmas) / max(dof, 1))
    return np.asarray(pts).reshape(-1, 3), np.asarray(tr), np.asarray(red), triples


def fuse(method: str, origins, bearings, ranges, **sigmas) -> np.ndarray | None:
    """(3,) m estimate of one frame by ``method`` (one of METHODS), or None when it has too few rays."""
    origins, bearings, ranges = np.asarray(origins, float), np.asarray(bearings, float), np.asarray(ranges, float)
    n = len(origins)
    if method in ("triples_median", "triples_weighted"):
        if n < 3:
            return None
        pts, tr, red, _ = triple_estimates(origins, bearings, ranges, **sigmas)
        if method == "triples_median":
            return np.median(pts, axis=0)
        w = 1.0 / (tr * np.maximum(red, 1.0))
        return (w[:, None] * pts).sum(0) / w.sum()
    if method == "all_ls":
        if n < 1 or (n == 1 and not np.isfinite(ranges[0])):
            return None
        return fuse_rays(origins, bearings, ranges, **sigmas)[0]
    if method == "triangulation":
        if n < 2:
            return None
        try:
            return triangulate_rays(origins, bearings)
        except PerceptionError:
            return None
    if method == "single":
        ok = np.isfinite(ranges)
        if not ok.any():
            return None
        return (origins[ok] + ranges[ok, None] * bearings[ok]).mean(0)
    raise PerceptionError(f"unknown fusion method {method!r}; methods: {', '.join(METHODS)}")


@dataclass(frozen=True)
class PoseNoise:
    """Perturbation of the camera poses fed to localisation (e.g. to stand in for VIO errors):
    per frame and camera, a Gaussian position offset (m) and a rotation about a random axis by
    a Gaussian angle (rad). With ``correlation_time`` > 0 (s) both are first-order
    Gauss-Markov processes over the frames instead of independent per frame (as VIO errors
    are: see the ``error_model`` of ``scripts/perceive.py``), with the same spread."""

    position_m: float = 0.0
    rotation_rad: float = 0.0
    seed: int = 0
    correlation_time: float = 0.0

    def apply(self, R: np.ndarray, p: np.ndarray, dt: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Perturbed copies of rotations (F, ..., 3, 3) and positions (F, ..., 3); ``dt``: the
        frame interval (s), needed when ``correlation_time`` > 0."""
        if self.position_m < 0 or self.rotation_rad < 0 or self.correlation_time < 0:
            raise PerceptionError(f"pose noise must be >= 0, got position {self.position_m} m, "
                                  f"rotation {self.rotation_rad} rad, correlation time {self.correlation_time} s")
        rng = np.random.default_rng(self.seed)
        dp = rng.normal(0, self.position_m, p.shape)
        w = rng.normal(0, 1, p.shape)
        w = w / np.linalg.norm(w, axis=-1, keepdims=True) * rng.normal(0, self.rotation_rad, p.shape[:-1])[..., None]
        if self.correlation_time > 0:
            if dt is None or not dt > 0:
                raise PerceptionError("pose noise with a correlation time needs the frame interval dt > 0")
            rho = float(np.exp(-dt / self.correlation_time))
            dp, w = _gauss_markov(dp, rho), _gauss_markov(w, rho)
        p = p + dp
        th = np.linalg.norm(w, axis=-1)[..., None, None]
        k = w / np.maximum(np.linalg.norm(w, axis=-1, keepdims=True), 1e-300)
        Kx = np.zeros(w.shape[:-1] + (3, 3))
        Kx[..., 0, 1], Kx[..., 0, 2], Kx[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
        Kx[..., 1, 0], Kx[..., 2, 0], Kx[..., 2, 1] = k[..., 2], -k[..., 1], k[..., 0]
        dR = np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * Kx @ Kx
        return dR @ R, p


def _gauss_markov(white: np.ndarray, rho: float) -> np.ndarray:
    """Filter independent draws along axis 0 into ``e[k] = rho e[k-1] + √(1 - rho²) white[k]``
    (``e[0] = white[0]``): the same stationary spread, correlated over the frames."""
    out = np.empty_like(white)
    out[0] = white[0]
    drive = np.sqrt(1.0 - rho * rho)
    for k in range(1, len(white)):
        out[k] = rho * out[k - 1] + drive * white[k]
    return out


@dataclass
class Localisation:
    """Per-frame estimates of every method (``F`` frames)."""

    t: np.ndarray                    # (F,) s
    truth: np.ndarray                # (F, 3) m
    estimates: dict                  # method -> (F, 3) m (NaN: no estimate that frame)
    n_detecting: np.ndarray          # (F,) cameras with a detection

    def errors(self) -> dict:
        """method -> (F,) m, distance of the estimate from the truth (NaN: none)."""
        return {m: np.linalg.norm(e - self.truth, axis=1) for m, e in self.estimates.items()}

    def metrics(self, frames: np.ndarray | None = None) -> dict:
        """Per method: coverage (fraction of frames with an estimate), error mean, p95 and
        median (m), over ``frames`` ((F,) bool; default all)."""
        out = {}
        for m, e in self.errors().items():
            if frames is not None:
                e = e[frames]
            ok = np.isfinite(e)
            out[m] = {"coverage": float(ok.mean()) if ok.size else None,
                      "error_mean_m": float(e[ok].mean()) if ok.any() else None,
                      "error_p95_m": float(np.percentile(e[ok], 95)) if ok.any() else None,
                      "error_median_m": float(np.median(e[ok])) if ok.any() else None}
        return out


def record_rays(record, pose_noise: PoseNoise | None = None):
    """The rays of a :class:`~mysim_jax.perception.track.TrackingRecord`'s detections: ``has``
    (F, G) bool, origins (F, G, 3) m, unit bearings (F, G, 3) and box-size ranges (F, G) m
    (NaN: no detection, or a box cut by the border), with the true camera poses or
    ``pose_noise``-perturbed ones."""
    intr = record.intr
    R, p = record.camera_R, record.camera_p
    if pose_noise is not None:
        t = np.asarray(record.t, float)
        R, p = pose_noise.apply(R, p, dt=float((t[-1] - t[0]) / (len(t) - 1)) if len(t) > 1 else None)
    boxes = record.det_box
    has = np.all(np.isfinite(boxes), axis=-1)                     # (F, G)
    safe = np.where(has[..., None], boxes, 0.0)
    centres = np.stack([(safe[..., 0] + safe[..., 2]) / 2, (safe[..., 1] + safe[..., 3]) / 2], -1)
    bearings = pixel_bearings(intr, R, centres)
    ranges = sphere_range(box_size_px(intr, safe), record.target_radius, intr.fx)
    ranges = np.where(has & ~box_touches_border(intr, safe) & (box_size_px(intr, safe) > 0), ranges, np.nan)
    return has, p, bearings, ranges


def localize_record(record, pose_noise: PoseNoise | None = None, methods=METHODS, angle_sigma: float = 2e-3,
                    range_sigma: float = 0.05, progress: bool = False) -> Localisation:
    """Estimate the target in every frame of a :class:`~mysim_jax.perception.track.TrackingRecord`
    from its detections, with the true camera poses or ``pose_noise``-perturbed ones."""
    has, p, bearings, ranges = record_rays(record, pose_noise)
    F = len(record.t)
    est = {m: np.full((F, 3), np.nan) for m in methods}
    for k in tqdm(range(F), desc="localise", unit="frame", disable=not progress):
        g = np.flatnonzero(has[k])
        for m in methods:
            x = fuse(m, p[k, g], bearings[k, g], ranges[k, g], angle_sigma=angle_sigma, range_sigma=range_sigma)
            if x is not None:
                est[m][k] = x
    return Localisation(t=np.asarray(record.t), truth=np.asarray(record.target_pos), estimates=est,
                        n_detecting=has.sum(1))


# --- size -> range relations ------------------------------------------------------------------


def size_range_fits(alpha, distance) -> dict:
    """Fit range ``ρ = c α^k`` to box area fractions ``alpha`` (α = w h / (W H)) and true distances:
    the paper's ``k = -1``, the pinhole's ``k = -1/2`` (one constant each, least squares in log
    range) and a free ``k``. Returns per fit the constant, exponent and the relative range
    error (mean, p95)."""
    a = np.asarray(alpha, float)
    d = np.asarray(distance, float)
    ok = np.isfinite(a) & np.isfinite(d) & (a > 0) & (d > 0)
    if ok.sum() < 3:
        raise PerceptionError(f"size_range_fits needs at least 3 valid (alpha, distance) pairs, got {int(ok.sum())}")
    la, ld = np.log(a[ok]), np.log(d[ok])
    out = {"samples": int(ok.sum())}
    slope, intercept = np.polyfit(la, ld, 1)
    resid = ld - (intercept + slope * la)
    se = np.sqrt(resid.var(ddof=2) / ((la - la.mean()) ** 2).sum())
    for name, k in (("paper_inverse_area", -1.0), ("pinhole_inverse_sqrt_area", -0.5), ("free_exponent", slope)):
        logc = intercept if name == "free_exponent" else float(np.mean(ld - k * la))
        rel = np.abs(np.exp(logc + k * la) / d[ok] - 1.0)
        out[name] = {"exponent": float(k), "constant": float(np.exp(logc)),
                     "relative_error_mean": float(rel.mean()), "relative_error_p95": float(np.percentile(rel, 95))}
    out["free_exponent"]["exponent_standard_error"] = float(se)
    return out
