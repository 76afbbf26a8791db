"""Where a tracking camera expects the target, from its own track, its teammates' cameras and
the start cue: data association (which of its detections are the target) and region hints
(where a detector that takes hints looks,
:class:`~mysim_jax.perception.track_detectors.RegionDetector`).

Data association (:func:`associate`). A detector can fire on things that are not the target
(a teammate, the net), and pointing the camera at such a thing keeps the real target out
of view. So before a camera's detections reach its tracker, each is checked against where
the target should be: the point where the other cameras' detection rays meet best (the
closest-meeting pair, :func:`_consensus_point`) when at least two of them see something,
else (before this camera has first seen the target) the start cue. Detections whose bearing
is farther from that point's than ``GimbalTrackerConfig.gate_deg`` plus the target's angular
radius there (the box of a partly hidden target is off its centre) are dropped, and the
rest are ordered nearest first. With no reference point the detector's
order stands. A camera whose detections are all dropped recovers
(:class:`~mysim_jax.perception.gimbal_tracker.GimbalTracker`), steered by the teammates' cue.

Region hints (:func:`region_hint`, :func:`point_hint`). A camera's hint is the first in view of
its own track's prediction, the point the cameras that saw the target last frame fix together,
and, before its first detection, the start cue (:func:`_hint`); :class:`_RegionMemory` keeps
what the hints need between frames.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from mysim_jax.perception.camera import Intrinsics, PerceptionError, project
from mysim_jax.perception.gimbal_tracker import GimbalTracker
from mysim_jax.perception.localize import (box_size_px, box_touches_border, fuse, pixel_bearings, sphere_range,
                                          sphere_size_px)
from mysim_jax.perception.render_io import Frame
from mysim_jax.perception.track_detectors import OUT_OF_VIEW, RegionHint, box_centre


# --- data association -----------------------------------------------------------------------


def _team_point(frames, detections, intr, radius, range_sigma: float = 0.05) -> np.ndarray | None:
    """(3,) m: the target's position from other cameras' detections (least squares over their
    rays, with ranges from whole boxes; one camera needs a range), or None."""
    boxes = np.array([np.asarray(d.box, float) for d in detections])
    centres = np.stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2], -1)
    bearings = pixel_bearings(intr, np.array([f.R for f in frames]), centres)
    ranges = sphere_range(box_size_px(intr, boxes), radius, intr.fx)
    ranges = np.where(box_touches_border(intr, boxes) | ~np.isfinite(ranges), np.nan, ranges)
    try:
        return fuse("all_ls", np.array([f.p for f in frames]), bearings, ranges, range_sigma=range_sigma)
    except PerceptionError:
        return None


def _consensus_point(frames, detections, intr) -> np.ndarray | None:
    """(3,) m: where the rays of the cameras' detections meet best, or None. Each pair of rays
    is triangulated (the midpoint of their closest approach); the pair whose rays pass
    closest to each other, as an angle seen from the cameras, wins, so one camera on a false
    detection does not move the point (unlike a least-squares fit of all rays)."""
    origins = np.array([np.asarray(f.p, float) for f in frames])
    rays = pixel_bearings(intr, np.array([f.R for f in frames]), np.array([box_centre(d.box) for d in detections]))
    best = None
    for i in range(len(rays)):
        for j in range(i + 1, len(rays)):
            a, b, w = rays[i], rays[j], origins[j] - origins[i]
            c = a @ b
            if 1 - c * c < 1e-9:        # parallel rays do not fix a point
                continue
            si = (w @ a - c * (w @ b)) / (1 - c * c)
            sj = (c * (w @ a) - w @ b) / (1 - c * c)
            if si <= 0 or sj <= 0:      # they meet behind a camera
                continue
            pi, pj = origins[i] + si * a, origins[j] + sj * b
            miss = np.linalg.norm(pi - pj) / min(si, sj)
            if best is None or miss < best[0]:
                best = (miss, 0.5 * (pi + pj))
    return None if best is None else best[1]


def associate(detections: Sequence, frame: Frame, point, gate_deg: float | None, intr: Intrinsics,
              radius: float = 0.0) -> list:
    """``detections`` of ``frame`` whose bearing is within ``gate_deg`` plus the angular radius
    of a target of ``radius`` m at ``point`` ((3,) m, world) of the direction to ``point``,
    nearest first; all of them, in their order, when ``point`` or ``gate_deg`` is None (see
    the module doc)."""
    if point is None or gate_deg is None or not len(detections):
        return list(detections)
    d = np.asarray(point, float) - np.asarray(frame.p, float)
    if not np.linalg.norm(d) > 1e-9:
        return list(detections)

    gate = gate_deg + np.degrees(np.arcsin(min(1.0, radius / np.linalg.norm(d))))
    d /= np.linalg.norm(d)
    rays = pixel_bearings(intr, frame.R, np.array([box_centre(det.box) for det in detections]))
    angles = np.degrees(np.arccos(np.clip(rays @ d, -1.0, 1.0)))
    order = [i for i in np.argsort(angles, kind="stable") if angles[i] <= gate]
    return [detections[i] for i in order]


def _associate_all(dets, frames, ref_of, gate_deg, intr, radius):
    """Each camera's detections gated on the point the others agree on (two or more other
    cameras), else on ``ref_of(camera)`` (the start cue before a first detection)."""
    raw = [list(d) for d in dets]
    out = list(dets)
    G = len(dets)
    for g in range(G):
        others = [s for s in range(G) if s != g and raw[s]]
        ref = None
        if len(others) >= 2:
            ref = _consensus_point([frames[s] for s in others], [raw[s][0] for s in others], intr)
        if ref is None:
            ref = ref_of(g)
        out[g] = associate(raw[g], frames[g], ref, gate_deg, intr, radius)
    return out


# --- region hints ---------------------------------------------------------------------------


def region_hint(tracker: GimbalTracker, t: float, frame: Frame, last_side: float | None,
                max_age_s: float) -> RegionHint | None:
    """Where ``tracker``'s camera should see the target in ``frame`` (taken at ``t``): its
    last detection's world bearing advanced at the tracked bearing rate, projected through the
    frame's camera rotation, with the last box's longer side; None when the last detection
    is older than ``max_age_s`` or there is none; :data:`OUT_OF_VIEW` when the bearing is
    behind the camera or far outside the image."""
    if tracker.last_bearing is None or last_side is None or t - tracker.last_seen_t > max_age_s + 1e-9:
        return None
    b = tracker.last_bearing + tracker.bearing_rate * (t - tracker.last_seen_t)
    return _hint_along(tracker.intr, frame, b, last_side)


def point_hint(intr: Intrinsics, frame: Frame, point, radius: float) -> RegionHint | None:
    """Where a target of ``radius`` m at ``point`` ((3,) m, world: e.g. the teammates'
    estimate) shows in ``frame``: its projection, with the side of the sphere's image;
    :data:`OUT_OF_VIEW` when it is behind the camera or far outside the image, None when the
    camera is inside the sphere."""
    d = np.asarray(point, float) - np.asarray(frame.p, float)
    dist = float(np.linalg.norm(d))
    if not dist > radius:
        return None
    return _hint_along(intr, frame, d / dist, float(sphere_size_px(dist, radius, intr.fx)))


def _hint_along(intr: Intrinsics, frame: Frame, bearing, side: float) -> RegionHint:
    """The hint at world ``bearing`` from ``frame``'s camera, or :data:`OUT_OF_VIEW`."""
    (u, v), depth = project(intr, np.asarray(frame.R, float), np.zeros(3), np.asarray(bearing, float))
    if depth <= 1e-6:
        return OUT_OF_VIEW
    margin = max(side, 32.0)
    if not (-margin <= u <= intr.width + margin and -margin <= v <= intr.height + margin):
        return OUT_OF_VIEW
    return RegionHint(centre=np.array([u, v]), side=float(side))


def _hint(tracker, t, frame, last_side, max_age_s, team, cue, intr, radius) -> RegionHint | None:
    """A camera's region hint: the first in view of its own track's prediction, the
    teammates' last point (``team``: (t, point) or None) when recent, and the start cue
    before its first detection (``cue``: a world point or None); :data:`OUT_OF_VIEW` when
    every one of them puts the target outside the image; None when there is none (the
    whole image is searched)."""
    hints = [region_hint(tracker, t, frame, last_side, max_age_s)]
    if team is not None and t - team[0] <= max_age_s + 1e-9:
        hints.append(point_hint(intr, frame, team[1], radius))
    if cue is not None and tracker.last_seen_t is None:
        hints.append(point_hint(intr, frame, cue, radius))
    hints = [h for h in hints if h is not None]
    return next((h for h in hints if h is not OUT_OF_VIEW), OUT_OF_VIEW if hints else None)


class _RegionMemory:
    """What the region hints of a tracking run remember between frames: each camera's last
    target box side (px) and the cameras' last joint point of the target."""

    def __init__(self, n_cameras: int, max_age_s: float, intr: Intrinsics, radius: float, range_sigma: float):
        self.last_side: list[float | None] = [None] * n_cameras
        self.team: tuple[float, np.ndarray] | None = None        # (t s, (3,) m)
        self.max_age_s, self.intr, self.radius, self.range_sigma = max_age_s, intr, radius, range_sigma

    def hint(self, g: int, tracker: GimbalTracker, t: float, frame: Frame, cue) -> RegionHint | None:
        return _hint(tracker, t, frame, self.last_side[g], self.max_age_s, self.team, cue, self.intr, self.radius)

    def update(self, t: float, frames, dets) -> None:
        """Remember this frame's associated detections (best first per camera)."""
        for g, d in enumerate(dets):
            if d:
                b = np.asarray(d[0].box, float)
                self.last_side[g] = float(max(b[2] - b[0], b[3] - b[1]))
        seen = [g for g in range(len(dets)) if dets[g]]
        if seen:
            point = _team_point([frames[g] for g in seen], [dets[g][0] for g in seen], self.intr, self.radius,
                                self.range_sigma)
            if point is not None:
                self.team = (t, point)
