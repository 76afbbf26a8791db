"""Gimbal target tracking (paper Alg. target_tracking_process), closed loop in the simulator.

Every UAV carries a gimbal camera (:mod:`mysim_jax.dynamics.gimbal`: a universal joint with
PD servos towards commanded angles). Each camera frame, for every gimbal camera:

1. render the camera's image at the current state (:mod:`mysim_jax.perception.render`);
2. detect the target (any callable ``Frame -> list[Detection]``, best first: the learned
   detector through :func:`image_detector`, or the :class:`OracleDetector` stand-in built
   from the renderer's ground-truth box);
3. turn the pixel error of the box centre from the image centre into gimbal commands
   (:class:`GimbalTracker`), with recovery when the target is lost;
4. set the commanded angles (``params.quadrotor.gimbal_angle``, a traced parameter) and
   advance the simulation by one frame period.

So the camera's motion comes from the gimbal's own joint dynamics (servo bandwidth, the
UAV's attitude, the tether loads on the UAV) and the images see the camera where the
simulated joint has put it. The simulation runs as jitted ``lax.scan`` chunks of one frame
period; the commands are a parameter, so nothing recompiles between frames.

Control law. The box centre pixel ``(u, v)`` is a bearing ``R_c K⁻¹ (u, v, 1)`` (world),
seen from the gimbal's centre (the camera's optical centre is the joint point, so it does
not move with the angles). Rotated into the UAV frame, the bearing gives the angles
``a*`` that would put the target at the image centre (the gimbal's inverse kinematics,
:class:`GimbalGeometry`); ``a* − a`` (``a``: the encoder angles) is the pixel error
expressed as angles through the intrinsics and the gimbal's geometry. The command is

    cmd = a + kp (a* − a) + ki ∫ (a* − a) dt + ȧ* · lead

with the bearing's world rate ``ȧ*`` from the last two detections (a lead of about one
frame plus the servo's lag compensates the frame delay), then rate-limited to
``max_rate`` and the tilt clipped to ``tilt_limits``. ``kp = 1`` points the camera at the
target in one frame (the servo is much faster than the frame rate).

Recovery when no detection comes: ``hold_frames`` frames holding the command, then up to
``predict_s`` pointing along the bearing predicted from the last detections (constant
angular rate in the world), or at a cue point when one is given (e.g. the other UAVs'
fused estimate of the target, :mod:`mysim_jax.perception.localize`), then a search pattern
(a raster: the pan turning round at ``search_pan_rate``, 1.25 turns per row, the rows 0.7
fields of view apart in tilt from the last tilt outwards) until the target is found again.

Data association (:func:`associate`). A detector can fire on things that are not the target
(a teammate, the net), and pointing the camera at such a thing keeps the real target out
of view. So before a camera's detections reach its tracker, each is checked against where
the target should be: the point where the other cameras' detection rays meet best (the
closest-meeting pair, :func:`_consensus_point`) when at least two of them see something,
else (before this camera has first seen the target) the start cue. Detections whose bearing
is farther from that point's than ``GimbalTrackerConfig.gate_deg`` plus the target's angular
radius there (the box of a partly hidden target is off its centre) are dropped, and the
rest are ordered nearest first. With no reference point the detector's
order stands. A camera whose detections are all dropped recovers as above, steered by the
teammates' cue.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import jax
import numpy as np
from tqdm.auto import tqdm

from mysim_jax.build import build
from mysim_jax.control.build import R_Y_90, gimbal_marker_frames
from mysim_jax.core.npgeom import quat_to_matrix
from mysim_jax.perception.camera import Intrinsics, PerceptionError, intrinsics as make_intrinsics, project
from mysim_jax.perception.detect import Detection   # noqa: F401  (the detections this module handles)
from mysim_jax.perception.detect.model import load_detector
from mysim_jax.perception.localize import (RANGE_SIGMA, PoseNoise, box_size_px, box_touches_border, fuse,
                                          pixel_bearings, sphere_range, sphere_size_px)
from mysim_jax.perception.render import Renderer
from mysim_jax.perception.render_io import Frame
from mysim_jax.perception.render_models import auto_target_style
from mysim_jax.sim import rollout, single_env_scene
from mysim_jax.tasks.scripted import team_policy


# --- detections -----------------------------------------------------------------------------


FrameDetector = Callable[[Frame], list]     # Frame -> detections, best first


def image_detector(detector) -> FrameDetector:
    """Adapt an image detector (``detector.detect(image (H, W, 3) uint8 RGB) -> list``) to frames."""
    if not hasattr(detector, "detect"):
        raise PerceptionError(f"a detector needs a detect(image) method; got {type(detector).__name__}")
    return lambda frame: detector.detect(frame.image)


@dataclass(frozen=True)
class RegionHint:
    """Where a camera's tracker expects the target in its next image."""

    centre: np.ndarray      # (2,) px, the expected box centre
    side: float             # px, the expected box's longer side


# the hint that the target is expected outside the image (behind the camera or beyond its
# border): a detector that takes hints does not look at all
OUT_OF_VIEW = RegionHint(centre=np.full(2, np.nan), side=0.0)


class RegionDetector:
    """A frame detector that looks where the tracker expects the target (region-of-interest
    mode) and at the whole image otherwise.

    Called as ``detector(frame, hint)``: with a :class:`RegionHint` it runs
    ``detector.detect_region(image, hint.centre, hint.side, region)`` (the learned
    detector's :meth:`~mysim_jax.perception.detect.model.CNNDetector.detect_region`);
    without a hint, ``detector.detect(image)`` on the whole image; with :data:`OUT_OF_VIEW`
    nothing (the target is expected outside this image). With ``fallback_full``,
    a region that finds nothing is followed by the whole image in the same frame (off by
    default: the hint is where the target is expected, so a miss there is mostly a hidden
    target, and the tracker's recovery and the team's cue take over). :meth:`stats` gives
    the calls of each kind and the detection time per frame (wall clock of the detector
    alone, not the rendering)."""

    accepts_hints = True

    def __init__(self, detector, region=None, fallback_full: bool = False):
        if not (hasattr(detector, "detect") and hasattr(detector, "detect_region")):
            raise PerceptionError(f"region mode needs a detector with detect and detect_region; "
                                  f"got {type(detector).__name__}")
        self.detector, self.region, self.fallback_full = detector, region, fallback_full
        self.seconds: list[float] = []
        self.kinds: list[str] = []          # "region", "region+full" (the fallback ran), "full"

    def __call__(self, frame: Frame, hint: RegionHint | None = None) -> list:
        if hint is OUT_OF_VIEW:
            self.seconds.append(0.0)
            self.kinds.append("skipped")
            return []
        t0 = time.perf_counter()
        kind = "full"
        if hint is not None:
            found = self.detector.detect_region(frame.image, hint.centre, hint.side, self.region)
            kind = "region"
            if not found and self.fallback_full:
                found, kind = self.detector.detect(frame.image), "region+full"
        else:
            found = self.detector.detect(frame.image)
        self.seconds.append(time.perf_counter() - t0)
        self.kinds.append(kind)
        return found

    def stats(self) -> dict:
        """Calls by kind and detection time (median ms, and frames/s from the mean time),
        over the frames the detector looked at, and per kind; ``skipped``: frames in which
        the target was expected outside the image (not looked at)."""
        sec, kinds = np.asarray(self.seconds), np.asarray(self.kinds)

        def summary(sel):
            t = sec[sel]
            return {"calls": int(t.size), "median_ms": float(1e3 * np.median(t)) if t.size else None,
                    "frames_per_s": float(1.0 / t.mean()) if t.size else None}

        out = {"all": summary(kinds != "skipped")}
        for kind in ("region", "region+full", "full"):
            out[kind] = summary(kinds == kind)
        out["skipped"] = int(np.sum(kinds == "skipped"))
        out["note"] = ("frames/s = 1 / mean detection time per camera frame looked at (the detector alone, one "
                       "image at a time); 'region+full': the region found nothing and the whole image was "
                       "searched; 'skipped': frames in which the target was expected outside the image")
        return out


class OracleDetector:
    """Stand-in detector from the renderer's ground truth: the visible target's box
    (``TargetView.box``) with Gaussian pixel noise on each edge, missed with probability
    ``miss_rate`` and whenever fewer than ``min_visible_px`` target pixels show.

    ``noise_px``: standard deviation of each box edge (px); ``seed``: the noise's seed.
    """

    def __init__(self, noise_px: float = 1.0, miss_rate: float = 0.0, min_visible_px: int = 4, seed: int = 0):
        if not noise_px >= 0:
            raise PerceptionError(f"noise_px must be >= 0, got {noise_px}")
        if not 0.0 <= miss_rate <= 1.0:
            raise PerceptionError(f"miss_rate must be in [0, 1], got {miss_rate}")
        self.noise_px = float(noise_px)
        self.miss_rate = float(miss_rate)
        self.min_visible_px = int(min_visible_px)
        self.rng = np.random.default_rng(seed)

    def __call__(self, frame: Frame) -> list[Detection]:
        tv = frame.target
        if tv is None:
            raise PerceptionError("the oracle detector needs a scene with a target (frame.target is None)")
        if tv.box is None or tv.visible_px < self.min_visible_px or self.rng.random() < self.miss_rate:
            return []
        box = tv.box + self.rng.normal(0.0, self.noise_px, 4)
        box = np.array([min(box[0], box[2]), min(box[1], box[3]), max(box[0], box[2]), max(box[1], box[3])])
        return [Detection(box=box, score=1.0)]


def box_centre(box) -> np.ndarray:
    """(2,) px centre of a box (u_min, v_min, u_max, v_max)."""
    b = np.asarray(box, float)
    return np.array([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2])


# --- gimbal geometry ------------------------------------------------------------------------


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rotvec_matrix(w) -> np.ndarray:
    """(3, 3) rotation by the rotation vector ``w`` (rad)."""
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        return np.eye(3)
    k = np.asarray(w, float) / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


class GimbalGeometry:
    """Forward and inverse kinematics of one gimbal camera (a ``mount: gimbal`` camera config).

    The camera body's orientation in the UAV frame is ``r_i R_z(a₁) R_y(π/2) R_z(a₂) r_jᵀ``
    (:func:`mysim_jax.control.build.camera_in_uav`): ``a₁`` pan about the outer axis,
    ``a₂`` tilt about the inner axis. The optical axis is the camera body's +x.
    """

    def __init__(self, camera_config):
        if getattr(camera_config, "mount", None) != "gimbal":
            raise PerceptionError(f"camera '{getattr(camera_config, 'name', camera_config)}' is not on a gimbal "
                                  f"(mount: {getattr(camera_config, 'mount', None)!r}); tracking needs "
                                  f"mount: gimbal")
        self.name = camera_config.name
        self.r_i, self.r_j = gimbal_marker_frames(camera_config)
        self._r_y = R_Y_90
        v = self.r_j.T @ np.array([1.0, 0.0, 0.0])        # optical axis in the inner marker's frame
        self._rho = float(np.hypot(v[0], v[1]))
        self._phi = float(np.arctan2(v[1], v[0]))
        self._v = v

    def camera_in_uav(self, angles) -> np.ndarray:
        """(3, 3) camera body frame -> UAV body frame at gimbal angles (a₁, a₂) rad."""
        a1, a2 = angles
        return self.r_i @ _rot_z(a1) @ self._r_y @ _rot_z(a2) @ self.r_j.T

    def angles(self, uav_R: np.ndarray, camera_R: np.ndarray) -> np.ndarray:
        """(2,) encoder angles from the UAV's and the camera body's (3, 3) body -> world rotations."""
        rel = (uav_R @ self.r_i).T @ (camera_R @ self.r_j)
        return np.array([np.arctan2(rel[1, 2], rel[0, 2]), np.arctan2(rel[2, 1], -rel[2, 0])])

    def aim(self, direction_uav, near, tilt_limits=None) -> np.ndarray:
        """(2,) angles pointing the optical axis along ``direction_uav`` (UAV frame), the
        solution nearest the angles ``near`` (two exist: tilt one way or flipped over) among
        those with the tilt within ``tilt_limits`` (rad; None: any)."""
        w = self.r_i.T @ (np.asarray(direction_uav, float) / np.linalg.norm(direction_uav))
        near = np.asarray(near, float)
        c = np.clip(-w[2] / max(self._rho, 1e-12), -1.0, 1.0)
        best = None
        for sign in (1.0, -1.0):
            a2 = sign * np.arccos(c) - self._phi
            u = self._r_y @ _rot_z(a2) @ self._v
            a1 = np.arctan2(w[1], w[0]) - np.arctan2(u[1], u[0])
            cand = near + _wrap(np.array([a1, a2]) - near)
            if tilt_limits is not None and not tilt_limits[0] <= cand[1] <= tilt_limits[1]:
                turns = cand[1] + 2 * np.pi * np.arange(-2, 3)       # the same tilt, whole turns apart
                inside = turns[(turns >= tilt_limits[0]) & (turns <= tilt_limits[1])]
                if inside.size:
                    cand[1] = inside[np.argmin(np.abs(inside - near[1]))]
            cost = np.abs(cand - near).sum()
            if tilt_limits is not None and not tilt_limits[0] <= cand[1] <= tilt_limits[1]:
                cost += 100.0 + abs(cand[1] - np.clip(cand[1], *tilt_limits))
            if best is None or cost < best[0]:
                best = (cost, cand)
        return best[1]


# --- the controller -------------------------------------------------------------------------


@dataclass(frozen=True)
class GimbalTrackerConfig:
    """Gains, limits and recovery timing of :class:`GimbalTracker` (angles rad, times s).

    The integral gain is off by default: with ``kp = 1`` the loop points the camera in one
    frame, the servo has no steady-state error to remove (the camera's centre of mass is on
    the joint), and a moving target is followed by the bearing-rate feed-forward; an integral
    then only adds an offset that decays at ``ki`` (docs/tracking.md, "What runs")."""

    kp: float = 1.0                         # on the angle error a* - a (1: point in one frame)
    ki: float = 0.0                         # 1/s, on the angle error (off: see the class doc)
    integral_limit: float = 0.05            # rad, anti-windup clip of ki * integral
    lead_s: float | None = None             # bearing-rate feed-forward; None: one frame + 20 ms servo lag
    max_rate: float = 10.0                  # rad/s, command slew limit per axis
    tilt_limits: tuple[float, float] | None = None    # rad, the tilt's mechanical range (None: unlimited)
    hold_frames: int = 2                    # frames holding the command after a loss
    predict_s: float = 1.0                  # s pointing along the predicted bearing (or a cue) after that
    search_pan_rate: float = 3.0            # rad/s, the search turns the pan round at this rate
    search_rows: int = 5                    # raster rows of the search: the last tilt, then above and below
    gate_deg: float | None = 5.0            # deg, detections farther than this plus the target's angular
                                            # radius from the team's point are dropped (module doc; None: no gate)

    def __post_init__(self):
        for name in ("kp", "max_rate", "search_pan_rate", "search_rows"):
            if not getattr(self, name) > 0:
                raise PerceptionError(f"GimbalTrackerConfig.{name} must be positive, got {getattr(self, name)}")
        for name in ("ki", "integral_limit", "predict_s"):
            if not getattr(self, name) >= 0:
                raise PerceptionError(f"GimbalTrackerConfig.{name} must be >= 0, got {getattr(self, name)}")
        if self.gate_deg is not None and not 0 < self.gate_deg <= 180:
            raise PerceptionError(f"GimbalTrackerConfig.gate_deg must be in (0, 180] deg or None, got {self.gate_deg}")
        if self.tilt_limits is not None and not self.tilt_limits[0] < self.tilt_limits[1]:
            raise PerceptionError(f"GimbalTrackerConfig.tilt_limits must be (low, high) with low < high, "
                                  f"got {self.tilt_limits}")


TRACK, HOLD, PREDICT, SEARCH = "track", "hold", "predict", "search"


class GimbalTracker:
    """Pan/tilt commands of one gimbal camera from its detections (see the module doc).

    ``geometry``: the gimbal's :class:`GimbalGeometry`; ``intr``: the camera's intrinsics;
    ``frame_dt``: s between frames.
    """

    def __init__(self, geometry: GimbalGeometry, intr: Intrinsics, frame_dt: float,
                 config: GimbalTrackerConfig = GimbalTrackerConfig(), initial_command=(0.0, 0.0)):
        if not frame_dt > 0:
            raise PerceptionError(f"frame_dt must be positive, got {frame_dt}")
        self.geometry, self.intr, self.dt, self.config = geometry, intr, float(frame_dt), config
        self.lead = config.lead_s if config.lead_s is not None else self.dt + 0.02
        self.command = np.asarray(initial_command, float).copy()
        self.integral = np.zeros(2)
        self.last_bearing: np.ndarray | None = None      # (3,) world unit vector at the last detection
        self.bearing_rate = np.zeros(3)                  # (3,) 1/s, world
        self.last_seen_t: float | None = None
        self.lost_frames = 0
        self.mode = SEARCH
        self.uav_omega: np.ndarray | None = None
        self.search_t0: float | None = None
        self.search_centre: np.ndarray | None = None

    def bearing(self, pixel, camera_R: np.ndarray) -> np.ndarray:
        """(3,) world unit bearing of ``pixel`` (u, v) from a camera with OpenCV -> world rotation ``camera_R``."""
        u, v = pixel
        ray = camera_R @ np.array([(u - self.intr.cx) / self.intr.fx, (v - self.intr.cy) / self.intr.fy, 1.0])
        return ray / np.linalg.norm(ray)

    def _limit(self, target: np.ndarray) -> np.ndarray:
        step = np.clip(_wrap(target - self.command), -self.config.max_rate * self.dt, self.config.max_rate * self.dt)
        cmd = self.command + step
        if self.config.tilt_limits is not None:
            cmd[1] = np.clip(cmd[1], *self.config.tilt_limits)
        return cmd

    def _aim(self, direction_world, uav_R, near) -> np.ndarray:
        if self.uav_omega is not None:      # the UAV's attitude one lead time ahead
            uav_R = uav_R @ _rotvec_matrix(self.uav_omega * self.lead)
        return self.geometry.aim(uav_R.T @ direction_world, near, self.config.tilt_limits)

    def update(self, t: float, detections: Sequence, angles, uav_R: np.ndarray, camera_R: np.ndarray,
               cue_direction=None, uav_omega=None) -> np.ndarray:
        """The command (2,) rad to hold until the next frame.

        ``t``: s, the frame's time; ``detections``: best first; ``angles``: (2,) encoder
        angles; ``uav_R``: (3, 3) UAV body -> world; ``camera_R``: (3, 3) OpenCV camera frame
        -> world; ``cue_direction``: optional (3,) world direction to the target from
        elsewhere (used while the target is lost); ``uav_omega``: optional (3,) rad/s, the UAV's
        body-frame angular velocity (its rotation over the lead time is compensated).
        """
        cfg = self.config
        self.uav_omega = None if uav_omega is None else np.asarray(uav_omega, float)
        angles = np.asarray(angles, float)
        if len(detections):
            b = self.bearing(box_centre(detections[0].box), camera_R)
            if self.last_bearing is not None and self.lost_frames == 0:
                rate = (b - self.last_bearing) / self.dt
                self.bearing_rate = 0.5 * self.bearing_rate + 0.5 * rate
            else:
                self.bearing_rate = np.zeros(3)
            self.last_bearing, self.last_seen_t, self.lost_frames = b, t, 0
            self.mode, self.search_t0 = TRACK, None
            aim = self._aim(b + self.bearing_rate * self.lead, uav_R, angles)
            error = _wrap(aim - angles)
            self.integral = np.clip(self.integral + error * self.dt, -cfg.integral_limit / max(cfg.ki, 1e-12),
                                    cfg.integral_limit / max(cfg.ki, 1e-12))
            target = angles + cfg.kp * error + cfg.ki * self.integral
            self.command = self._limit(target)
            return self.command.copy()

        self.lost_frames += 1
        self.integral[:] = 0.0
        since = np.inf if self.last_seen_t is None else t - self.last_seen_t
        if self.last_seen_t is not None and self.lost_frames <= cfg.hold_frames:
            self.mode = HOLD
            return self.command.copy()
        direction = None
        if cue_direction is not None:
            direction = np.asarray(cue_direction, float)
        elif self.last_bearing is not None and since <= cfg.hold_frames * self.dt + cfg.predict_s:
            direction = self.last_bearing + self.bearing_rate * min(since + self.lead, 0.5)
        if direction is not None and np.linalg.norm(direction) > 1e-9:
            self.mode, self.search_t0 = PREDICT, None
            self.command = self._limit(self._aim(direction, uav_R, self.command))
            return self.command.copy()
        # search: a raster; the pan turns round 1.25 times per row (the overlap catches a target
        # that moved on while the row began), rows 0.7 fields of view apart in tilt, first at
        # the last tilt, then alternately above and below it
        if self.mode != SEARCH or self.search_t0 is None:
            self.mode, self.search_t0, self.search_centre = SEARCH, t, self.command.copy()
        s = t - self.search_t0 + self.dt
        row = int(s * cfg.search_pan_rate / (2.5 * np.pi)) % cfg.search_rows
        step = 0.7 * 2 * np.arctan(self.intr.height / (2 * self.intr.fy))
        offset = step * ((row + 1) // 2) * (1 if row % 2 else -1)
        target = self.search_centre + np.array([cfg.search_pan_rate * s, offset])
        step_pan = cfg.search_pan_rate * self.dt
        self.command = np.array([self.command[0] + step_pan, self._limit(target)[1]])
        if cfg.tilt_limits is not None:
            self.command[1] = np.clip(self.command[1], *cfg.tilt_limits)
        return self.command.copy()


# --- closed loop in the simulator -----------------------------------------------------------


def gimbal_cameras(config) -> list[tuple[str, object]]:
    """``[(uav body, camera config), ...]`` of every gimbal camera, in the simulator's gimbal order."""
    return [(q.body, c) for q in config.quadrotors for c in q.cameras if c.mount == "gimbal"]


class _SkyRenderer(Renderer):
    """The renderer for a tracking camera: it may look above the horizon (the target is often
    higher than the UAV), so the check that a camera sees ground (needed by VIO) is skipped."""

    def _check_ground(self, name, columns, poses, rows):
        return None


def check_tracking_scene(config) -> None:
    """Raise unless the scene has a target and a gimbal camera on at least one UAV."""
    if getattr(config, "target", None) is None:
        raise PerceptionError(f"scene '{config.name}' has no target; tracking needs a target: block")
    if not gimbal_cameras(config):
        fixed = [c.name for q in config.quadrotors for c in q.cameras]
        raise PerceptionError(
            f"scene '{config.name}' has no gimbal camera (cameras: {', '.join(fixed) or 'none'}); add one with "
            f"mount: gimbal under a quadrotor's cameras: (see configs/capture_falling_gimbals.yaml)")


@dataclass
class TrackingRecord:
    """What the closed loop saw and did, per frame and gimbal camera (``F`` frames, ``G`` cameras)."""

    cameras: tuple[str, ...]
    uavs: tuple[str, ...]
    t: np.ndarray                   # (F,) s
    camera_R: np.ndarray            # (F, G, 3, 3) OpenCV camera frame -> world (true)
    camera_p: np.ndarray            # (F, G, 3) m, optical centre (true)
    angles: np.ndarray              # (F, G, 2) rad, encoder angles at the frame
    command: np.ndarray             # (F, G, 2) rad, command set after the frame
    mode: np.ndarray                # (F, G) str, tracker mode after the frame
    det_box: np.ndarray             # (F, G, 4) px, best detection (NaN: none)
    true_box: np.ndarray            # (F, G, 4) px, visible ground-truth box (NaN: none visible)
    true_centre: np.ndarray         # (F, G, 2) px, projection of the target's centre
    true_depth: np.ndarray          # (F, G) m, along the optical axis
    visible_fraction: np.ndarray    # (F, G) visible target pixels / its unoccluded silhouette's
    target_pos: np.ndarray          # (F, 3) m, true target centre
    target_vel: np.ndarray          # (F, 3) m/s, true target velocity
    target_radius: float            # m
    intr: Intrinsics
    columns: dict = field(default_factory=dict)    # trajectory columns, one row per frame

    def in_view(self) -> np.ndarray:
        """(F, G) bool: the target's centre projects inside the image, in front of the camera."""
        u, v = self.true_centre[..., 0], self.true_centre[..., 1]
        return ((self.true_depth > 0) & (u >= -0.5) & (u <= self.intr.width - 0.5)
                & (v >= -0.5) & (v <= self.intr.height - 0.5))

    def pixel_error(self) -> np.ndarray:
        """(F, G) px, distance of the target's projected centre from the image centre (NaN behind the camera)."""
        d = np.hypot(self.true_centre[..., 0] - self.intr.cx, self.true_centre[..., 1] - self.intr.cy)
        return np.where(self.true_depth > 0, d, np.nan)

    @classmethod
    def load_npz(cls, path) -> "TrackingRecord":
        """A record written by :meth:`save_npz` (``scripts/perceive.py --track`` writes
        ``tracking.npz``), e.g. to localise again with other settings; ``columns`` stay empty."""
        try:
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as err:
            raise PerceptionError(f"{path}: not a tracking record ({err})") from None
        names = [f.name for f in dataclasses.fields(cls) if f.name not in ("intr", "columns")]
        missing = [n for n in names + ["intr"] if n not in data.files]
        if missing:
            raise PerceptionError(f"{path}: not a tracking record of this version (missing {', '.join(missing)}); "
                                  f"write it with scripts/perceive.py --track")
        w, h, fx, fy, cx, cy = data["intr"]
        fields = {n: data[n] for n in names}
        fields["cameras"] = tuple(str(c) for c in fields["cameras"])
        fields["uavs"] = tuple(str(u) for u in fields["uavs"])
        fields["target_radius"] = float(fields["target_radius"])
        return cls(intr=Intrinsics(width=int(w), height=int(h), fx=float(fx), fy=float(fy), cx=float(cx),
                                   cy=float(cy)), **fields)

    def save_npz(self, path) -> None:
        np.savez_compressed(path, **{f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                                     if f.name not in ("intr", "columns")},
                            intr=np.array([self.intr.width, self.intr.height, self.intr.fx, self.intr.fy,
                                           self.intr.cx, self.intr.cy]))


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


def _point_at_start(config, scene, state):
    """A copy of ``config`` whose gimbal cameras start pointed at the target's start position."""
    bi = {n: i for i, n in enumerate(scene.body_names)}
    target = np.asarray(state.phys.body_pos[bi[config.target.name]], float)
    quads = []
    for q in config.quadrotors:
        cams = []
        for c in q.cameras:
            if c.mount == "gimbal":
                uR = quat_to_matrix(np.asarray(state.phys.body_quat[bi[q.body]], float))
                d = target - np.asarray(state.phys.body_pos[bi[c.name]], float)
                a = GimbalGeometry(c).aim(uR.T @ d, c.command.angle)
                c = c.model_copy(update={"command": c.command.model_copy(update={"angle": (float(a[0]), float(a[1]))})})
            cams.append(c)
        quads.append(q.model_copy(update={"cameras": cams}))
    return config.model_copy(update={"quadrotors": quads})


def _state_columns(scene, state) -> dict[str, np.ndarray]:
    """One-row trajectory columns (time, poses, point positions) of a simulator state."""
    phys = state.phys
    cols = {"time": np.array([float(state.time)])}
    pp, bp, bq = np.asarray(phys.point_pos), np.asarray(phys.body_pos), np.asarray(phys.body_quat)
    for i, n in enumerate(scene.point_names):
        for c, a in enumerate("xyz"):
            cols[f"{n}_{a}"] = pp[i, c:c + 1].astype(float)
    for i, n in enumerate(scene.body_names):
        for c, a in enumerate("xyz"):
            cols[f"{n}_{a}"] = bp[i, c:c + 1].astype(float)
        for c, a in enumerate("wxyz"):
            cols[f"{n}_q{a}"] = bq[i, c:c + 1].astype(float)
    return cols


def _detect(renderer, detector, cams, geoms, cols, bq, bi, t, force_loss, hint_of=None):
    """Every gimbal camera's frame at this row, its detections (none inside ``force_loss``),
    its gimbal angles and its UAV's attitude. ``hint_of(g, frame)``: where camera ``g``
    expects the target (a :class:`RegionHint` or None), for a detector that takes hints."""
    frames, dets, angles, uav_Rs = [], [], [], []
    hints = getattr(detector, "accepts_hints", False) and hint_of is not None
    for g, (uav, cam) in enumerate(cams):
        frame = renderer.render(cols, cam.name, 0)
        found = list(detector(frame, hint_of(g, frame)) if hints else detector(frame))
        if force_loss is not None and force_loss[0] <= t < force_loss[1]:
            found = []
        uR = quat_to_matrix(bq[bi[uav]])
        angles.append(geoms[g].angles(uR, quat_to_matrix(bq[bi[cam.name]])))
        frames.append(frame)
        dets.append(found)
        uav_Rs.append(uR)
    return frames, dets, angles, uav_Rs


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


def _steer(trackers, t, frames, dets, angles, uav_Rs, omegas, intr, radius, cue, cooperative_cue,
           range_sigma: float = 0.05):
    """Each tracker's gimbal command from its detections, or, without one, from the start
    cue (``cue``, a world point, before its first detection) or from the point the cameras
    that see the target locate (``cooperative_cue``)."""
    seen = [g for g in range(len(trackers)) if dets[g]]
    commands = []
    for g, tracker in enumerate(trackers):
        aim = None
        if cue is not None and not dets[g] and tracker.last_seen_t is None:
            aim = cue - frames[g].p
        elif cooperative_cue and not dets[g] and any(s != g for s in seen):
            point = _team_point([frames[s] for s in seen if s != g], [dets[s][0] for s in seen if s != g],
                                intr, radius, range_sigma)
            if point is not None:
                aim = point - frames[g].p
        commands.append(tracker.update(t, dets[g], angles[g], uav_Rs[g], frames[g].R, aim, uav_omega=omegas[g]))
    return np.asarray(commands, float)


def _record(rec: dict, t, frames, angles, commands, trackers, dets, target_pos, target_vel) -> None:
    """Append one frame's row to the record."""
    tv = [f.target for f in frames]
    rec["t"].append(t)
    rec["camera_R"].append([f.R for f in frames])
    rec["camera_p"].append([f.p for f in frames])
    rec["angles"].append(angles)
    rec["command"].append(commands.copy())
    rec["mode"].append([tr.mode for tr in trackers])
    rec["det_box"].append([d[0].box if d else np.full(4, np.nan) for d in dets])
    rec["true_box"].append([v.box if v.box is not None else np.full(4, np.nan) for v in tv])
    rec["true_centre"].append([v.centre for v in tv])
    rec["true_depth"].append([v.depth for v in tv])
    rec["visible_fraction"].append([v.visible_fraction for v in tv])
    rec["target_pos"].append(target_pos)
    rec["target_vel"].append(target_vel)


def _steps_per_frame(scene, frame_rate: float) -> int:
    steps = int(round(1.0 / (frame_rate * scene.dt)))
    if steps < 1 or abs(steps * scene.dt * frame_rate - 1.0) > 1e-6:
        raise PerceptionError(f"frame_rate {frame_rate:g} Hz is not a whole number of simulator steps "
                              f"(dt = {scene.dt:g} s); pick 1 / (k dt), e.g. "
                              f"{1.0 / (round(1 / (frame_rate * scene.dt)) * scene.dt):g} Hz")
    return steps


def _start_cue(config, params, state, target_body: int):
    """``t -> point``: the target's path predicted from its true start state (ballistic for
    a falling target, constant velocity otherwise)."""
    p0 = np.asarray(state.phys.body_pos[target_body], float)
    v0 = np.asarray(state.phys.body_vel[target_body], float)
    g_acc = np.asarray(params.gravity, float) if config.target.behaviour == "falling" else np.zeros(3)

    def cue_point(t):
        return p0 + v0 * t + 0.5 * g_acc * t * t
    return cue_point


def _tracking_scene(config, initial_cue: bool, frame_rate: float):
    """``(config, scene, params, state, steps per frame)`` of a tracking run: the cameras
    pointed at the target's start with ``initial_cue``, one environment, the gimbals' sine
    commands zeroed (the trackers command them)."""
    scene, params, state = build(config)
    if initial_cue:
        config = _point_at_start(config, scene, state)
        scene, params, state = build(config)
    scene = single_env_scene(scene)
    qp = params.quadrotor
    params = params.replace(quadrotor=qp.replace(gimbal_amplitude=0.0 * qp.gimbal_amplitude))
    return config, scene, params, state, _steps_per_frame(scene, frame_rate)


def _finite_poses(state, t: float) -> tuple[np.ndarray, np.ndarray]:
    """The bodies' quaternions and positions; PerceptionError once the simulation is non-finite."""
    bq = np.asarray(state.phys.body_quat, float)
    bp = np.asarray(state.phys.body_pos, float)
    if not (np.all(np.isfinite(bq)) and np.all(np.isfinite(bp))):
        raise PerceptionError(f"the simulation turned non-finite at t = {t:g} s; simulate the scene with "
                              f"scripts/simulate.py to see where")
    return bq, bp


def run_tracking(config, detector: FrameDetector | None = None, intr: Intrinsics | None = None,
                 frame_rate: float = 25.0, tracker_config: GimbalTrackerConfig = GimbalTrackerConfig(),
                 t_end: float | None = None, initial_cue: bool = True, cooperative_cue: bool = True,
                 force_loss: tuple[float, float] | None = None, target_style: str = "auto",
                 range_sigma: float | None = None, progress: bool = True) -> TrackingRecord:
    """Simulate ``config`` (a scene config with gimbal cameras and a target) with every gimbal
    steered by a :class:`GimbalTracker` from its rendered images (see the module doc).

    ``detector``: ``Frame -> detections`` (default: :class:`OracleDetector`); ``intr``: the
    cameras' intrinsics (default: the paper's camera at 640 x 360); ``frame_rate``: Hz, a
    whole number of simulator steps per frame; ``t_end``: s (default: the config's).
    ``initial_cue``: until a camera first detects the target, it points at the target's
    path predicted from its true start state (ballistic for a falling target, constant
    velocity otherwise): the cue that starts a capture; without it the cameras search. ``cooperative_cue``: a
    camera that has lost the target points at the target located by the cameras that see it
    (least squares over their rays and box ranges; one camera with a whole box suffices). ``force_loss``: ``(t0, t1)`` s, a window in which every
    detection is dropped (to test recovery). ``target_style``: how the renderer draws the
    target (:class:`~mysim_jax.perception.render.Renderer`; ``"auto"``: a drone for a
    maneuvering target, else a sphere). ``range_sigma``: the relative noise of ranges from
    box sizes in the teammates' point (the cooperative cue and the region hints; default
    :data:`~mysim_jax.perception.localize.RANGE_SIGMA` of the target's look). A detector
    that takes hints (:class:`RegionDetector`) is told where each camera expects the
    target (:func:`region_hint`, :func:`point_hint`).
    """
    check_tracking_scene(config)
    if not frame_rate > 0:
        raise PerceptionError(f"frame_rate must be positive, got {frame_rate}")
    intr = make_intrinsics(width=640, height=360) if intr is None else intr
    detector = OracleDetector() if detector is None else detector
    config, scene, params, state, steps = _tracking_scene(config, initial_cue, frame_rate)
    frame_dt = steps * scene.dt
    t_end = config.sim.t_end if t_end is None else float(t_end)
    n_frames = int(np.floor(t_end / frame_dt + 1e-9)) + 1
    policy = team_policy(config, scene)
    cams = gimbal_cameras(config)
    names = tuple(c.name for _, c in cams)
    uavs = tuple(u for u, _ in cams)
    geoms = [GimbalGeometry(c) for _, c in cams]
    renderer = _SkyRenderer(config, intr, target_style=target_style)
    trackers = [GimbalTracker(g, intr, frame_dt, tracker_config, c.command.angle) for g, (_, c) in zip(geoms, cams)]
    advance = jax.jit(rollout, static_argnums=(0, 3, 4, 5))
    bi = {n: i for i, n in enumerate(scene.body_names)}
    target = config.target.name

    cue_point = _start_cue(config, params, state, bi[target])
    range_sigma = RANGE_SIGMA[auto_target_style(config)] if range_sigma is None else float(range_sigma)
    memory = _RegionMemory(len(cams), (tracker_config.hold_frames + 1) * frame_dt, intr, config.target.radius,
                           range_sigma)
    rec = {k: [] for k in ("t", "camera_R", "camera_p", "angles", "command", "mode", "det_box", "true_box",
                           "true_centre", "true_depth", "visible_fraction", "target_pos", "target_vel")}
    rows = []
    bar = tqdm(total=n_frames, desc="track (render, detect, steer, simulate)", unit="frame", disable=not progress)
    for k in range(n_frames):
        cols = _state_columns(scene, state)
        rows.append(cols)
        t = float(cols["time"][0])
        bq, bp = _finite_poses(state, t)
        cue_now = cue_point(t) if initial_cue else None
        hint_of = lambda g, frame: memory.hint(g, trackers[g], t, frame, cue_now)  # noqa: E731
        frames, dets, angles, uav_Rs = _detect(renderer, detector, cams, geoms, cols, bq, bi, t, force_loss, hint_of)
        if tracker_config.gate_deg is not None:
            ref_of = lambda g: cue_point(t) if initial_cue and trackers[g].last_seen_t is None else None  # noqa: E731
            dets = _associate_all(dets, frames, ref_of, tracker_config.gate_deg, intr, config.target.radius)
        memory.update(t, frames, dets)
        omegas = [np.asarray(state.phys.body_angvel[bi[u]], float) for u in uavs]
        commands = _steer(trackers, t, frames, dets, angles, uav_Rs, omegas, intr, config.target.radius,
                          cue_point(t) if initial_cue else None, cooperative_cue, range_sigma)
        _record(rec, t, frames, angles, commands, trackers, dets, bp[bi[target]],
                np.asarray(state.phys.body_vel[bi[target]], float))
        bar.update(1)
        if k == n_frames - 1:
            break
        qp = params.quadrotor
        params = params.replace(quadrotor=qp.replace(gimbal_angle=jax.numpy.asarray(commands, qp.gimbal_angle.dtype)))
        state, _ = advance(scene, params, state, steps, steps, policy)
    bar.close()
    return TrackingRecord(cameras=names, uavs=uavs, intr=intr, target_radius=float(config.target.radius),
                          columns={key: np.concatenate([r[key] for r in rows]) for key in rows[0]},
                          **{k: np.asarray(v) for k, v in rec.items()})


MOVING_SPEED = 0.5      # m/s: above this the target counts as moving (falling, evading), below as held


def target_moving(record: TrackingRecord) -> np.ndarray:
    """(F,) bool: frames in which the target's speed (central differences) is above MOVING_SPEED."""
    if len(record.t) < 2:
        return np.zeros(len(record.t), bool)
    v = np.gradient(record.target_pos, record.t, axis=0)
    return np.linalg.norm(v, axis=1) > MOVING_SPEED


def tracking_metrics(record: TrackingRecord) -> dict:
    """In-view fraction, detection fraction and pixel error of the target's centre from the
    image centre (px; mean and 95th percentile over frames with the target in front), per
    camera, over all, and over the frames with the target moving (:func:`target_moving`)."""
    inview = record.in_view()
    err = record.pixel_error()
    detected = np.all(np.isfinite(record.det_box), axis=-1)

    def stats(sel):
        e = err[sel]
        e = e[np.isfinite(e)]
        iv = inview[sel]
        return {"camera_frames": int(iv.size), "in_view_fraction": float(iv.mean()) if iv.size else None,
                "detected_fraction": float(detected[sel].mean()) if iv.size else None,
                "pixel_error_mean_px": float(e.mean()) if e.size else None,
                "pixel_error_p95_px": float(np.percentile(e, 95)) if e.size else None,
                "pixel_error_median_px": float(np.median(e)) if e.size else None}

    out = {"all": stats(np.ones_like(inview, bool))}
    moving = target_moving(record)
    out["target_moving"] = stats(np.broadcast_to(moving[:, None], inview.shape))
    out["target_moving"]["note"] = f"frames with the target faster than {MOVING_SPEED:g} m/s"
    for g, name in enumerate(record.cameras):
        sel = np.zeros_like(inview, bool)
        sel[:, g] = True
        out[name] = stats(sel)
    modes, counts = np.unique(record.mode, return_counts=True)
    out["modes"] = {str(m): int(c) for m, c in zip(modes, counts)}
    out["image_centre_px"] = [record.intr.cx, record.intr.cy]
    return out


def make_detector(kind: str, weights=None, noise_px: float = 1.0, miss_rate: float = 0.0, seed: int = 0,
                  region: bool = True):
    """The frame detector a tracking run uses: ``"oracle"`` (the true box with edge noise
    and misses) or ``"learned"`` (the CNN, with ``weights`` or the committed ones; with
    ``region`` a :class:`RegionDetector`, which looks where the tracker expects the target,
    else the whole image every frame). PerceptionError for weights that do not fit the
    choice or do not exist."""
    if weights is not None and kind != "learned":
        raise PerceptionError("--weights is for --detector learned")
    if weights is not None and not Path(weights).is_file():
        raise PerceptionError(f"--weights {weights}: no such file; train one with scripts/train_detector.py")
    if kind == "oracle":
        return OracleDetector(noise_px=noise_px, miss_rate=miss_rate, seed=seed)
    cnn = load_detector(weights)
    return RegionDetector(cnn) if region else image_detector(cnn)


def make_pose_noise(position_m: float, rotation_rad: float, correlation_time: float = 0.0, seed: int = 0) -> PoseNoise:
    """Camera-pose noise for localisation (standard deviations, Gauss-Markov correlation
    time; 0: white). PerceptionError for a negative value."""
    if not (position_m >= 0 and rotation_rad >= 0 and correlation_time >= 0):
        raise PerceptionError(f"--pose-noise values and --pose-noise-time must be >= 0, got "
                              f"{[position_m, rotation_rad]}, {correlation_time}")
    return PoseNoise(position_m=position_m, rotation_rad=rotation_rad, seed=seed, correlation_time=correlation_time)
