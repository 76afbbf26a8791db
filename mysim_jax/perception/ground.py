"""The textured ground plane z = ``ground_z`` as a camera sees it: albedo and depth per pixel.

The ground's albedo is procedural, so it has detail at every distance a camera sees it
from, with no texture image to load: a sum of layers, each a periodic tile of band-limited
noise (``tile_px`` texels a side, wavelengths 4 to 64 texels, pushed through ``tanh`` so it
has blobs with edges and corners a feature tracker can follow) laid on the ground at its
own size, rotation and offset. Successive layers are ~6x smaller, so together they are not
periodic anywhere a camera looks.

Anti-aliasing: a pixel covers ``footprint`` metres of ground (range / focal length,
lengthened by the slant). A layer whose texels are smaller than a pixel would alias into
flicker that a tracker takes for features; it fades out between footprints of 1 and 4 of
its texels, so every pixel shows only the layers it can resolve.

Each layer is sampled with ``cv2.remap`` (bilinear, wrapping at the tile's edges) at the
pixel's ground point: the cost per frame is a few full-image array operations per layer.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from mysim_jax.perception.camera import Intrinsics, pixel_rays


def _band_limited_tile(rng: np.random.Generator, n: int, shortest: float = 4.0, longest: float = 64.0) -> np.ndarray:
    """(n, n) periodic noise with wavelengths between ``shortest`` and ``longest`` texels, in (-1, 1)."""
    spectrum = np.fft.rfft2(rng.standard_normal((n, n)))
    ky = np.fft.fftfreq(n)[:, None]
    kx = np.fft.rfftfreq(n)[None, :]
    k = np.hypot(kx, ky)
    band = (k >= 1.0 / longest) & (k <= 1.0 / shortest)
    shaped = np.fft.irfft2(spectrum * band / np.maximum(k, 1.0 / n), s=(n, n))
    shaped /= shaped.std()
    return np.tanh(1.5 * shaped).astype(np.float32)


@dataclass(frozen=True)
class GroundTexture:
    """Procedural ground albedo (see the module doc). Deterministic for a ``seed``."""

    seed: int = 0
    tile_px: int = 512
    tile_sizes: tuple[float, ...] = (41.0, 6.7, 1.09, 0.177)     # m, one per layer
    mean: float = 0.5
    contrast: float = 0.16                                       # albedo swing of one layer
    layers: tuple[np.ndarray, ...] = field(init=False, repr=False, compare=False)
    frames: np.ndarray = field(init=False, repr=False, compare=False)   # (L, 2, 3) ground -> texel affine

    def __post_init__(self):
        rng = np.random.default_rng(self.seed)
        layers, frames = [], []
        for size in self.tile_sizes:
            layers.append(_band_limited_tile(rng, self.tile_px))
            angle = rng.uniform(0.0, 2 * np.pi)
            offset = rng.uniform(0.0, self.tile_px, size=2)
            scale = self.tile_px / size
            c, s = np.cos(angle) * scale, np.sin(angle) * scale
            frames.append([[c, -s, offset[0]], [s, c, offset[1]]])
        object.__setattr__(self, "layers", tuple(layers))
        object.__setattr__(self, "frames", np.asarray(frames, dtype=np.float64))

    def texel_sizes(self) -> np.ndarray:
        """(L,) metres per texel of every layer."""
        return np.asarray(self.tile_sizes) / self.tile_px

    def albedo(self, x: np.ndarray, y: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        """Albedo in [0, 1] at ground points (x, y) (m) seen with pixel ``footprint`` (m); float32, any shape."""
        x = np.asarray(x, dtype=np.float32)
        y = np.asarray(y, dtype=np.float32)
        shape = x.shape
        x2, y2 = x.reshape(-1, 1) if x.ndim < 2 else x, y.reshape(-1, 1) if y.ndim < 2 else y
        log_fp = np.log2(np.maximum(np.asarray(footprint, dtype=np.float32), 1e-9)).reshape(x2.shape)
        out = np.full(x2.shape, self.mean, dtype=np.float32)
        n = float(self.tile_px)
        for tile, frame, texel in zip(self.layers, self.frames, self.texel_sizes()):
            weight = np.clip(1.0 - 0.5 * (log_fp - np.float32(np.log2(texel))), 0.0, 1.0)
            if not np.any(weight > 0):
                continue
            u = np.mod(frame[0, 0] * x2 + frame[0, 1] * y2 + frame[0, 2], n).astype(np.float32)
            v = np.mod(frame[1, 0] * x2 + frame[1, 1] * y2 + frame[1, 2], n).astype(np.float32)
            sample = cv2.remap(tile, u, v, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            out += np.float32(self.contrast) * weight * sample.reshape(x2.shape)
        return np.clip(out, 0.0, 1.0).reshape(shape)


@dataclass(frozen=True)
class GroundView:
    """What one camera sees of the ground plane."""

    albedo: np.ndarray     # (H, W) float32 in [0, 1]; 0 where the pixel sees sky
    depth: np.ndarray      # (H, W) float32 m along the optical axis; inf where the pixel sees sky
    points: np.ndarray     # (H, W, 3) float32 m, world point seen by each pixel (NaN on sky)


_RAYS: dict[tuple, np.ndarray] = {}


def _rays(intr: Intrinsics) -> np.ndarray:
    key = (intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy)
    if key not in _RAYS:
        if len(_RAYS) > 8:
            _RAYS.clear()
        _RAYS[key] = pixel_rays(intr)
    return _RAYS[key]


def view_ground(intr: Intrinsics, R: np.ndarray, p: np.ndarray, texture: GroundTexture,
                ground_z: float = 0.0) -> GroundView:
    """Ray-cast the ground plane from one camera pose (``R``: OpenCV camera -> world, ``p``: centre, m)."""
    rays = _rays(intr)                                            # (H, W, 3), z = 1
    dirs = rays @ np.asarray(R, dtype=np.float32).T               # world directions, same length
    height = np.float32(p[2] - ground_z)
    dz = dirs[..., 2]
    hit = dz < -1e-6
    t = np.where(hit, height / np.where(hit, -dz, 1.0), np.inf).astype(np.float32)   # = depth (ray z = 1)
    t_hit = np.where(hit, t, 0.0)
    xs = np.where(hit, np.float32(p[0]) + t_hit * dirs[..., 0], np.nan).astype(np.float32)
    ys = np.where(hit, np.float32(p[1]) + t_hit * dirs[..., 1], np.nan).astype(np.float32)
    norm = np.linalg.norm(dirs, axis=-1)
    # metres of ground per pixel: range / f across, / cos(incidence) along; their geometric mean
    footprint = np.where(hit, t_hit * norm / np.float32(intr.fx) * np.sqrt(norm / np.maximum(-dz, 1e-6)), 1.0)
    albedo = texture.albedo(np.nan_to_num(xs), np.nan_to_num(ys), footprint)
    albedo = np.where(hit, albedo, 0.0).astype(np.float32)
    points = np.stack([xs, ys, np.where(hit, np.float32(ground_z), np.nan)], -1)
    return GroundView(albedo=albedo, depth=t, points=points)
