"""Pan/tilt commands of one gimbal camera from its detections: the gimbal's kinematics
(:class:`GimbalGeometry`) and the tracking controller with its recovery when the target is
lost (:class:`GimbalTracker`). The closed loop that renders, detects and steers every gimbal
in the simulator is :mod:`mysim_jax.perception.track`.

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
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from mysim_jax.control.build import R_Y_90, gimbal_marker_frames
from mysim_jax.core.npgeom import rotvec_to_matrix
from mysim_jax.perception.camera import Intrinsics, PerceptionError
from mysim_jax.perception.track_detectors import box_centre


# --- gimbal geometry ------------------------------------------------------------------------


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


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
                                            # radius from the team's point are dropped (track_cues; None: no gate)

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
            uav_R = uav_R @ rotvec_to_matrix(self.uav_omega * self.lead)
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
