"""Camera images of a saved run: textured ground, sky, UAVs, target, net and tethers, with a
depth image, an object-id image and the target's ground-truth boxes.

This is the post-processing renderer of paper Sec. 2.3 (Alg. blender_rendering) without
Blender: it reads the poses of a run's bodies and the positions of its net's masses from the
trajectory columns (:mod:`mysim_jax.io.trajectory`), places a model of every object there,
and draws what one camera (:mod:`mysim_jax.perception.camera`: pinhole, OpenCV frame) sees
at one output row::

    run = load_run("out/capture")                       # trajectory.csv + config.yaml
    renderer = Renderer(run.config, intrinsics(width=640, height=360))
    frame = renderer.render(run.columns, "cam0", row=40)
    frame.image, frame.depth, frame.ids, frame.target.box
    write_video(renderer.render_many(run.columns, "cam0"), "cam0.mp4", fps=run.fps)

What is drawn:

* the ground plane (:mod:`mysim_jax.perception.ground`: procedural, anti-aliased texture),
  coloured by a palette, lit by the sun and fading into haze with distance, and a sky whose
  colour goes from the horizon's to the zenith's with the ray's elevation;
* every quadrotor: a hull, four arms to its rotor positions (from the scene's rotor layout;
  the front pair, body +x, in red so the heading shows), motors and rotor discs;
* the target: a sphere of its radius, or (``target_style``; default for a maneuvering target)
  a small quadrotor that fits inside that sphere;
* the net's lines and the tethers as capsules of the lines' diameter, through every lumped
  mass, never thinner on screen than ``min_line_px`` (so a line stays visible at any range);
  a tether ends at its marker on the UAV;
* every camera body of the scene (a small box with a lens), except the viewing camera;
  the viewing camera's own UAV and its other cameras are left out unless ``draw_own_uav``.

Objects are ray cast analytically (:mod:`mysim_jax.perception.render_raster`): each pixel
shows the nearest surface (a depth test against the ground and every other object), and
silhouettes are anti-aliased from their exact distance to the pixel centre. A pixel belongs
to an object in ``Frame.ids`` when the object covers its centre. Lighting: a sun (Lambert)
and a sky/ground hemisphere; no shadows.

Target boxes (:class:`TargetView`) come from the rendered id image, so occlusion counts:
``box`` bounds the target's visible pixels, ``full_box`` its silhouette with nothing in
front (the ground and image borders still clip), ``visible_fraction`` is their pixel ratio.
Boxes are in the image's pixel coordinates (centre of the top-left pixel at (0, 0), as
:func:`~mysim_jax.perception.camera.project`) and enclose whole pixels: ``u_min`` is the left
edge of the leftmost pixel (its index - 0.5), ``u_max`` the right edge of the rightmost.

Speed: the cost is the ground (a dozen full-image operations) plus the candidate pixels of
the objects (an object's screen area, a line's length); BENCHMARKS.md, section (h), has the
frame rates.

This module places the objects at a row and draws them (:class:`Renderer`). The objects'
models are in :mod:`mysim_jax.perception.render_models`; the run folder, :class:`Frame`,
:class:`TargetView` and the video and image writers in :mod:`mysim_jax.perception.render_io`;
:func:`~mysim_jax.perception.camera.look_at` (a free camera) in the camera module. All are
importable from here too.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Iterator, Literal

import numpy as np
from tqdm.auto import tqdm

from mysim_jax.core.npgeom import quat_to_matrix
from mysim_jax.perception.camera import (R_BODY_CV, CameraPoses, Intrinsics, PerceptionError, check_sees_ground,
                                         intrinsics as make_intrinsics, look_at)
from mysim_jax.perception.ground import GroundTexture, view_ground
from mysim_jax.perception.render_io import Frame, Run, TargetView, load_run, write_images, write_video
from mysim_jax.perception.render_models import (CAMERA, FRONT, HULL, LENS, MOTOR, NET, REAR, ROTOR, TARGET,
                                                TARGET_DRONE, TETHER, Model, auto_target_style, body_models,
                                                camera_model, line_segments, quadrotor_model, sphere_model,
                                                stack_models)
from mysim_jax.perception.render_raster import (Capsules, Ellipsoids, Fragments, Lights, capsule_fragments,
                                                composite, ellipsoid_fragments)

# The renderer's public names, with those of the modules it draws from (object models, the
# files and results, a free camera's poses), so that ``from mysim_jax.perception.render
# import ...`` reaches all of them.
__all__ = ["Renderer", "Lighting", "SKY", "GROUND",
           "Frame", "TargetView", "Run", "load_run", "write_video", "write_images", "look_at",
           "Model", "quadrotor_model", "camera_model", "sphere_model", "auto_target_style", "body_models",
           "line_segments", "stack_models", "HULL", "FRONT", "REAR", "MOTOR", "ROTOR", "TARGET", "TARGET_DRONE",
           "NET", "TETHER", "CAMERA", "LENS"]

SKY, GROUND = 0, 1                 # ids of the background in Frame.ids


# --- appearance -----------------------------------------------------------------------------


@dataclass(frozen=True)
class Lighting:
    """Sun, sky and ground colours (RGB in [0, 1]) and haze."""

    sun_azimuth_deg: float = 135.0        # from world +x towards +y
    sun_elevation_deg: float = 50.0
    sun_strength: float = 0.7
    sky_strength: float = 0.45            # ambient from the sky (on a surface facing up)
    ground_strength: float = 0.2          # ambient bounced off the ground (on a surface facing down)
    zenith: tuple[float, float, float] = (0.30, 0.50, 0.84)
    horizon: tuple[float, float, float] = (0.80, 0.86, 0.93)
    ground_dark: tuple[float, float, float] = (0.17, 0.22, 0.10)     # albedo 0
    ground_light: tuple[float, float, float] = (0.62, 0.57, 0.40)    # albedo 1
    visibility_m: float = 1500.0          # haze: half the ground's contrast is gone at 0.69 x this range

    def sun_direction(self) -> np.ndarray:
        """(3,) world unit vector towards the sun."""
        az, el = np.radians(self.sun_azimuth_deg), np.radians(self.sun_elevation_deg)
        return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


_HAZE_LEVELS = 64
_SKY_LEVELS = 256


def _background_lut(lighting: Lighting) -> np.ndarray:
    """(256 * 64 + 256, 3) uint8: ground colour per (albedo byte, haze level), then sky per elevation byte."""
    a = np.arange(256)[:, None, None] / 255.0
    haze = np.arange(_HAZE_LEVELS)[None, :, None] / (_HAZE_LEVELS - 1)
    dark, light = np.asarray(lighting.ground_dark), np.asarray(lighting.ground_light)
    sun = np.sin(np.radians(lighting.sun_elevation_deg)) * lighting.sun_strength
    ground = (dark + (light - dark) * a) * (lighting.sky_strength + max(sun, 0.0))
    horizon, zenith = np.asarray(lighting.horizon), np.asarray(lighting.zenith)
    ground = ground * (1 - haze) + horizon * haze
    e = np.arange(_SKY_LEVELS)[:, None] / (_SKY_LEVELS - 1)
    sky = horizon + (zenith - horizon) * np.sqrt(e)
    lut = np.concatenate([ground.reshape(-1, 3), sky])
    return np.clip(np.round(lut * 255), 0, 255).astype(np.uint8)


# --- the renderer ---------------------------------------------------------------------------


_POSE = ("x", "y", "z", "qw", "qx", "qy", "qz")


def _check_settings(intr: Intrinsics, target_style, min_line_px) -> None:
    """PerceptionError for a camera or a setting the renderer cannot draw with."""
    for name, value in (("width", intr.width), ("height", intr.height)):
        if not isinstance(value, (int, np.integer)) or value < 1:
            raise PerceptionError(f"image {name} must be a positive whole number of pixels, got {value!r}; "
                                  f"make the camera with intrinsics(width=..., height=...)")
    if not (intr.fx > 0 and intr.fy > 0):
        raise PerceptionError(f"focal lengths must be positive, got fx = {intr.fx}, fy = {intr.fy}")
    if abs(intr.fx - intr.fy) > 1e-9 * intr.fx:
        raise PerceptionError(f"the renderer needs square pixels (fx = fy), got fx = {intr.fx}, fy = {intr.fy}")
    if target_style not in ("auto", "sphere", "drone"):
        raise PerceptionError(f"target_style must be 'auto', 'sphere' or 'drone', got {target_style!r}")
    if not min_line_px >= 0:
        raise PerceptionError(f"min_line_px must be >= 0, got {min_line_px}")


class Renderer:
    """Renders camera images of runs of one scene (see the module doc).

    ``config``: the run's scene config (``load_run(...).config``); ``intr``: the camera
    (default: the paper's camera at 1920 x 1080; ``intrinsics(width=640, height=360)`` for a
    smaller image of the same field of view). ``texture``, ``lighting``, ``ground_z`` (m):
    the world. ``target_style``: ``"sphere"``, ``"drone"`` or ``"auto"`` (a drone for a
    maneuvering target). ``min_line_px``: the narrowest a net line or tether is drawn (px).
    ``draw_own_uav``: also draw the viewing camera's UAV and its other cameras. ``hide``:
    bodies never drawn, whatever the camera (e.g. the UAV a free camera is mounted on).
    """

    def __init__(self, config, intr: Intrinsics | None = None, *, texture: GroundTexture | None = None,
                 lighting: Lighting | None = None, ground_z: float = 0.0,
                 target_style: Literal["auto", "sphere", "drone"] = "auto", min_line_px: float = 1.0,
                 draw_own_uav: bool = False, hide: Iterable[str] = ()):
        intr = make_intrinsics() if intr is None else intr
        _check_settings(intr, target_style, min_line_px)
        self.config = config
        self.intr = intr
        self.texture = GroundTexture() if texture is None else texture
        self.lighting = Lighting() if lighting is None else lighting
        self.ground_z = float(ground_z)
        self.min_line_px = float(min_line_px)
        self.draw_own_uav = bool(draw_own_uav)
        self.hide = frozenset(hide)
        self._lut = _background_lut(self.lighting)

        target = getattr(config, "target", None)
        self.target_name = None if target is None else target.name
        bodies, models, self.camera_owner = body_models(config, target_style)
        names = ["sky", "ground"] + bodies
        unknown = sorted(self.hide - set(bodies))
        if unknown:
            raise PerceptionError(f"hide: no body {', '.join(map(repr, unknown))} in the scene; bodies: {', '.join(bodies)}")
        self.cameras: tuple[str, ...] = tuple(self.camera_owner)
        self._bodies = bodies
        self._body_columns = [f"{b}_{k}" for b in bodies for k in _POSE]
        (self._e_owner, self._e_centre, self._e_axes, self._e_semi, self._e_colour,
         self._c_owner, self._c_a, self._c_b, self._c_radius, self._c_colour) = stack_models(models)

        points, segments, radius, colours, self._markers = line_segments(getattr(config, "net", None), bodies, names)
        self._points = points
        self._point_columns = [f"{n}_{a}" for n in points for a in "xyz"]
        seg = np.asarray(segments, dtype=int).reshape(-1, 3)
        # marker m (negative -m-1 ... stored as -(m+1)) -> index len(points) + m
        ends = seg[:, :2].copy()
        ends[ends < 0] = len(points) + (-ends[ends < 0] - 1)
        self._seg_ends = ends
        self._seg_obj = seg[:, 2]
        self._seg_radius = np.asarray(radius, dtype=float)
        self._seg_colour = np.asarray(colours, dtype=float).reshape(-1, 3)
        self.names: tuple[str, ...] = tuple(names)
        self._body_id = {b: names.index(b) for b in bodies}

    # --- inputs ---------------------------------------------------------------------------

    def required_columns(self) -> list[str]:
        """Trajectory columns a render reads: time, body poses, net and tether mass positions."""
        return ["time"] + self._body_columns + self._point_columns

    def check_columns(self, columns: dict[str, np.ndarray]) -> int:
        """Raise unless ``columns`` has every column this scene's render needs; returns the row count."""
        if not isinstance(columns, dict):
            raise PerceptionError(f"columns must be a dict of trajectory columns (read_trajectory_csv), "
                                  f"got {type(columns).__name__}")
        missing = [k for k in self.required_columns() if k not in columns]
        if missing:
            shown = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
            raise PerceptionError(
                f"the trajectory lacks {len(missing)} column(s) the renderer needs for this scene: {shown}. "
                f"Render a run with the config it was simulated with (load_run reads both from its folder); "
                f"scripts/simulate.py writes every pose and mass position")
        n = len(columns["time"])
        if n == 0:
            raise PerceptionError("the trajectory has no rows; the run stopped before its first output")
        return n

    def _camera(self, columns, camera) -> tuple[str, CameraPoses | None]:
        if isinstance(camera, CameraPoses):
            return camera.name, camera
        if not isinstance(camera, str) or camera not in self.camera_owner:
            if self.cameras:
                hint = f"its cameras: {', '.join(self.cameras)}"
            else:
                hint = "it has none (add one under a quadrotor's cameras: in the scene file)"
            raise PerceptionError(f"camera {camera!r} is not in the run; {hint}; or pass a free camera's "
                                  f"CameraPoses, e.g. look_at(eye, target, columns['time'])")
        return camera, None

    def _pose(self, columns, name, poses, row) -> tuple[np.ndarray, np.ndarray]:
        if poses is not None:
            return np.asarray(poses.R[row], float), np.asarray(poses.p[row], float)
        pos = np.array([columns[f"{name}_{a}"][row] for a in "xyz"], dtype=float)
        q = np.array([columns[f"{name}_q{a}"][row] for a in "wxyz"], dtype=float)
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(q))):
            raise PerceptionError(f"the pose of camera '{name}' at row {row} is not finite; the run diverged there")
        return quat_to_matrix(q) @ R_BODY_CV, pos

    def _check_rows(self, rows, n: int, columns) -> list[int]:
        out = []
        for r in rows:
            if isinstance(r, bool) or not isinstance(r, (int, np.integer)):
                raise PerceptionError(f"rows must be whole numbers, got {r!r}")
            if not 0 <= r < n:
                t = columns["time"]
                raise PerceptionError(f"row {r} is out of range: the run has {n} output rows, 0 to {n - 1} "
                                      f"(t = {t[0]:g} to {t[-1]:g} s)")
            out.append(int(r))
        return out

    def _check_ground(self, name, columns, poses, rows):
        if poses is None:
            qs = np.array([[columns[f"{name}_q{a}"][r] for a in "wxyz"] for r in rows], dtype=float)
            ps = np.array([[columns[f"{name}_{a}"][r] for a in "xyz"] for r in rows], dtype=float)
            R = quat_to_matrix(qs) @ R_BODY_CV
        else:
            R, ps = poses.R[rows], poses.p[rows]
        t = np.asarray(columns["time"], float)[rows]
        check_sees_ground(self.intr, CameraPoses(name=name, t=t, R=R, p=ps), self.ground_z)

    # --- rendering ------------------------------------------------------------------------

    def render(self, columns: dict[str, np.ndarray], camera: str | CameraPoses, row: int) -> Frame:
        """The image camera ``camera`` (a scene camera's name, or a free camera's poses over the
        run's rows, e.g. from :func:`look_at`) sees at output row ``row``."""
        n = self.check_columns(columns)
        name, poses = self._camera(columns, camera)
        if poses is not None and len(poses.t) != n:
            raise PerceptionError(f"camera poses '{name}' have {len(poses.t)} rows but the run has {n}; "
                                  f"make them at the run's times (look_at(eye, target, columns['time']))")
        (row,) = self._check_rows([row], n, columns)
        self._check_ground(name, columns, poses, [row])
        return self._render(columns, name, poses, row)

    def render_many(self, columns: dict[str, np.ndarray], camera: str | CameraPoses,
                    rows: Iterable[int] | None = None, progress: bool = True) -> Iterator[Frame]:
        """Frames at ``rows`` (default: every row), one at a time (a 1080p frame holds ~20 MB).

        Every row is checked (range, the camera sees ground) before the first frame is drawn.
        """
        n = self.check_columns(columns)
        name, poses = self._camera(columns, camera)
        if poses is not None and len(poses.t) != n:
            raise PerceptionError(f"camera poses '{name}' have {len(poses.t)} rows but the run has {n}; "
                                  f"make them at the run's times (look_at(eye, target, columns['time']))")
        rows = list(range(n)) if rows is None else self._check_rows(list(rows), n, columns)
        if rows:
            self._check_ground(name, columns, poses, rows)
        return self._iterate(columns, name, poses, rows, progress)

    def _iterate(self, columns, name, poses, rows, progress):
        for r in tqdm(rows, desc=f"render {name}", unit="frame", disable=not progress):
            yield self._render(columns, name, poses, r)

    def _hidden(self, name: str) -> set[str]:
        if name not in self.camera_owner:
            return set(self.hide)
        if self.draw_own_uav:
            return {name} | self.hide
        owner = self.camera_owner[name]
        return {owner} | {c for c, o in self.camera_owner.items() if o == owner} | self.hide

    def _render(self, columns, name, poses, row) -> Frame:
        intr = self.intr
        R, p = self._pose(columns, name, poses, row)
        ground = view_ground(intr, R, p, self.texture, self.ground_z)
        image, back_depth = self._background(ground, R)
        ids = np.where(ground.hit, np.int16(GROUND), np.int16(SKY)).astype(np.int16)
        depth = ground.depth.copy()

        frags, silhouette = self._objects(columns, row, R, p, self._hidden(name))
        flat_img = image.reshape(-1, 3)
        comp = composite(frags, flat_img, back_depth.reshape(-1), background_scale=1.0 / 255.0)
        if comp.pix.size:
            flat_img[comp.pix] = np.round(comp.colour * 255.0).astype(np.uint8)
            hit = comp.hit_obj >= 0
            depth.reshape(-1)[comp.pix[hit]] = comp.hit_depth[hit]
            ids.reshape(-1)[comp.pix[hit]] = comp.hit_obj[hit]
        target = None
        if self.target_name is not None:
            target = self._target_view(columns, row, R, p, comp, silhouette)
        return Frame(image=image, depth=depth, ids=ids, names=self.names, target=target, row=row,
                     t=float(columns["time"][row]), camera=name, R=R, p=p)

    def _background(self, ground, R) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) uint8 ground-and-sky image and (H, W) float32 depth of the background."""
        intr = self.intr
        u = (np.arange(intr.width, dtype=np.float32) - np.float32(intr.cx)) / np.float32(intr.fx)
        v = (np.arange(intr.height, dtype=np.float32) - np.float32(intr.cy)) / np.float32(intr.fy)
        norm = np.sqrt(u[None, :] ** 2 + (v ** 2 + np.float32(1.0))[:, None])        # |ray| (z = 1)
        hit = ground.hit
        # ground: albedo byte x haze level; range = depth |ray|
        haze = np.where(hit, ground.depth, np.float32(0.0)) * norm
        haze *= np.float32(-1.0 / self.lighting.visibility_m)
        np.exp(haze, out=haze)
        index = ((np.float32(1.0) - haze) * np.float32(_HAZE_LEVELS - 1) + np.float32(0.5)).astype(np.int32)
        index += (ground.albedo * np.float32(255.0) + np.float32(0.5)).astype(np.int32) * _HAZE_LEVELS
        # sky: elevation byte of the ray
        Rz = np.asarray(R, float)[2]
        up = (np.float32(Rz[0]) * u)[None, :] + (np.float32(Rz[1]) * v + np.float32(Rz[2]))[:, None]
        up /= norm
        sky = (np.clip(up, 0.0, 1.0) * np.float32(_SKY_LEVELS - 1) + np.float32(0.5)).astype(np.int32)
        sky += 256 * _HAZE_LEVELS
        index = np.where(hit, index, sky)
        return self._lut[index], ground.depth

    def _lights(self, R) -> Lights:
        L = self.lighting
        return Lights(sun=R.T @ L.sun_direction(), up=R.T @ np.array([0.0, 0.0, 1.0]), sun_strength=L.sun_strength,
                      sky_strength=L.sky_strength, ground_strength=L.ground_strength)

    def _objects(self, columns, row, R, p, hidden: set[str]) -> tuple[Fragments, np.ndarray]:
        """Fragments of every drawn object, and the flat pixels of the target's silhouette."""
        intr = self.intr
        vals = np.array([columns[k][row] for k in self._body_columns], dtype=float).reshape(-1, 7)
        bpos, bquat = vals[:, :3], vals[:, 3:]
        finite = np.all(np.isfinite(vals), axis=1)
        if not np.all(finite):
            bad = [b for b, ok in zip(self._bodies, finite) if not ok]
            raise PerceptionError(f"row {row}: the pose of {', '.join(bad)} is not finite; the run diverged there")
        bR = quat_to_matrix(bquat)                                   # (B, 3, 3) body -> world
        # world -> camera: X_c = R^T (X - p)
        Rt = R.T
        lights = self._lights(R)
        drawn = np.array([b not in hidden for b in self._bodies], dtype=bool)

        ek = drawn[self._e_owner] if self._e_owner.size else np.zeros(0, bool)
        eo = self._e_owner[ek]
        e_centre_w = bpos[eo] + np.einsum("nij,nj->ni", bR[eo], self._e_centre[ek])
        ell = Ellipsoids(centre=(e_centre_w - p) @ R,
                         axes=np.einsum("ij,njk->nik", Rt, np.einsum("nij,njk->nik", bR[eo], self._e_axes[ek])),
                         semi=self._e_semi[ek], colour=self._e_colour[ek],
                         obj=np.array([self._body_id[self._bodies[o]] for o in eo], dtype=int))

        ck = drawn[self._c_owner] if self._c_owner.size else np.zeros(0, bool)
        co = self._c_owner[ck]
        ca = bpos[co] + np.einsum("nij,nj->ni", bR[co], self._c_a[ck])
        cb = bpos[co] + np.einsum("nij,nj->ni", bR[co], self._c_b[ck])
        c_obj = [np.array([self._body_id[self._bodies[o]] for o in co], dtype=int)]
        c_a, c_b = [(ca - p) @ R], [(cb - p) @ R]
        c_rad, c_col, c_min = [self._c_radius[ck]], [self._c_colour[ck]], [np.zeros(int(ck.sum()))]

        if len(self._seg_ends):
            pts = np.array([columns[k][row] for k in self._point_columns], dtype=float).reshape(-1, 3)
            markers = [bpos[b] + bR[b] @ off for b, off in self._markers]
            allp = np.concatenate([pts] + ([np.asarray(markers)] if markers else []), axis=0)
            if not np.all(np.isfinite(allp)):
                raise PerceptionError(f"row {row}: net positions are not finite; the run diverged there")
            cam_pts = (allp - p) @ R
            c_a.append(cam_pts[self._seg_ends[:, 0]])
            c_b.append(cam_pts[self._seg_ends[:, 1]])
            c_rad.append(self._seg_radius)
            c_col.append(self._seg_colour)
            c_min.append(np.full(len(self._seg_ends), 0.5 * self.min_line_px))
            c_obj.append(self._seg_obj)
        caps = Capsules(a=np.concatenate(c_a), b=np.concatenate(c_b), radius=np.concatenate(c_rad),
                        min_px=np.concatenate(c_min), colour=np.concatenate(c_col), obj=np.concatenate(c_obj))
        frags = Fragments.concat([ellipsoid_fragments(intr, ell, lights), capsule_fragments(intr, caps, lights)])
        silhouette = np.zeros(0, np.int64)
        if self.target_name is not None:
            tid = self._body_id[self.target_name]
            silhouette = np.unique(frags.pix[(frags.obj == tid) & (frags.cover >= 0.5)])
        return frags, silhouette

    def _target_view(self, columns, row, R, p, comp, silhouette) -> TargetView:
        W = self.intr.width
        tid = self._body_id[self.target_name]
        c = np.array([columns[f"{self.target_name}_{a}"][row] for a in "xyz"], dtype=float)
        xc = (c - p) @ R
        z = float(xc[2])
        centre = np.array([self.intr.fx * xc[0] / z + self.intr.cx, self.intr.fy * xc[1] / z + self.intr.cy]) \
            if abs(z) > 1e-12 else np.full(2, np.nan)

        def box(pix):
            if pix.size == 0:
                return None
            u, v = pix % W, pix // W
            return np.array([u.min() - 0.5, v.min() - 0.5, u.max() + 0.5, v.max() + 0.5])

        visible = comp.pix[comp.hit_obj == tid]
        return TargetView(box=box(visible), full_box=box(silhouette),
                          visible_fraction=float(visible.size / silhouette.size) if silhouette.size else 0.0,
                          visible_px=int(visible.size), full_px=int(silhouette.size), centre=centre, depth=z)

