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

Each layer is sampled with ``cv2.remap`` (bilinear) at the pixel's ground point. Ground
points are kept relative to an origin near the points (the camera's nadir in
:func:`view_ground`) and every layer's offset is reduced modulo its tile in float64, so the
float32 texel coordinates stay exact to a small fraction of a texel however far the camera
is from the world origin. The cost per frame is a dozen full-image float32 operations for
the geometry, plus a few per layer that the pixels resolve (layers fully faded out are
skipped).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

from mysim_jax.perception.camera import Intrinsics


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
    # (L,) tiles of (tile_px + 1)^2 texels: the tile with its first row and column repeated
    # after the last, so bilinear lookups at texel coordinates in [0, tile_px] need no wrap
    _padded: tuple[np.ndarray, ...] = field(init=False, repr=False, compare=False)

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
        object.__setattr__(self, "_padded", tuple(cv2.copyMakeBorder(t, 0, 1, 0, 1, cv2.BORDER_WRAP) for t in layers))

    def texel_sizes(self) -> np.ndarray:
        """(L,) metres per texel of every layer."""
        return np.asarray(self.tile_sizes) / self.tile_px

    def albedo(self, x: np.ndarray, y: np.ndarray, footprint: np.ndarray) -> np.ndarray:
        """Albedo in [0, 1] at ground points (x, y) (m) seen with pixel ``footprint`` (m); float32, any shape."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        shape = np.broadcast_shapes(x.shape, y.shape, np.shape(footprint))
        x, y = np.broadcast_to(x, shape), np.broadcast_to(y, shape)
        origin = np.array([np.mean(x), np.mean(y)]) if x.size else np.zeros(2)
        # lay the points out as a 2-D block of at most 4096 columns (remap takes < 32767 rows)
        n = x.size
        cols = max(min(n, 4096), 1)
        rows = -(-n // cols)

        def block(values, fill=0.0):
            out = np.full(rows * cols, fill, dtype=np.float32)
            out[:n] = values.reshape(-1)
            return out.reshape(rows, cols)

        fp = np.maximum(np.broadcast_to(np.asarray(footprint, dtype=np.float32), shape), 1e-9)
        albedo = self._sample(block(x - origin[0]), block(y - origin[1]), origin, np.log2(block(fp, 1.0)))
        return albedo.reshape(-1)[:n].reshape(shape)

    def _sample(self, x: np.ndarray, y: np.ndarray, origin: np.ndarray, log_fp: np.ndarray,
                mask: np.ndarray | None = None) -> np.ndarray:
        """Albedo at ground points ``origin + (x, y)`` (float32 2-D arrays, m) of log2 footprint ``log_fp``."""
        out = np.full(x.shape, self.mean, dtype=np.float32)
        n = float(self.tile_px)
        n32, inv_n = np.float32(n), np.float32(1.0 / n)
        for tile, frame, texel in zip(self._padded, self.frames, self.texel_sizes()):
            weight = np.float32(1.0 + 0.5 * np.log2(texel)) - np.float32(0.5) * log_fp
            np.clip(weight, 0.0, 1.0, out=weight)
            if mask is not None:
                weight[~mask] = 0.0
            if not np.any(weight > 0):
                continue
            # texel coordinates, offset reduced modulo the tile at the origin (float64)
            shift = np.mod(frame[:, :2] @ origin + frame[:, 2], n)
            coords = []
            for row, c in zip(frame[:, :2].astype(np.float32), shift.astype(np.float32)):
                t = x * row[0]
                t += y * row[1]
                t += c
                t -= n32 * np.floor(t * inv_n)
                coords.append(t)
            sample = cv2.remap(tile, coords[0], coords[1], interpolation=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REPLICATE)
            sample *= weight
            sample *= np.float32(self.contrast)
            out += sample
        return np.clip(out, 0.0, 1.0, out=out)


@dataclass(frozen=True)
class GroundView:
    """What one camera sees of the ground plane.

    ``x``, ``y`` are the seen points relative to ``origin`` (float32 keeps centimetres
    exact far from the world origin); ``points`` assembles world points on first use.
    """

    albedo: np.ndarray     # (H, W) float32 in [0, 1]; 0 where the pixel sees sky
    depth: np.ndarray      # (H, W) float32 m along the optical axis; inf where the pixel sees sky
    x: np.ndarray          # (H, W) float32 m, world x of the seen point minus origin[0] (0 on sky)
    y: np.ndarray          # (H, W) float32 m, world y of the seen point minus origin[1] (0 on sky)
    origin: np.ndarray     # (2,) float64 m, world (x, y) of the camera's nadir
    ground_z: float        # m

    @property
    def hit(self) -> np.ndarray:
        """(H, W) bool: the pixel sees the ground (else sky)."""
        return np.isfinite(self.depth)

    @cached_property
    def points(self) -> np.ndarray:
        """(H, W, 3) float32 m, world point seen by each pixel (NaN on sky)."""
        hit = self.hit
        out = np.empty(self.depth.shape + (3,), dtype=np.float32)
        out[..., 0] = np.where(hit, (self.x + np.float32(self.origin[0])), np.nan)
        out[..., 1] = np.where(hit, (self.y + np.float32(self.origin[1])), np.nan)
        out[..., 2] = np.where(hit, np.float32(self.ground_z), np.nan)
        return out


def view_ground(intr: Intrinsics, R: np.ndarray, p: np.ndarray, texture: GroundTexture,
                ground_z: float = 0.0) -> GroundView:
    """Ray-cast the ground plane from one camera pose (``R``: OpenCV camera -> world, ``p``: centre, m).

    A camera at or below the ground sees only sky (depth inf everywhere).
    """
    R = np.asarray(R, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    Kinv = np.linalg.inv(intr.K)
    D = R @ Kinv                     # world direction (z_c = 1) of pixel (u, v): D @ (u, v, 1)
    u = np.arange(intr.width, dtype=np.float32)
    v = np.arange(intr.height, dtype=np.float32)

    def plane(row):                  # (H, W) float32 of D[row] @ (u, v, 1), as an outer sum
        return (np.float32(row[0]) * u)[None, :] + (np.float32(row[1]) * v + np.float32(row[2]))[:, None]

    height = float(p[2] - ground_z)
    down = -plane(D[2])
    hit = down > 1e-6 if height > 0 else np.zeros(down.shape, dtype=bool)
    safe_down = np.where(hit, down, np.float32(1.0))
    depth = np.float32(max(height, 0.0)) / safe_down           # = ray parameter: rays have z_c = 1
    x = depth * plane(D[0])
    y = depth * plane(D[1])
    x[~hit] = 0.0
    y[~hit] = 0.0
    # metres of ground per pixel: range / f across, / cos(incidence) along; their geometric mean:
    # |d| t / f * sqrt(|d| / down), with |d|^2 = 1 + ((u - cx) / fx)^2 + ((v - cy) / fy)^2
    norm2 = ((u - np.float32(intr.cx)) / np.float32(intr.fx))[None, :] ** 2 \
        + (((v - np.float32(intr.cy)) / np.float32(intr.fy)) ** 2 + np.float32(1.0))[:, None]
    log_fp = np.log2(norm2)
    log_fp *= np.float32(0.75)
    log_fp -= np.float32(1.5) * np.log2(safe_down)
    log_fp += np.float32(np.log2(max(height, 1e-9) / intr.fx))
    albedo = texture._sample(x, y, p[:2], log_fp, mask=hit)
    albedo[~hit] = 0.0
    depth[~hit] = np.inf
    return GroundView(albedo=albedo, depth=depth, x=x, y=y, origin=p[:2].copy(), ground_z=float(ground_z))
