"""Ray casting of ellipsoids and capsules into anti-aliased, depth-sorted fragments over a background.

Everything here works in one camera's OpenCV frame (x right, y down, z forward; m) with the
optical centre at the origin; a pixel (u, v) looks along ``d = ((u - cx) / fx, (v - cy) / fy, 1)``,
so a ray parameter along ``d`` is a depth along the optical axis.

Objects are made of two primitives: **ellipsoids** (spheres are ellipsoids) and **capsules**
(a segment swept by a ball; net lines, tethers, arms). Each primitive is tested only at its
*candidate pixels*: the bounding box of an ellipsoid's bounding sphere, and a band around a
capsule's projected segment (so a long thin line costs its length in pixels, not its
bounding box). All candidates of all primitives are evaluated together in a few vectorised
NumPy passes:

* an exact ray-ellipsoid intersection, and the closest approach between the ray and a
  capsule's axis (the hit depth is that of a ball of the capsule's radius at the closest
  point: exact for the caps and for a segment across the ray, within the radius otherwise);
* **coverage** ``clip(0.5 + s, 0, 1)``, with ``s`` the signed distance of the pixel centre
  from the primitive's silhouette in pixels (positive inside), as analytic anti-aliasing.
  A pixel whose centre ray hits the primitive has coverage >= 0.5; it is a *hit*;
* capsules can have a minimum width in pixels (``min_px``, a half width): a line thinner than
  that on screen is drawn at that width, so it never vanishes between pixel centres.

:func:`composite` sorts the fragments by pixel and depth and blends them front to back over
the background (the ground or sky) with their coverage as opacity. Depth and object ids are
those of each pixel's nearest *hit* (not of the anti-aliased fringe), so an id image counts a
pixel as an object's when the object covers its centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mysim_jax.perception.camera import Intrinsics

NEAR = 1e-3          # m, nearest depth drawn


@dataclass(frozen=True)
class Ellipsoids:
    """N ellipsoids in the camera frame."""

    centre: np.ndarray    # (N, 3) m
    axes: np.ndarray      # (N, 3, 3) columns: the principal axes (unit vectors) in the camera frame
    semi: np.ndarray      # (N, 3) m, semi-axis lengths along those axes
    colour: np.ndarray    # (N, 3) linear RGB albedo in [0, 1]
    obj: np.ndarray       # (N,) int, object id


@dataclass(frozen=True)
class Capsules:
    """N capsules in the camera frame."""

    a: np.ndarray         # (N, 3) m, one end of the axis
    b: np.ndarray         # (N, 3) m, the other end
    radius: np.ndarray    # (N,) m
    min_px: np.ndarray    # (N,) px, smallest half width on screen (0: true size)
    colour: np.ndarray    # (N, 3) albedo in [0, 1]
    obj: np.ndarray       # (N,) int


@dataclass(frozen=True)
class Lights:
    """Lighting in the camera frame: a sun and a sky/ground hemisphere."""

    sun: np.ndarray       # (3,) unit vector towards the sun
    up: np.ndarray        # (3,) unit vector world +z
    sun_strength: float
    sky_strength: float       # ambient from above
    ground_strength: float    # ambient from below (light bounced off the ground)


@dataclass(frozen=True)
class Fragments:
    """Candidate-pixel samples of primitives (flat arrays, one entry per sample)."""

    pix: np.ndarray       # (F,) int64, flat pixel index v * W + u
    depth: np.ndarray     # (F,) float32 m along the optical axis
    cover: np.ndarray     # (F,) float32 in (0, 1], coverage (>= 0.5: the pixel centre's ray hits)
    colour: np.ndarray    # (F, 3) float32, shaded colour in [0, 1]
    obj: np.ndarray       # (F,) int32, object id

    @staticmethod
    def empty() -> "Fragments":
        return Fragments(np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.float32),
                         np.zeros((0, 3), np.float32), np.zeros(0, np.int32))

    @staticmethod
    def concat(parts: list["Fragments"]) -> "Fragments":
        parts = [f for f in parts if f.pix.size]
        if not parts:
            return Fragments.empty()
        return Fragments(*(np.concatenate([getattr(f, k) for f in parts]) for k in
                           ("pix", "depth", "cover", "colour", "obj")))

    def select(self, keep: np.ndarray) -> "Fragments":
        return Fragments(self.pix[keep], self.depth[keep], self.cover[keep], self.colour[keep], self.obj[keep])


# --- candidate pixels ----------------------------------------------------------------------


def _sphere_boxes(intr: Intrinsics, centre: np.ndarray, radius: np.ndarray, margin: float) -> np.ndarray:
    """(N, 4) int pixel boxes [u0, u1) x [v0, v1) covering spheres' images (clipped to the image; empty if none)."""
    W, H = intr.width, intr.height
    x, y, z = centre[:, 0], centre[:, 1], centre[:, 2]
    r = radius
    out = np.zeros((len(z), 4), dtype=np.int64)
    near = z - r <= NEAR * 2
    far = ~near
    # tangent planes through the camera containing the image y (then x) axis: slopes k = x / z
    zz2 = np.where(far, z * z - r * r, 1.0)
    bounds = []
    for c in (x, y):
        root = r * np.sqrt(np.maximum(c * c + z * z - r * r, 0.0))
        bounds.append(((c * z - root) / zz2, (c * z + root) / zz2))
    u_lo = intr.fx * bounds[0][0] + intr.cx - margin
    u_hi = intr.fx * bounds[0][1] + intr.cx + margin
    v_lo = intr.fy * bounds[1][0] + intr.cy - margin
    v_hi = intr.fy * bounds[1][1] + intr.cy + margin
    u_lo = np.where(near, 0, u_lo)
    u_hi = np.where(near, W - 1, u_hi)
    v_lo = np.where(near, 0, v_lo)
    v_hi = np.where(near, H - 1, v_hi)
    out[:, 0] = np.clip(np.floor(u_lo), 0, W)
    out[:, 1] = np.clip(np.floor(u_hi) + 1, 0, W)
    out[:, 2] = np.clip(np.floor(v_lo), 0, H)
    out[:, 3] = np.clip(np.floor(v_hi) + 1, 0, H)
    behind = z + r <= NEAR
    out[behind] = 0
    return out


def _enumerate(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For ``counts[k]`` items of each group k: every item's group and its index within it."""
    total = int(counts.sum())
    owner = np.repeat(np.arange(len(counts)), counts)
    local = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)
    return owner, local


def _box_pixels(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (u, v) inside boxes [u0, u1) x [v0, v1), and the box each belongs to."""
    wu = np.maximum(boxes[:, 1] - boxes[:, 0], 0)
    wv = np.maximum(boxes[:, 3] - boxes[:, 2], 0)
    owner, local = _enumerate(wu * wv)
    if owner.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), owner
    wu_o = wu[owner]
    u = boxes[owner, 0] + local % wu_o
    v = boxes[owner, 2] + local // wu_o
    return u, v, owner


def _band_pixels(intr: Intrinsics, p0: np.ndarray, p1: np.ndarray,
                 half: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (u, v) within ~``half`` px of 2-D segments p0-p1 (N, 2), and their segment.

    Walks the segment's major axis one pixel at a time and takes, at each step, the pixels of
    the minor axis within the band's extent there (a superset of the band, clipped to the image).
    """
    W, H = intr.width, intr.height
    d = p1 - p0
    swap = np.abs(d[:, 1]) > np.abs(d[:, 0])              # major axis y
    a0 = np.where(swap, p0[:, 1], p0[:, 0])
    a1 = np.where(swap, p1[:, 1], p1[:, 0])
    b0 = np.where(swap, p0[:, 0], p0[:, 1])
    b1 = np.where(swap, p1[:, 0], p1[:, 1])
    size_a = np.where(swap, H, W)
    size_b = np.where(swap, W, H)
    da = a1 - a0
    slope = np.where(np.abs(da) > 1e-9, (b1 - b0) / np.where(np.abs(da) > 1e-9, da, 1.0), 0.0)
    lo_a = np.minimum(a0, a1)
    hi_a = np.maximum(a0, a1)
    start = np.clip(np.floor(lo_a - half), 0, size_a).astype(np.int64)
    stop = np.clip(np.floor(hi_a + half) + 1, 0, size_a).astype(np.int64)
    extent = half * np.sqrt(1.0 + slope * slope)             # minor half extent at one major step
    n_minor = (np.floor(2 * extent) + 1).astype(np.int64)    # whole pixels in [centre - extent, centre + extent]
    n_major = np.maximum(stop - start, 0)
    owner, local = _enumerate(n_major * n_minor)
    if owner.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), owner
    m = n_minor[owner]
    a = start[owner] + local // m
    a_on = np.clip(a, lo_a[owner], hi_a[owner])
    centre_b = b0[owner] + slope[owner] * (a_on - a0[owner])
    b = np.ceil(centre_b - extent[owner]).astype(np.int64) + local % m
    inside = (b >= 0) & (b < size_b[owner])
    a, b, owner = a[inside], b[inside], owner[inside]
    sw = swap[owner]
    return np.where(sw, b, a), np.where(sw, a, b), owner


def _rays(intr: Intrinsics, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x, y components (float64) of the rays (x, y, 1) through pixels (u, v)."""
    return (u - intr.cx) * (1.0 / intr.fx), (v - intr.cy) * (1.0 / intr.fy)


def _shade(colour: np.ndarray, nx, ny, nz, lights: Lights) -> np.ndarray:
    """Lambertian sun plus hemisphere ambient; normal components (F,) (unit), ``colour`` (F, 3)."""
    up = nx * lights.up[0] + ny * lights.up[1] + nz * lights.up[2]
    sun = np.maximum(nx * lights.sun[0] + ny * lights.sun[1] + nz * lights.sun[2], 0.0)
    light = (lights.sky_strength * (0.5 + 0.5 * up) + lights.ground_strength * (0.5 - 0.5 * up)
             + lights.sun_strength * sun)
    return np.clip(colour * light[:, None], 0.0, 1.0).astype(np.float32)


# --- primitives ----------------------------------------------------------------------------


def ellipsoid_fragments(intr: Intrinsics, ell: Ellipsoids, lights: Lights) -> Fragments:
    """Fragments of every ellipsoid at the candidate pixels of its bounding sphere."""
    if len(ell.centre) == 0:
        return Fragments.empty()
    f = intr.fx
    boxes = _sphere_boxes(intr, ell.centre, ell.semi.max(axis=1), margin=0.55)
    u, v, k = _box_pixels(boxes)
    if u.size == 0:
        return Fragments.empty()
    # unit frame of each ellipsoid: x' = M (x - c), M = S^-1 A^T; the camera is at the origin
    M = np.swapaxes(ell.axes, 1, 2) / ell.semi[:, :, None]          # (N, 3, 3)
    o = -np.einsum("nij,nj->ni", M, ell.centre)                     # (N, 3) camera in the unit frame
    x, y = _rays(intr, u, v)
    Mk = M[k]                                                       # (F, 3, 3)
    dp = Mk[:, :, 0] * x[:, None] + Mk[:, :, 1] * y[:, None] + Mk[:, :, 2]    # (F, 3) ray in the unit frame
    op = o[k]
    a = np.einsum("fi,fi->f", dp, dp)
    b = np.einsum("fi,fi->f", op, dp)
    oo = np.einsum("ni,ni->n", o, o)[k]
    t_close = -b / a
    h2 = np.maximum(oo - b * b / a, 0.0)
    h = np.sqrt(h2)
    root = np.sqrt(np.maximum(1.0 - h2, 0.0) / a)                   # half chord, in depth
    t_near = t_close - root
    hit_t = np.where(t_near > NEAR, t_near, t_close + root)         # from inside: the far wall
    q = op + t_close[:, None] * dp                                  # unit-frame closest point, |q| = h
    rho = np.linalg.norm(q * ell.semi[k], axis=1) / np.maximum(h, 1e-12)
    s = (1.0 - h) * rho * f / np.maximum(t_close, NEAR)
    cover = np.clip(0.5 + s, 0.0, 1.0)
    hit = h2 <= 1.0
    depth = np.where(hit, hit_t, t_close)
    keep = (cover > 0.0) & (depth > NEAR)
    if not np.any(keep):
        return Fragments.empty()
    u, v, k, dp, op = u[keep], v[keep], k[keep], dp[keep], op[keep]
    depth, cover, hit = depth[keep], cover[keep], hit[keep]
    # normal: gradient of |S^-1 A^T x|^2 at the hit (or, off the silhouette, at the closest point)
    qs = op + depth[:, None] * dp
    qs = np.where(hit[:, None], qs, qs / np.maximum(np.linalg.norm(qs, axis=1, keepdims=True), 1e-12))
    n = np.einsum("fij,fj->fi", ell.axes[k], qs / ell.semi[k])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    colour = _shade(ell.colour[k], n[:, 0], n[:, 1], n[:, 2], lights)
    return Fragments(v * intr.width + u, depth.astype(np.float32), cover.astype(np.float32), colour,
                     ell.obj[k].astype(np.int32))


def _clip_segments(a: np.ndarray, b: np.ndarray, z_min: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Segments clipped to z >= z_min: new ends and a mask of those with something left."""
    za, zb = a[:, 2], b[:, 2]
    keep = (za >= z_min) | (zb >= z_min)
    dz = zb - za
    t = np.where(np.abs(dz) > 1e-12, (z_min - za) / np.where(np.abs(dz) > 1e-12, dz, 1.0), 0.0)
    cut = a + t[:, None] * (b - a)
    a2 = np.where((za < z_min)[:, None], cut, a)
    b2 = np.where((zb < z_min)[:, None], cut, b)
    return a2, b2, keep


def _split_by_depth(a, b, idx, r, z_min, ratio: float = 1.3, most: int = 32):
    """Cut capsules whose far end is more than ``ratio`` times as deep as the near one into
    pieces of that depth ratio (at most ``most``), so each piece's screen band is tight."""
    z0 = np.maximum(np.minimum(a[:, 2], b[:, 2]) - r, z_min)
    z1 = np.maximum(a[:, 2], b[:, 2]) + r
    k = np.clip(np.ceil(np.log(z1 / z0) / np.log(ratio)), 1, most).astype(np.int64)
    if np.all(k == 1):
        return a, b, idx
    owner = np.repeat(np.arange(len(a)), k)
    i = np.arange(len(owner)) - np.repeat(np.cumsum(k) - k, k)
    za, zb = a[owner, 2], b[owner, 2]
    kk = k[owner].astype(float)
    # piece ends at depths spaced geometrically between the ends' depths (uniform when equal)
    ratio_ab = np.maximum(zb, z_min) / np.maximum(za, z_min)
    def at(frac):
        zs = np.maximum(za, z_min) * ratio_ab ** frac
        dz = zb - za
        return np.where(np.abs(dz) > 1e-12, (zs - za) / np.where(np.abs(dz) > 1e-12, dz, 1.0), frac)
    s0, s1 = at(i / kk), at((i + 1) / kk)
    d = b[owner] - a[owner]
    return a[owner] + s0[:, None] * d, a[owner] + s1[:, None] * d, idx[owner]


def capsule_fragments(intr: Intrinsics, cap: Capsules, lights: Lights) -> Fragments:
    """Fragments of every capsule at the candidate pixels of a band around its projected axis."""
    if len(cap.a) == 0:
        return Fragments.empty()
    f = intr.fx
    z_min = NEAR * 2
    a, b, keep = _clip_segments(cap.a, cap.b, z_min)
    idx = np.nonzero(keep)[0]
    if idx.size == 0:
        return Fragments.empty()
    a, b, idx = _split_by_depth(a[idx], b[idx], idx, cap.radius[idx], z_min)
    r = cap.radius[idx]
    z_lo = np.maximum(np.minimum(a[:, 2], b[:, 2]) - r, z_min)
    # band half width, px: the radius on screen (stretched by up to |d|^2 off the axis) plus the AA fringe
    stretch = 1.0 + (max(intr.cx, intr.width - intr.cx) / f) ** 2 + (max(intr.cy, intr.height - intr.cy) / intr.fy) ** 2
    half = np.maximum(r * f * stretch / z_lo, cap.min_px[idx]) + 0.55
    p0 = np.stack([f * a[:, 0] / a[:, 2] + intr.cx, intr.fy * a[:, 1] / a[:, 2] + intr.cy], -1)
    p1 = np.stack([f * b[:, 0] / b[:, 2] + intr.cx, intr.fy * b[:, 1] / b[:, 2] + intr.cy], -1)
    half = np.minimum(half, 2.0 * (intr.width + intr.height))
    u, v, j = _band_pixels(intr, p0, p1, half)
    if u.size == 0:
        return Fragments.empty()
    # closest approach between the ray tau * d, d = (x, y, 1) (tau is the depth), and the axis
    # a + s (b - a), s in [0, 1]; per-capsule dot products first, then per candidate
    ba = b - a
    C = np.maximum(np.einsum("ni,ni->n", ba, ba), 1e-18)
    E = np.einsum("ni,ni->n", ba, a)
    AA = np.einsum("ni,ni->n", a, a)
    x, y = _rays(intr, u, v)
    n2 = x * x + y * y + 1.0
    Bd = x * ba[j, 0] + y * ba[j, 1] + ba[j, 2]          # d . (b - a)
    Da = x * a[j, 0] + y * a[j, 1] + a[j, 2]             # d . a
    Cj, Ej = C[j], E[j]
    denom = Cj * n2 - Bd * Bd
    ok = denom > 1e-9 * Cj * n2
    s = np.clip(np.where(ok, (Da * Bd - Ej * n2) / np.where(ok, denom, 1.0), 0.0), 0.0, 1.0)
    tau = (Da + s * Bd) / n2                             # depth of the ray's closest point
    h2 = np.maximum(AA[j] + 2.0 * s * Ej + s * s * Cj - tau * tau * n2, 0.0)
    h = np.sqrt(h2)
    pixel_m = np.maximum(tau, NEAR) / f                  # metres per pixel at that depth
    r_eff = np.maximum(r[j], cap.min_px[idx][j] * pixel_m)
    cover = np.clip(0.5 + (r_eff - h) / pixel_m, 0.0, 1.0)
    hit = h <= r_eff
    depth = np.where(hit, tau - np.sqrt(np.maximum(r_eff * r_eff - h2, 0.0) / n2), tau)
    keep = (cover > 0.0) & (depth > NEAR)
    if not np.any(keep):
        return Fragments.empty()
    u, v, j, x, y, depth, cover, s = u[keep], v[keep], j[keep], x[keep], y[keep], depth[keep], cover[keep], s[keep]
    nx = depth * x - (a[j, 0] + s * ba[j, 0])            # surface point minus its axis point
    ny = depth * y - (a[j, 1] + s * ba[j, 1])
    nz = depth - (a[j, 2] + s * ba[j, 2])
    norm = np.maximum(np.sqrt(nx * nx + ny * ny + nz * nz), 1e-12)
    colour = _shade(cap.colour[idx][j], nx / norm, ny / norm, nz / norm, lights)
    return Fragments(v * intr.width + u, depth.astype(np.float32), cover.astype(np.float32), colour,
                     cap.obj[idx][j].astype(np.int32))


# --- compositing ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Composite:
    """Per pixel touched by a fragment: the blended colour and the nearest hit."""

    pix: np.ndarray       # (P,) int64, flat pixel indices (sorted, unique)
    colour: np.ndarray    # (P, 3) float32, blended colour in [0, 1]
    hit_depth: np.ndarray  # (P,) float32 m, depth of the nearest hit (inf: only fringe here)
    hit_obj: np.ndarray   # (P,) int32, object id of the nearest hit (-1: only fringe here)


def _one_per_object(frags: Fragments) -> Fragments:
    """Keep one fragment per (pixel, object): the nearest hit, else the largest coverage.

    The primitives of one object (the pieces of a line, a UAV's parts) touch and overlap;
    blending their anti-aliased fringes over each other would darken every joint.
    """
    if frags.pix.size == 0:
        return frags
    hit = frags.cover >= 0.5
    order = np.lexsort((np.where(hit, frags.depth, -frags.cover), ~hit, frags.obj, frags.pix))
    pix, obj = frags.pix[order], frags.obj[order]
    first = np.r_[True, (pix[1:] != pix[:-1]) | (obj[1:] != obj[:-1])]
    return frags.select(order[first])


def composite(frags: Fragments, background: np.ndarray, background_depth: np.ndarray,
              background_scale: float = 1.0) -> Composite:
    """Blend fragments front to back over ``background`` (flat (H*W, 3) colours, times
    ``background_scale`` in [0, 1]) where they are nearer than ``background_depth`` (flat (H*W,) m)."""
    in_front = frags.depth < background_depth[frags.pix]
    frags = _one_per_object(frags.select(in_front))
    if frags.pix.size == 0:
        e = np.zeros(0, np.int64)
        return Composite(e, np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32))
    order = np.lexsort((frags.depth, frags.pix))
    pix = frags.pix[order]
    cover = frags.cover[order].astype(np.float64)
    starts = np.flatnonzero(np.r_[True, pix[1:] != pix[:-1]])
    group = np.cumsum(np.r_[False, pix[1:] != pix[:-1]])
    # transmittance in front of each fragment: prod of (1 - cover) of the nearer ones of its pixel
    log_keep = np.log(np.maximum(1.0 - cover, 1e-12))
    csum = np.cumsum(log_keep)
    before = csum - log_keep
    trans = np.exp(before - before[starts][group])
    weight = cover * trans
    colour = np.add.reduceat(frags.colour[order] * weight[:, None], starts, axis=0)
    last = np.r_[starts[1:], len(pix)] - 1
    remaining = np.exp(csum[last] - before[starts])
    upix = pix[starts]
    colour += background[upix] * (remaining * background_scale)[:, None]
    # nearest hit: the first fragment (in depth order) that covers the pixel centre
    position = np.where(frags.cover[order] >= 0.5, np.arange(len(pix)), len(pix))
    first = np.minimum.reduceat(position, starts)
    has_hit = first < len(pix)
    firsts = np.where(has_hit, first, 0)
    hit_depth = np.where(has_hit, frags.depth[order][firsts], np.inf).astype(np.float32)
    hit_obj = np.where(has_hit, frags.obj[order][firsts], -1).astype(np.int32)
    return Composite(upix, np.clip(colour, 0.0, 1.0).astype(np.float32), hit_depth, hit_obj)
