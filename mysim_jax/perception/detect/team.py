"""The team's own UAVs in a camera's image: where they are expected, and which detections they explain.

A capture team knows where its own UAVs are (each UAV's state estimate) and where each of its
cameras looks (the camera's pose estimate), so it knows where its teammates appear in a
camera's image. A teammate is the object most like the target (both are small quadrotors),
so a detector that takes hints (:meth:`~mysim_jax.perception.detect.model.CNNDetector.detect_region`)
can be told the teammates' expected boxes, and drops a detection that a teammate explains
better than the target does.

Fit of a detection to an expected box (centre ``c``, longer side ``s``; :func:`fit`): the
distance of the detection's centre from ``c`` in units of ``s``, plus the log ratio of the
detection's longer side to ``s`` (0 for a perfect fit; 0.5 for a box half a side off
centre, or of the right centre and 1.65 times too large or small). A detection is a
teammate's (:func:`explained_by_teammates`) when its fit to some teammate's box is below
``gate`` and below its fit to the box the tracker expects the target in by more than
``margin``. A teammate just in front of the target is as large as the target and a fraction
of its side off it, so both fits are small there; the margin keeps the target's own
detection in that case.

Expected boxes (:func:`expected_boxes`): a teammate is a sphere of its rotor tips' radius
around its position, projected through the camera: a square of side ``2 f r / z`` around the
projected centre (``z`` the depth along the optical axis; teammates behind the camera or
nearer than ``min_depth`` are left out). :func:`perturbed_positions` gives the team's
estimates of them from the true positions: each teammate off by a Gaussian position error,
the camera's attitude off by a Gaussian rotation (what the camera's and the teammates' state
estimates get wrong).

NumPy only.
"""

from __future__ import annotations

import numpy as np

from mysim_jax.core.npgeom import rotvec_to_matrix
from mysim_jax.perception.camera import Intrinsics, PerceptionError, project

MIN_DEPTH = 0.1     # m, teammates nearer the camera than this are not expected in its image
# The team's errors in where a teammate appears (:func:`perturbed_positions`): the VIO-like
# pose errors of the tracking runs (docs/tracking.md, ``--pose-noise 0.036 0.004``: 36 mm
# and 4 mrad), a teammate's position relative to the camera carrying two UAVs' position
# errors (sqrt(2) x 36 mm).
TEAM_POSITION_SIGMA_M = 0.051
TEAM_ATTITUDE_SIGMA_RAD = 0.004


def expected_boxes(intr: Intrinsics, R: np.ndarray, p: np.ndarray, positions: np.ndarray, radius,
                   min_depth: float = MIN_DEPTH) -> np.ndarray:
    """(K', 4) px (u_min, v_min, u_max, v_max): where teammates at ``positions`` (K, 3) m of
    rotor-tip ``radius`` m (scalar or (K,)) appear in the image of a camera at pose ``R``
    (3, 3) OpenCV -> world, ``p`` (3,) m; those behind it or nearer than ``min_depth`` m are
    left out."""
    pos = np.asarray(positions, float).reshape(-1, 3)
    r = np.broadcast_to(np.asarray(radius, float), pos.shape[:1])
    if np.any(~np.isfinite(pos)) or np.any(~(r > 0)):
        raise PerceptionError(f"teammates need finite positions and positive radii, got {pos.tolist()}, {r.tolist()}")
    uv, z = project(intr, np.asarray(R, float), np.asarray(p, float), pos)
    keep = z > min_depth
    half = intr.fx * r[keep] / z[keep]
    c = uv[keep]
    return np.stack([c[:, 0] - half, c[:, 1] - half, c[:, 0] + half, c[:, 1] + half], -1).reshape(-1, 4)


def perturbed_positions(rng: np.random.Generator, positions: np.ndarray, R: np.ndarray, position_sigma: float,
                        attitude_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """The team's estimates ``(positions (K, 3) m, camera R (3, 3))``: each of ``positions``
    off by N(0, ``position_sigma``^2) m per axis, the camera's attitude ``R`` turned by a
    rotation vector drawn N(0, ``attitude_sigma``^2) rad per axis."""
    pos = np.asarray(positions, float).reshape(-1, 3)
    noisy = pos + rng.normal(0.0, position_sigma, pos.shape)
    return noisy, rotvec_to_matrix(rng.normal(0.0, attitude_sigma, 3)) @ np.asarray(R, float)


def frame_team(label: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """What a rendered frame's label says about the team (``meta``: ``uavs`` with ``pos``
    and ``radius``, ``camera_R``, ``camera_p``): ``(positions (K, 3) m, radii (K,) m,
    camera R (3, 3), camera p (3,))``, K possibly 0; None when the label does not list the
    UAVs drawn (frames rendered before it did)."""
    meta = label.get("meta") or {}
    uavs = meta.get("uavs")
    if uavs is None:
        return None
    pos = np.array([u["pos"] for u in uavs], float).reshape(-1, 3)
    radii = np.array([u["radius"] for u in uavs], float)
    if not uavs:                   # no UAV drawn: the camera's pose is not needed
        return pos, radii, np.eye(3), np.zeros(3)
    return pos, radii, np.asarray(meta["camera_R"], float), np.asarray(meta["camera_p"], float)


def noisy_team_boxes(rng: np.random.Generator, intr: Intrinsics, team, position_sigma: float = TEAM_POSITION_SIGMA_M,
                     attitude_sigma: float = TEAM_ATTITUDE_SIGMA_RAD) -> np.ndarray:
    """(K', 4) px: where the team expects its UAVs of ``team`` (:func:`frame_team`) in the
    frame, from its estimates (:func:`perturbed_positions`); (0, 4) without UAVs."""
    pos, radii, R, p = team
    if len(pos) == 0:
        return np.zeros((0, 4))
    noisy, R_est = perturbed_positions(rng, pos, R, position_sigma, attitude_sigma)
    return expected_boxes(intr, R_est, p, noisy, radii)


def _centre_side(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    b = np.asarray(boxes, float).reshape(-1, 4)
    return np.stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2], -1), np.maximum(b[:, 2:] - b[:, :2], 1e-6).max(-1)


def fit(boxes: np.ndarray, centre, side) -> np.ndarray:
    """(N,) how well each of ``boxes`` (N, 4) px fits an expected box of ``centre`` (2,) px
    and longer side ``side`` px (module doc; 0 is a perfect fit)."""
    c, s = _centre_side(boxes)
    side = max(float(side), 1e-6)
    return np.linalg.norm(c - np.asarray(centre, float), axis=-1) / side + np.abs(np.log(s / side))


def explained_by_teammates(boxes: np.ndarray, centre, side, teammates: np.ndarray, gate: float,
                           margin: float = 0.0) -> np.ndarray:
    """(N,) bool: which of ``boxes`` (N, 4) px a teammate explains: their fit to some box of
    ``teammates`` (K, 4) px is below ``gate``, and below their fit to the target's expected
    box (``centre`` (2,) px, longer side ``side`` px) by more than ``margin``."""
    boxes = np.asarray(boxes, float).reshape(-1, 4)
    tm = np.asarray(teammates, float).reshape(-1, 4)
    if boxes.shape[0] == 0 or tm.shape[0] == 0:
        return np.zeros(boxes.shape[0], bool)
    tc, ts = _centre_side(tm)
    to_team = np.min(np.stack([fit(boxes, c, s) for c, s in zip(tc, ts)], -1), -1)
    return (to_team < gate) & (to_team + margin < fit(boxes, centre, side))
