"""Rendered detection data: camera images of the capture scenes' target with its ground-truth box.

Every sample is one frame of :class:`~mysim_jax.perception.render.Renderer` for a scene built
from a capture config (``configs/capture_falling.yaml``: the falling sphere;
``configs/capture_maneuvering_cameras.yaml``: the evading drone, drawn as a small dark
quadrotor). Nothing is simulated: poses are sampled directly and written as a one-row
trajectory (the ``columns`` dict the renderer reads from a saved run), and the camera is a
free camera (:class:`~mysim_jax.perception.camera.CameraPoses`). Per sample:

* the camera: yaw uniform, pitch (down, deg) and roll drawn from the split's ranges, at the
  height that puts the target at its sampled height above the ground;
* the target: its range from the camera (m, log-uniform), where its centre projects in the
  image (uniform over the image widened by the target's apparent radius, so some targets are
  cut by the border), height above the ground, and a random attitude (the drone);
* what else is in view: with ``p_occluder`` the capture formation (the 2 m net hanging under
  its four UAVs) or one UAV is put on the line of sight in front of the target, offset so
  that it hides part of it; otherwise, with ``p_distractors``, the formation or one to three
  UAVs are put elsewhere in view (2-30 m away) as distractors; unused objects are hidden
  under the ground;
* or, with ``p_onboard``, the camera is a gimbal camera mounted under one UAV of the capture
  formation (``ONBOARD_OFFSET`` below its centre, as in ``configs/capture_*_gimbals.yaml``;
  its own UAV is not drawn, as the tracker's images do not show it): its own tether hangs
  past the lens to the net below (all tethers leaning up to ``ONBOARD_MAX_LEAN_DEG`` from
  vertical, as when the net trails the formation), and the teammates and the net are
  around the target;
* the world: a ground texture seed, sun azimuth/elevation/strength and sky and ground
  colours, from the split's ranges; with ``p_random_palette`` a training frame's sky and
  ground colours are random instead (:func:`random_palette`: domain randomisation, never
  near a held-out palette; held-out frames keep their own);
* with ``p_empty`` the target is hidden under the ground (a frame with no target).

The ground truth is the renderer's :class:`~mysim_jax.perception.render_io.TargetView`: ``box``
bounds the target's visible pixels (occlusion and image border included).

Splits (:data:`TRAIN` and :data:`HELD_OUT`) differ in every sampled range that describes the
target's appearance: ranges, camera pitch, texture seeds and lighting of the held-out split
are disjoint from the training split's (see ``docs/detector.md``).

Counting a target. A target showing fewer than ``min_visible_px`` pixels, or less than
``min_visible_fraction`` of its whole silhouette, is marked ``ignore``: the metrics neither
require it to be found nor count a detection of it as false
(:mod:`mysim_jax.perception.detect.metrics`). The whole silhouette includes the part beyond
the image border (KITTI's truncation): a drone cut by the border down to one rotor disc is
not required. For a target that touches the border it is counted on a second render of the
same view with the image widened on every side (:func:`whole_silhouette_px`).
``Sample.visible_fraction`` is the occluded share within the image, ``Sample.truncation``
the share of the whole silhouette outside it; the counted fraction is
``visible_fraction * (1 - truncation)``.
"""

from __future__ import annotations

import colorsys
import copy
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import yaml

from mysim_jax.config.scene import config_from_dict
from mysim_jax.perception.camera import CameraPoses, Intrinsics, intrinsics
from mysim_jax.perception.ground import GroundTexture
from mysim_jax.perception.render import Lighting, Renderer
from mysim_jax.perception.render_models import tip_radius

ROOT = Path(__file__).resolve().parents[3]
SCENE_FILES = {"sphere": ROOT / "configs" / "capture_falling.yaml",
               "drone": ROOT / "configs" / "capture_maneuvering_cameras.yaml"}
# what else a frame shows (its ``meta["scene"]``)
SCENE_NONE, SCENE_ONBOARD, SCENE_DISTRACTORS = "none", "onboard", "distractors"
SCENE_NET, SCENE_UAV = "net", "uav"               # the formation's net / one UAV in front of the target
OCCLUDED_SCENES = (SCENE_NET, SCENE_UAV)
PARK_Z = -100.0                 # m, height of hidden objects (under the ground, which hides them)
ONBOARD_OFFSET = (0.0, 0.0, -0.04)   # m, an onboard camera below its UAV's centre (UAV frame, level UAV)
ONBOARD_MIN_HEIGHT = 2.0        # m, lowest onboard camera (the net hangs ~1.4 m below it)
ONBOARD_MAX_LEAN_DEG = 30.0     # tethers lean up to this from vertical (the net trailing the formation)


@dataclass(frozen=True)
class Palette:
    """Sky and ground colours (RGB in [0, 1]) of a lighting condition."""

    zenith: tuple[float, float, float]
    horizon: tuple[float, float, float]
    ground_dark: tuple[float, float, float]
    ground_light: tuple[float, float, float]


# training palettes: clear day, greenish fields, dry grass
TRAIN_PALETTES = (
    Palette((0.30, 0.50, 0.84), (0.80, 0.86, 0.93), (0.17, 0.22, 0.10), (0.62, 0.57, 0.40)),
    Palette((0.25, 0.45, 0.80), (0.75, 0.83, 0.92), (0.10, 0.20, 0.08), (0.45, 0.55, 0.30)),
    Palette((0.35, 0.55, 0.85), (0.85, 0.88, 0.92), (0.30, 0.27, 0.15), (0.75, 0.68, 0.48)),
)
# held-out palettes: overcast grey sky over dark soil, warm evening sky over sand
HELD_OUT_PALETTES = (
    Palette((0.55, 0.58, 0.62), (0.78, 0.79, 0.80), (0.14, 0.13, 0.12), (0.48, 0.44, 0.38)),
    Palette((0.28, 0.35, 0.62), (0.95, 0.78, 0.60), (0.35, 0.30, 0.22), (0.85, 0.76, 0.58)),
)


# a random training palette whose ground colours are all within this of a held-out palette's
# (RGB in [0, 1], per channel) is drawn again, so held-out ground colours stay unseen
PALETTE_EXCLUSION = 0.2


def random_palette(rng: np.random.Generator) -> Palette:
    """A random sky and ground (domain randomisation of the training frames): ground of any hue,
    grey to saturated, its dark and light tones 0-40 deg of hue apart; sky of any hue, mostly
    pale. Redrawn while both ground colours are within ``PALETTE_EXCLUSION`` of a held-out
    palette's."""
    def hsv(h, s, v):
        return tuple(float(x) for x in colorsys.hsv_to_rgb(h % 1.0, s, v))

    while True:
        h = rng.uniform(0, 1)
        dark = hsv(h, rng.uniform(0, 0.8), rng.uniform(0.06, 0.4))
        light = hsv(h + rng.uniform(-1, 1) / 9, rng.uniform(0, 0.7), rng.uniform(0.4, 0.9))
        hs = rng.uniform(0, 1)
        zenith = hsv(hs, rng.uniform(0, 0.7), rng.uniform(0.35, 0.95))
        horizon = hsv(hs + rng.uniform(-1, 1) / 12, rng.uniform(0, 0.35), rng.uniform(0.7, 1.0))
        near = any(np.max(np.abs(np.r_[dark, light] - np.r_[q.ground_dark, q.ground_light])) < PALETTE_EXCLUSION
                   for q in HELD_OUT_PALETTES)
        if not near:
            return Palette(zenith, horizon, dark, light)


@dataclass(frozen=True)
class Split:
    """Sampling ranges of one data split. Each range is a tuple of (low, high) intervals;
    a value is drawn from one interval picked with probability proportional to its width
    (distances: to its log-width)."""

    name: str
    distance_m: tuple[tuple[float, float], ...]         # range camera -> target centre
    pitch_deg: tuple[tuple[float, float], ...]          # camera pitch below the horizon
    sun_elevation_deg: tuple[tuple[float, float], ...]
    sun_strength: tuple[tuple[float, float], ...]
    texture_seeds: tuple[int, int]                      # [low, high) ground texture seeds
    palettes: tuple[Palette, ...]
    roll_deg: float = 15.0                              # |camera roll| at most
    target_height_m: tuple[float, float] = (0.5, 8.0)   # target centre above the ground


TRAIN = Split(name="train", distance_m=((3.0, 25.0),), pitch_deg=((-8.0, 50.0),),
              sun_elevation_deg=((25.0, 80.0),), sun_strength=((0.5, 0.9),), texture_seeds=(0, 100),
              palettes=TRAIN_PALETTES)
HELD_OUT = Split(name="held_out", distance_m=((2.0, 3.0), (25.0, 35.0)), pitch_deg=((50.0, 75.0),),
                 sun_elevation_deg=((8.0, 25.0),), sun_strength=((0.3, 0.5), (0.9, 1.1)),
                 texture_seeds=(1000, 1020), palettes=HELD_OUT_PALETTES)
SPLITS = {"train": TRAIN, "held_out": HELD_OUT}


@dataclass(frozen=True)
class Sample:
    """One rendered frame and its ground truth."""

    image: np.ndarray            # (H, W, 3) uint8 RGB
    box: np.ndarray | None       # (4,) px (u_min, v_min, u_max, v_max) of the visible target; None: not visible
    ignore: bool                 # a target too small or too hidden to count (see the module doc)
    kind: str                    # 'sphere' or 'drone'
    distance: float              # m, camera -> target centre (nan: no target placed)
    visible_fraction: float      # visible / unoccluded silhouette pixels within the image
    visible_px: int
    truncation: float = 0.0      # share of the whole silhouette outside the image (0: none cut by the border)
    meta: dict = field(default_factory=dict)   # sampled parameters: lighting, texture seed, scene, camera pose
                                               # (camera_R (3, 3) OpenCV -> world, camera_p (3,) m), target_pos (3,) m,
                                               # formation (onboard frames: the camera's UAV, tether k, net pose),
                                               # uavs (the UAVs drawn: name, pos (3,) m, radius m)
    mask: np.ndarray | None = None   # (h, w) bool over ``box``'s pixels: which of them show the target


@lru_cache(maxsize=2)
def scene_config(kind: str):
    """The capture scene of target ``kind`` ('sphere' or 'drone'), cameras removed (the
    dataset's camera is a free one)."""
    raw = yaml.safe_load(SCENE_FILES[kind].read_text())
    raw = copy.deepcopy(raw)
    for q in raw.get("quadrotors", []):
        q.pop("cameras", None)
    return config_from_dict(raw, source=str(SCENE_FILES[kind]))


@lru_cache(maxsize=32)
def _texture(seed: int) -> GroundTexture:
    return GroundTexture(seed=seed)


def _draw(rng: np.random.Generator, intervals, log: bool = False) -> float:
    lo = np.array([a for a, _ in intervals], float)
    hi = np.array([b for _, b in intervals], float)
    if log:
        lo, hi = np.log(lo), np.log(hi)
    w = hi - lo
    i = rng.choice(len(w), p=w / w.sum())
    x = rng.uniform(lo[i], hi[i])
    return float(np.exp(x) if log else x)


def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def _random_quat(rng: np.random.Generator, tilt_deg: float) -> np.ndarray:
    """Scalar-first quaternion: uniform yaw, then a tilt of at most ``tilt_deg`` about a random horizontal axis."""
    yaw = rng.uniform(0, 2 * np.pi)
    tilt = np.radians(rng.uniform(0, tilt_deg))
    phi = rng.uniform(0, 2 * np.pi)
    qt = np.array([np.cos(tilt / 2), np.sin(tilt / 2) * np.cos(phi), np.sin(tilt / 2) * np.sin(phi), 0.0])
    qy = _yaw_quat(yaw)
    w1, v1, w2, v2 = qt[0], qt[1:], qy[0], qy[1:]
    return np.r_[w1 * w2 - v1 @ v2, w1 * v2 + w2 * v1 + np.cross(v1, v2)]


def camera_matrix(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """(3, 3) OpenCV camera frame -> world of a camera with heading ``yaw`` (about world z),
    looking ``pitch`` below the horizon, rolled ``roll`` about its optical axis (rad)."""
    f = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), -np.sin(pitch)])
    r = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    d = np.cross(f, r)
    c, s = np.cos(roll), np.sin(roll)
    r, d = c * r + s * d, -s * r + c * d
    return np.stack([r, d, f], axis=-1)


class _Columns:
    """A one-row trajectory being written: body poses and net point positions."""

    def __init__(self, config):
        self.config = config
        self.cols: dict[str, np.ndarray] = {"time": np.array([0.0])}
        self._parked = 0
        names = [q.body for q in config.quadrotors] + [config.target.name]
        for name in names:
            self.body(name, None, None)
        self.net(None)

    def body(self, name, pos, quat):
        if pos is None:     # park it under the ground, bodies apart
            pos, quat = (3.0 * self._parked, 0.0, PARK_Z), (1.0, 0.0, 0.0, 0.0)
            self._parked += 1
        for a, v in zip("xyz", pos):
            self.cols[f"{name}_{a}"] = np.array([float(v)])
        for a, v in zip("wxyz", quat):
            self.cols[f"{name}_q{a}"] = np.array([float(v)])

    def put(self, name, p):
        for a, v in zip("xyz", p):
            self.cols[f"{name}_{a}"] = np.array([float(v)])

    def centre_under(self, k: int, uav_pos, yaw: float, sag: float, lean=(0.0, 0.0)) -> np.ndarray:
        """(3,) m: the net centre that, laid out by :meth:`net` with ``(centre, yaw, sag, lean)``,
        puts the UAV of tether ``k`` at ``uav_pos``."""
        net = self.config.net
        i, j = net.tether_knots()[k]
        knot = self._net_offset(self._coord(j), self._coord(i), yaw, sag)
        return np.asarray(uav_pos, float) + np.asarray(net.tethers.attach, float) - self._tether_vector(lean) - knot

    def _coord(self, k) -> float:
        """Net coordinate in [-1, 1] of knot row / column ``k``."""
        return -1 + 2 * k / (self.config.net.knots - 1)

    def _net_offset(self, a, b, yaw: float, sag: float) -> np.ndarray:
        """(3,) m: net point at net coordinates ``a``, ``b`` in [-1, 1] from the net centre,
        the net turned ``yaw`` and its centre ``sag`` below its edges."""
        size = self.config.net.size
        x, y = a * size / 2, b * size / 2
        c, s = np.cos(yaw), np.sin(yaw)
        return np.array([c * x - s * y, s * x + c * y, -sag * (1 - a * a) * (1 - b * b)])

    def _tether_vector(self, lean) -> np.ndarray:
        """(3,) m: knot -> UAV attach point of a taut tether leaning ``lean`` (2,) m sideways."""
        length = self.config.net.tethers.length
        lx, ly = float(lean[0]), float(lean[1])
        return np.array([lx, ly, np.sqrt(max(length ** 2 - lx * lx - ly * ly, 0.0))])

    def net(self, pose):
        """Lay the net out: ``pose`` = (centre (3,), yaw, sag m[, lean (2,) m]) hangs it level
        with its centre ``sag`` below its edges, each UAV above its knot shifted ``lean``
        sideways (taut tethers; default straight above); None parks it (and its tethers)
        under the ground."""
        net = self.config.net
        g = net.knots
        if pose is None:
            centre, yaw, sag = np.array([0.0, 0.0, PARK_Z]), 0.0, 0.0
        else:
            centre, yaw, sag = pose[:3]
            lean = pose[3] if len(pose) > 3 else (0.0, 0.0)

        def point(a, b):      # a, b in [-1, 1]: net coordinates
            return centre + self._net_offset(a, b, yaw, sag)

        coord = self._coord
        n = net.masses_per_edge
        for i in range(g):
            for j in range(g):
                self.put(net.knot_name(i, j), point(coord(j), coord(i)))
                for kind, (i2, j2) in (("h", (i, j + 1)), ("v", (i + 1, j))):
                    if i2 < g and j2 < g:
                        for m in range(n):
                            f = (m + 1) / (n + 1)
                            self.put(f"{net.name}_{kind}{i}_{j}_{m}",
                                     point((1 - f) * coord(j) + f * coord(j2), (1 - f) * coord(i) + f * coord(i2)))
        t = net.tethers
        if t is None:
            return
        for k, (uav, (i, j)) in enumerate(zip(t.uavs, net.tether_knots())):
            knot = point(coord(j), coord(i))
            if pose is None:
                end = knot.copy()
            else:   # the UAV above its knot (leaning), level, the tether taut
                end = knot + self._tether_vector(lean)
                self.body(uav, end - np.asarray(t.attach), _yaw_quat(yaw))
            for m in range(t.n_masses):
                f = (m + 1) / (t.n_masses + 1)
                self.put(f"{net.name}_t{k}_{m}", (1 - f) * knot + f * end)


@dataclass(frozen=True)
class DatasetSpec:
    """How many frames of which split, and the rendering and counting settings."""

    split: str = "train"
    n_images: int = 100
    seed: int = 0
    width: int = 640                    # px
    height: int = 360                   # px
    p_empty: float = 0.1                # frames with no target
    p_occluder: float = 0.25            # frames with the net formation or a UAV in front of the target
    p_distractors: float = 0.5          # frames with UAVs / the formation elsewhere in view
    p_drone: float = 0.5                # evading-drone target (else the falling sphere)
    p_onboard: float = 0.0              # frames from a camera under a UAV of the formation
    p_random_palette: float = 0.0       # training frames with a random sky and ground (random_palette)
    min_visible_px: int = 6
    min_visible_fraction: float = 0.3


def whole_silhouette_px(renderer_args: dict, intr, columns, poses, depth: float, radius: float) -> int:
    """Pixels of the target's unoccluded silhouette in an image of ``intr``'s camera widened on
    every side by the target's apparent diameter plus 2 px (so none of it is cut), rendered
    with ``Renderer(**renderer_args)``."""
    pad = int(np.ceil(2.0 * intr.fx * radius / max(depth, 1e-3))) + 2
    wide = Intrinsics(width=intr.width + 2 * pad, height=intr.height + 2 * pad, fx=intr.fx, fy=intr.fy,
                      cx=intr.cx + pad, cy=intr.cy + pad)
    tv = Renderer(intr=wide, **renderer_args).render(columns, poses, 0).target
    return 0 if tv is None else int(tv.full_px)


def _in_view_point(rng, intr, R, p, distance, margin=0.0):
    """World point at ``distance`` m along the ray of a random pixel (image widened by ``margin`` px)."""
    u = rng.uniform(-margin, intr.width + margin)
    v = rng.uniform(-margin, intr.height + margin)
    ray = np.array([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, 1.0])
    ray /= np.linalg.norm(ray)
    return p + R @ ray * distance, (u, v)


def is_ignored(visible_px: int, visible_fraction: float, truncation: float, min_visible_px: int,
               min_visible_fraction: float) -> bool:
    """The counting rule (module doc): a target showing fewer than ``min_visible_px`` pixels or
    less than ``min_visible_fraction`` of its whole silhouette (``visible_fraction`` within the
    image, ``truncation`` of it outside) is neither required nor a false positive."""
    return visible_px < min_visible_px or visible_fraction * (1.0 - truncation) < min_visible_fraction


def _touches_border(box, intr) -> bool:
    return bool(box[0] <= -0.5 or box[1] <= -0.5 or box[2] >= intr.width - 0.5 or box[3] >= intr.height - 0.5)


def _world(spec: DatasetSpec, split, rng, index: int):
    """The frame's lighting (a palette of the split, or a random one) and ground texture seed."""
    palette = split.palettes[rng.integers(len(split.palettes))]
    # random palettes draw from their own stream, so p_random_palette = 0 leaves every frame as it was
    rng_palette = np.random.default_rng([spec.seed, 0 if spec.split == "train" else 1, index, 2])
    if spec.split == "train" and rng_palette.random() < spec.p_random_palette:
        palette = random_palette(rng_palette)
    jitter = lambda c: tuple(np.clip(np.asarray(c) + rng.uniform(-0.04, 0.04, 3), 0, 1).tolist())
    lighting = Lighting(sun_azimuth_deg=rng.uniform(0, 360), sun_elevation_deg=_draw(rng, split.sun_elevation_deg),
                        sun_strength=_draw(rng, split.sun_strength), zenith=jitter(palette.zenith),
                        horizon=jitter(palette.horizon), ground_dark=jitter(palette.ground_dark),
                        ground_light=jitter(palette.ground_light))
    tex_seed = int(rng.integers(*split.texture_seeds))
    return lighting, tex_seed


def _occluders(spec: DatasetSpec, rng, rng_onboard, config, cols, intr, R, p, offset, distance, radius, onboard,
               empty):
    """Add what stands between the camera and the target, or around it, to the frame's
    columns: an onboard view through the formation, the net or a UAV across the line of
    sight, or distractors elsewhere. Returns ``(scene kind, bodies hidden, formation)``."""
    tethers = config.net.tethers if config.net is not None else None
    uavs = [q.body for q in config.quadrotors]
    meta_occ = SCENE_NONE
    los = offset / distance
    side = np.cross(los, [0.0, 0.0, 1.0])
    side = side / max(np.linalg.norm(side), 1e-9)
    up = np.cross(side, los)
    hide: tuple[str, ...] = ()
    formation = None
    if onboard:                      # the camera under tether k's UAV, the formation around it
        meta_occ = SCENE_ONBOARD
        k = int(rng_onboard.integers(len(tethers.uavs)))
        f_yaw, sag = rng_onboard.uniform(0, 2 * np.pi), rng_onboard.uniform(0.0, 0.4)
        tilt, heading = np.radians(rng_onboard.uniform(0.0, ONBOARD_MAX_LEAN_DEG)), rng_onboard.uniform(0, 2 * np.pi)
        lean = tethers.length * np.sin(tilt) * np.array([np.cos(heading), np.sin(heading)])
        uav_pos = p - np.asarray(ONBOARD_OFFSET)
        centre = cols.centre_under(k, uav_pos, f_yaw, sag, lean)
        cols.net((centre, f_yaw, sag, lean))
        hide = (tethers.uavs[k],)
        formation = dict(uav=tethers.uavs[k], tether=k, centre=centre.tolist(), yaw=float(f_yaw), sag=float(sag),
                         lean=lean.tolist())
    elif not empty and rng.random() < spec.p_occluder and distance > 2.0:
        f = rng.uniform(0.3, 0.85)
        at = p + offset * f
        if rng.random() < 0.5:       # the formation, its net across the line of sight
            meta_occ = SCENE_NET
            shift = rng.uniform(-0.8, 0.8) * side + rng.uniform(-0.8, 0.8) * up
            cols.net((at + shift, rng.uniform(0, 2 * np.pi), rng.uniform(0.0, 0.4)))
        else:                        # one UAV partly in front
            meta_occ = SCENE_UAV
            lateral = radius * f * rng.uniform(0.3, 1.6)
            ang = rng.uniform(0, 2 * np.pi)
            cols.body(uavs[0], at + lateral * (np.cos(ang) * side + np.sin(ang) * up), _random_quat(rng, 20.0))
    elif rng.random() < spec.p_distractors:
        meta_occ = SCENE_DISTRACTORS
        if rng.random() < 0.4:
            d = float(np.exp(rng.uniform(np.log(3.0), np.log(30.0))))
            at, _ = _in_view_point(rng, intr, R, p, d, margin=0.0)
            at[2] = max(at[2], 2.0)
            cols.net((at, rng.uniform(0, 2 * np.pi), rng.uniform(0.0, 0.4)))
        else:
            for name in uavs[: rng.integers(1, 4)]:
                d = float(np.exp(rng.uniform(np.log(2.0), np.log(30.0))))
                at, _ = _in_view_point(rng, intr, R, p, d, margin=0.0)
                at[2] = max(at[2], 0.3)
                cols.body(name, at, _random_quat(rng, 20.0))

    return meta_occ, hide, formation


def _uavs_drawn(config, cols: _Columns, hide) -> list[dict]:
    """The UAVs the frame draws (not parked under the ground, not the onboard camera's own):
    per UAV its ``name``, ``pos`` (3,) m and ``radius`` m (its rotor tips' distance from its
    centre), as the team's own estimates would give them."""
    out = []
    for q in config.quadrotors:
        pos = [float(cols.cols[f"{q.body}_{a}"][0]) for a in "xyz"]
        if q.body in hide or pos[2] < PARK_Z / 2:
            continue
        out.append(dict(name=q.body, pos=pos, radius=tip_radius(q.rotors.arm_length)))
    return out


def render_sample(spec: DatasetSpec, index: int) -> Sample:
    """Frame ``index`` of the dataset ``spec`` (deterministic for (spec.seed, spec.split, index))."""
    split = SPLITS[spec.split]
    rng = np.random.default_rng([spec.seed, 0 if spec.split == "train" else 1, index])
    kind = "drone" if rng.random() < spec.p_drone else "sphere"
    config = scene_config(kind)
    intr = intrinsics(width=spec.width, height=spec.height)
    radius = config.target.radius

    lighting, tex_seed = _world(spec, split, rng, index)

    # camera and target
    yaw = rng.uniform(0, 2 * np.pi)
    pitch = np.radians(_draw(rng, split.pitch_deg))
    roll = np.radians(rng.uniform(-split.roll_deg, split.roll_deg))
    R = camera_matrix(yaw, pitch, roll)
    distance = _draw(rng, split.distance_m, log=True)
    r_px = intr.fx * radius / distance
    offset, (u, v) = _in_view_point(rng, intr, R, np.zeros(3), distance, margin=0.8 * r_px)
    h_target = rng.uniform(*split.target_height_m)
    h_cam = h_target - offset[2]
    # onboard frames draw from their own stream, so p_onboard = 0 leaves every frame as it was
    rng_onboard = np.random.default_rng([spec.seed, 0 if spec.split == "train" else 1, index, 1])
    tethers = config.net.tethers if config.net is not None else None
    onboard = tethers is not None and rng_onboard.random() < spec.p_onboard
    h_min = ONBOARD_MIN_HEIGHT if onboard else 0.5
    if h_cam < h_min:                    # looking up at the target (or no room for the net): raise both
        h_target += h_min - h_cam
        h_cam = h_min
    p = np.array([0.0, 0.0, h_cam])
    target_pos = p + offset
    cols = _Columns(config)
    empty = rng.random() < spec.p_empty
    target_quat = _random_quat(rng, 25.0) if kind == "drone" else _yaw_quat(rng.uniform(0, 2 * np.pi))
    if not empty:
        cols.body(config.target.name, target_pos, target_quat)

    meta_occ, hide, formation = _occluders(spec, rng, rng_onboard, config, cols, intr, R, p, offset, distance,
                                           radius, onboard, empty)

    renderer_args = dict(config=config, texture=_texture(tex_seed), lighting=lighting, hide=hide)
    renderer = Renderer(intr=intr, **renderer_args)
    poses = CameraPoses(name="observer", t=np.array([0.0]), R=R[None], p=p[None])
    frame = renderer.render(cols.cols, poses, 0)
    tv = frame.target
    box = None if tv is None or tv.box is None else np.asarray(tv.box, float)
    visible_px = 0 if tv is None else tv.visible_px
    fraction = 0.0 if tv is None else tv.visible_fraction
    truncation = 0.0
    if tv is not None and tv.full_box is not None and _touches_border(tv.full_box, intr):
        whole = whole_silhouette_px(renderer_args, intr, cols.cols, poses, tv.depth, radius)
        truncation = max(0.0, 1.0 - tv.full_px / whole) if whole else 0.0
    ignore = box is not None and is_ignored(visible_px, fraction, truncation, spec.min_visible_px,
                                            spec.min_visible_fraction)
    meta = dict(texture_seed=tex_seed, sun_azimuth_deg=lighting.sun_azimuth_deg,
                sun_elevation_deg=lighting.sun_elevation_deg, sun_strength=lighting.sun_strength,
                pitch_deg=float(np.degrees(pitch)), roll_deg=float(np.degrees(roll)), camera_height_m=float(h_cam),
                scene=meta_occ, pixel=(float(u), float(v)), camera_R=R.tolist(), camera_p=p.tolist(),
                target_pos=None if empty else target_pos.tolist(), target_radius=float(radius),
                formation=formation, uavs=_uavs_drawn(config, cols, hide))
    return Sample(image=frame.image, box=box, ignore=bool(ignore), kind=kind,
                  distance=float("nan") if empty else float(distance), visible_fraction=float(fraction),
                  visible_px=int(visible_px), truncation=float(truncation), meta=meta,
                  mask=None if box is None else box_mask(frame, config.target.name, box))


def counted_samples(spec: DatasetSpec, n: int) -> list[Sample]:
    """The first ``n`` samples of ``spec`` (of its ``n_images``) with a counted target (fewer
    when the set has fewer)."""
    out = []
    for i in range(spec.n_images):
        s = render_sample(spec, i)
        if s.box is not None and not s.ignore:
            out.append(s)
        if len(out) == n:
            break
    return out


def box_mask(frame, target_name: str, box: np.ndarray) -> np.ndarray:
    """(h, w) bool: the pixels of ``box`` (renderer px, the visible target's box) that show
    the target in ``frame`` (:class:`~mysim_jax.perception.render_io.Frame`)."""
    u0, v0, u1, v1 = (int(round(x + 0.5)) for x in box)          # edge coordinates: whole pixels
    return frame.ids[v0:v1, u0:u1] == frame.names.index(target_name)


