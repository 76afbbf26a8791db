"""Pinhole cameras: intrinsics from the paper's Table camera, poses from a saved run.

Intrinsics. The paper's camera has a 50 mm lens, a 36 x 24 mm sensor, 1920 x 1080 pixels,
its principal point at the image centre and no distortion. A 36 x 24 mm sensor is 3:2 and
the image is 16:9, so the two cannot both fill the sensor with square pixels; as Blender
does (sensor fit ``auto``, which the paper's rendering used), the sensor width spans the
image width and the pixels are square:

    fx = fy = f / sensor_width * W        (2666.7 px at 1920 px)

so the vertical field of view is that of a 36 * H / W = 20.25 mm tall sensor. Smaller
images keep the field of view: every intrinsic scales with the width.

Frames. A camera body of the scene (a ``cameras:`` entry of a quadrotor) has its optical
axis along the body's +x axis (the UAV's nose, with the default mount), image right along
the body's -y and image down along the body's -z. Images use the OpenCV convention: the
camera frame ``c`` has x right, y down, z forward, and a pixel (u, v) of a point
X_c = (x, y, z) is (fx x / z + cx, fy y / z + cy), u to the right, v down, the centre of
the top-left pixel at (0, 0).

Poses come from the trajectory CSV that ``scripts/simulate.py`` writes
(:mod:`mysim_jax.io.trajectory`): the camera body's position and scalar-first body→world
quaternion per output row; a free camera's (one that is no body of the scene) from
:func:`look_at`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from typing import Annotated

from pydantic import Field

from mysim_jax.core.config_base import PosFloat, StrictModel
from mysim_jax.core.npgeom import quat_to_matrix

Pixels = Annotated[int, Field(gt=0, le=16384)]

# Camera body frame -> OpenCV camera frame: the columns are the OpenCV axes (x right,
# y down, z forward) written in the camera body frame (x forward, y left, z up).
R_BODY_CV = np.array([[0.0, 0.0, 1.0],
                      [-1.0, 0.0, 0.0],
                      [0.0, -1.0, 0.0]])


class PerceptionError(ValueError):
    """Input the perception stage cannot use. The message names it and says how to fix it."""


class PinholeConfig(StrictModel):
    """A pinhole camera (paper Table camera). Distortion is not modelled (the table's is zero)."""

    focal_length_mm: PosFloat = 50.0
    sensor_width_mm: PosFloat = 36.0
    sensor_height_mm: PosFloat = 24.0     # recorded; the width sets the pixel scale (see module doc)
    width: Pixels = 1920                  # px
    height: Pixels = 1080                 # px


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels: image size, focal lengths and principal point."""

    width: int      # px
    height: int     # px
    fx: float       # px
    fy: float       # px
    cx: float       # px
    cy: float       # px

    @property
    def K(self) -> np.ndarray:
        """(3, 3) camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fov_deg(self) -> tuple[float, float]:
        """Horizontal and vertical field of view (degrees)."""
        return (float(np.degrees(2 * np.arctan(self.width / (2 * self.fx)))),
                float(np.degrees(2 * np.arctan(self.height / (2 * self.fy)))))


def intrinsics(config: PinholeConfig | None = None, width: int | None = None, height: int | None = None) -> Intrinsics:
    """Intrinsics of ``config`` (default: the paper's camera) at ``width`` x ``height`` pixels.

    ``width``/``height`` override the config's image size (a smaller image of the same camera:
    same field of view). The principal point is the image centre, (960, 540) at 1920 x 1080
    as in the paper's table.
    """
    config = config or PinholeConfig()
    w = config.width if width is None else width
    h = config.height if height is None else height
    for name, value in (("width", w), ("height", h)):
        if not isinstance(value, (int, np.integer)) or value < 1:
            raise PerceptionError(f"image {name} must be a positive whole number of pixels, got {value!r}")
    if w > 16384 or h > 16384:
        raise PerceptionError(f"image size {w} x {h} is larger than 16384 px on a side; render a smaller image")
    fx = config.focal_length_mm / config.sensor_width_mm * w
    return Intrinsics(width=int(w), height=int(h), fx=fx, fy=fx, cx=w / 2.0, cy=h / 2.0)


@dataclass(frozen=True)
class CameraPoses:
    """World poses of a camera's OpenCV frame over a run: X_world = R @ X_c + p."""

    name: str
    t: np.ndarray   # (N,) s
    R: np.ndarray   # (N, 3, 3) OpenCV camera frame -> world
    p: np.ndarray   # (N, 3) m, optical centre in the world


def body_pose_columns(columns: dict[str, np.ndarray], name: str) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) positions and (N, 4) scalar-first quaternions of body ``name`` from trajectory columns."""
    keys = [f"{name}_{k}" for k in ("x", "y", "z", "qw", "qx", "qy", "qz")]
    missing = [k for k in keys if k not in columns]
    if missing:
        bodies = sorted({k[:-3] for k in columns if k.endswith("_qw")})
        raise PerceptionError(f"the trajectory has no pose of '{name}' (missing columns {', '.join(missing)}); "
                              f"bodies with poses: {', '.join(bodies) or 'none'}")
    pos = np.stack([columns[k] for k in keys[:3]], -1).astype(float)
    quat = np.stack([columns[k] for k in keys[3:]], -1).astype(float)
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
        raise PerceptionError(f"the pose of '{name}' has non-finite values; the run diverged (see its summary)")
    return pos, quat


def camera_poses(columns: dict[str, np.ndarray], name: str) -> CameraPoses:
    """Poses of the camera body ``name`` (a scene camera) over a run, in the OpenCV convention."""
    pos, quat = body_pose_columns(columns, name)
    R = quat_to_matrix(quat) @ R_BODY_CV
    return CameraPoses(name=name, t=np.asarray(columns["time"], dtype=float), R=R, p=pos)


def look_at(eye, target, t, up=(0.0, 0.0, 1.0), name: str = "observer") -> CameraPoses:
    """Poses of a free camera at ``eye`` looking at ``target`` ((3,) or (N, 3) m each) at times ``t`` (N,).

    The image's up direction is ``up`` projected on the image plane (world z: no roll).
    """
    t = np.atleast_1d(np.asarray(t, dtype=float))
    eye = np.broadcast_to(np.asarray(eye, dtype=float), (len(t), 3))
    target = np.broadcast_to(np.asarray(target, dtype=float), (len(t), 3))
    z = target - eye
    norm = np.linalg.norm(z, axis=1, keepdims=True)
    if np.any(norm < 1e-9):
        raise PerceptionError("look_at: eye and target coincide; the camera has no direction")
    z = z / norm
    x = np.cross(z, np.asarray(up, dtype=float))
    xn = np.linalg.norm(x, axis=1, keepdims=True)
    if np.any(xn < 1e-9):
        raise PerceptionError("look_at: the camera looks straight along 'up'; pass another up vector")
    x = x / xn
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=-1)
    return CameraPoses(name=name, t=t, R=R, p=eye.copy())


def project(intr: Intrinsics, R: np.ndarray, p: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (..., 2) and depths (...,) along the optical axis of world points (..., 3).

    ``R``, ``p``: one camera pose (OpenCV frame -> world). Points behind the camera get a
    non-positive depth; their pixels are meaningless.
    """
    Xc = (np.asarray(points, dtype=float) - p) @ R     # R^T (X - p), row-wise
    z = Xc[..., 2]
    safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
    uv = np.stack([intr.fx * Xc[..., 0] / safe + intr.cx, intr.fy * Xc[..., 1] / safe + intr.cy], -1)
    return uv, z


def corner_rays(intr: Intrinsics) -> np.ndarray:
    """(4, 3) camera-frame rays through the image's four outer corners (z = 1)."""
    us = np.array([-0.5, intr.width - 0.5])
    vs = np.array([-0.5, intr.height - 0.5])
    return np.array([[(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, 1.0] for v in vs for u in us])


def check_sees_ground(intr: Intrinsics, poses: CameraPoses, ground_z: float = 0.0) -> None:
    """Raise unless the camera is above the ground and sees some of it in every frame.

    A ray's downward component is linear in the pixel, so its largest value over the image
    is at a corner: the camera sees ground iff a corner ray points down.
    """
    below = np.nonzero(poses.p[:, 2] <= ground_z)[0]
    if below.size:
        i = below[0]
        raise PerceptionError(f"camera '{poses.name}' is at or below the ground (z = {poses.p[i, 2]:.3g} m) at "
                              f"t = {poses.t[i]:g} s; it sees no ground")
    down = -(poses.R @ corner_rays(intr).T)[:, 2, :]          # (N, 4)
    blind = np.nonzero(down.max(axis=1) <= 1e-9)[0]
    if blind.size:
        i = blind[0]
        axis = poses.R[i][:, 2]
        raise PerceptionError(
            f"camera '{poses.name}' sees nothing of the ground at t = {poses.t[i]:g} s (and {blind.size - 1} other "
            f"frames): its optical axis points along {np.round(axis, 3).tolist()} (world), and a "
            f"{intr.fov_deg[1]:.1f} deg tall field of view does not reach below the horizon. Pitch the camera "
            f"down (its 'quat' in the scene's cameras: entry) or fly the UAV level"
        )
