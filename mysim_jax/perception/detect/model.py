"""The learned detector: a small CenterNet-style CNN (flax linen).

Network (:class:`CenterNet`): a strided convolution backbone down to 1/32 of the input, a
top-down path (upsample and add the lateral features) back to 1/4, and three heads at stride
``STRIDE`` = 4: a centre heatmap (one class, logits), the box size (log of width and height
in output cells) and the sub-cell offset of the box centre. No normalisation layers (plain
ReLU convolutions), so a forward pass has no state besides the parameters.

Coordinates. The network works in *edge coordinates* x = u + 0.5, y = v + 0.5 (the image
spans [0, W] x [0, H]; a renderer box (u_min, v_min, u_max, v_max) is
[u_min + 0.5, u_max + 0.5] there). Output cell (i, j) spans edge coordinates
[j s, (j + 1) s] x [i s, (i + 1) s] with s = STRIDE; a box's centre falls in one cell, which
is its positive in the heatmap, with a Gaussian of the box's size around it.

Training target and loss (:func:`encode_targets`, :func:`loss_fn`): the CenterNet focal loss
on the heatmap (alpha 2, beta 4), normalised by the number of boxes, plus L1 losses on the
log size and the offset at the centre cell. A target marked ``ignore`` adds no positive and
masks the heatmap loss over its box. A box may carry a weight of its positive's focal term
(default 1; training uses it to weigh targets that occluders or the crop's edge hide in part).

Decoding (:func:`decode`): sigmoid heatmap, local maxima in 3 x 3 windows, the ``top_k``
highest with their boxes.

Inference (:class:`CNNDetector`): the image is resized to ``input_width`` px wide (its aspect
kept), padded on the right and bottom (edge pixels repeated) to multiples of 32, run through
the jitted network (one compile per padded size), and the boxes are scaled back to the input
image's pixels.

Image pyramid. With ``pyramid`` = (1.0, 0.5, ...) the network also runs on the image resized
to ``input_width * level`` px wide. A target close to the camera can be larger than anything
the network saw whole in its training crops (it then finds parts of it); at a coarser level
it has a size the network knows, and a far target is larger at a finer one. Each level keeps
the boxes whose longer side, in that level's network pixels, lies in ``pyramid_band_px``
(lo, hi), except that the finest level keeps everything below hi and the coarsest everything
above lo. The kept boxes of all levels are merged by non-maximum suppression (IoU
``PYRAMID_NMS_IOU``), best first. With one level (the default) nothing is dropped or merged.

Flip test (``flip_test``, CenterNet's): each level also runs on the mirrored image, and the
two passes' heatmaps (probabilities) and log box sizes are averaged cell by cell before
decoding (the level's width is then rounded to a multiple of ``STRIDE``, so the mirrored
cells line up with the image's); the centre offsets are the unmirrored pass's. It doubles
the network's work.

Second stage (``refiner``, :mod:`~mysim_jax.perception.detect.refine`). With one, the
network above only proposes: its merged boxes scoring at least the refiner's
``candidate_min_score`` are each looked at again in a window scaled to a fixed size, and the
detections are the second stage's boxes with its scores (by default the geometric mean of
both stages' probabilities), merged by non-maximum suppression (IoU ``PYRAMID_NMS_IOU``)
and cut at the score floor.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import cv2
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from mysim_jax.core import rng
from mysim_jax.perception.camera import PerceptionError
from mysim_jax.perception.detect import Detection, default_weights_path
from mysim_jax.perception.detect.metrics import iou
from mysim_jax.perception.detect.refine import Refiner, RefineSettings, normalise
from mysim_jax.perception.detect.team import explained_by_teammates

STRIDE = 4          # px of network input per output cell
PYRAMID_NMS_IOU = 0.5   # boxes of pyramid levels overlapping more than this are one detection
PAD_TO = 32         # input sides are padded to multiples of this (the backbone's total stride)


class CenterNet(nn.Module):
    """(B, H, W, 3) images in [-0.5, 0.5] (H, W multiples of 32) -> (B, H/4, W/4, 5) outputs:
    heatmap logit, log width, log height (output cells), centre offset x, y (cells)."""

    widths: tuple[int, ...] = (16, 32, 48, 64, 96)    # channels at strides 2, 4, 8, 16, 32

    @nn.compact
    def __call__(self, x):
        conv = partial(nn.Conv, kernel_size=(3, 3), padding="SAME",
                       kernel_init=rng.as_matrix(nn.initializers.he_normal()))
        feats = []
        for k, c in enumerate(self.widths):
            x = nn.relu(conv(c, strides=(2, 2), name=f"down{k}")(x))
            if k > 0:
                x = nn.relu(conv(c, name=f"body{k}")(x))
            feats.append(x)
        # top-down path: stride 32 -> 4
        y = feats[-1]
        for k in range(len(self.widths) - 2, 0, -1):
            c = self.widths[k]
            b, h, w, _ = feats[k].shape
            y = jax.image.resize(y, (b, h, w, y.shape[-1]), method="nearest")
            lateral = nn.Conv(c, (1, 1), name=f"lat{k}", kernel_init=rng.as_matrix(nn.initializers.lecun_normal()))
            y = lateral(y) + feats[k]
            y = nn.relu(conv(c, name=f"up{k}")(y))
        head = nn.relu(conv(self.widths[1], name="head")(y))
        heat = nn.Conv(1, (1, 1), name="heat", kernel_init=rng.as_matrix(nn.initializers.lecun_normal()),
                       bias_init=nn.initializers.constant(-4.0))(head)
        box = nn.Conv(4, (1, 1), name="box", kernel_init=rng.as_matrix(nn.initializers.normal(1e-3)))(head)
        return jnp.concatenate([heat, box], axis=-1)


# --- training targets and loss ----------------------------------------------------------------


def encode_targets(boxes: list, shape: tuple[int, int]) -> dict[str, np.ndarray]:
    """Heatmap, regression targets and masks of one image of input size ``shape`` (H, W) px.

    ``boxes``: list of ((4,) renderer box in input px, ignore flag[, weight of its positive]).
    Returns arrays at the output resolution (h, w) = (H / 4, W / 4): ``heat`` (h, w) Gaussian
    peaks in [0, 1], ``weight`` (h, w) heatmap-loss weight (0 over ignored boxes), ``pos_weight``
    (h, w) weight of the positive at each box's centre cell (1 elsewhere), ``index`` () flat centre cell
    of the first counted box, ``reg`` (4,) its log w, log h, offset x, y, ``has`` () 1 if it exists.
    """
    H, W = shape
    h, w = H // STRIDE, W // STRIDE
    heat = np.zeros((h, w), np.float32)
    weight = np.ones((h, w), np.float32)
    pos_weight = np.ones((h, w), np.float32)
    out = dict(heat=heat, weight=weight, pos_weight=pos_weight, index=np.int32(0), reg=np.zeros(4, np.float32),
               has=np.float32(0))
    ys, xs = np.mgrid[0:h, 0:w]
    for box, ignore, *extra in boxes:
        x0, y0, x1, y1 = (np.asarray(box, float) + 0.5) / STRIDE        # edge coordinates, cells
        if ignore:
            weight[max(int(np.floor(y0)), 0):int(np.ceil(y1)) + 1, max(int(np.floor(x0)), 0):int(np.ceil(x1)) + 1] = 0
            continue
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        j, i = int(np.clip(np.floor(cx), 0, w - 1)), int(np.clip(np.floor(cy), 0, h - 1))
        bw, bh = max(x1 - x0, 1e-3), max(y1 - y0, 1e-3)
        sigma = max(0.5, 0.12 * np.sqrt(bw * bh))
        g = np.exp(-((xs - j) ** 2 + (ys - i) ** 2) / (2 * sigma ** 2))
        np.maximum(heat, g.astype(np.float32), out=heat)
        heat[i, j] = 1.0
        pos_weight[i, j] = float(extra[0]) if extra else 1.0
        if not out["has"]:
            out.update(index=np.int32(i * w + j), reg=np.array([np.log(bw), np.log(bh), cx - j, cy - i], np.float32),
                       has=np.float32(1))
    return out


def loss_fn(params, model: CenterNet, images, targets, size_weight: float = 0.5) -> tuple[jnp.ndarray, dict]:
    """Mean loss over a batch: focal heatmap loss (each positive times ``targets['pos_weight']``
    if given) + ``size_weight`` * L1 on log size + L1 on offset."""
    out = model.apply({"params": params}, normalise(images))
    B = out.shape[0]
    logit = out[..., 0].reshape(B, -1)
    heat = targets["heat"].reshape(B, -1)
    weight = targets["weight"].reshape(B, -1)
    p = jax.nn.sigmoid(logit)
    log_p, log_1p = jax.nn.log_sigmoid(logit), jax.nn.log_sigmoid(-logit)
    pos = (heat >= 1.0).astype(jnp.float32)
    pos_weight = targets["pos_weight"].reshape(B, -1) if "pos_weight" in targets else 1.0
    pos_loss = -pos * pos_weight * (1 - p) ** 2 * log_p
    neg_loss = -(1 - pos) * (1 - heat) ** 4 * p ** 2 * log_1p
    n_pos = jnp.maximum(jnp.sum(pos), 1.0)
    focal = jnp.sum(weight * (pos_loss + neg_loss)) / n_pos
    reg_pred = jnp.take_along_axis(out[..., 1:].reshape(B, -1, 4), targets["index"][:, None, None], axis=1)[:, 0]
    err = jnp.abs(reg_pred - targets["reg"]) * targets["has"][:, None]
    n_box = jnp.maximum(jnp.sum(targets["has"]), 1.0)
    size = jnp.sum(err[:, :2]) / n_box
    offset = jnp.sum(err[:, 2:]) / n_box
    total = focal + size_weight * size + offset
    return total, dict(focal=focal, size=size, offset=offset)


# --- decoding ---------------------------------------------------------------------------------


def decode(out: jnp.ndarray, top_k: int = 10):
    """(B, h, w, 5) network outputs -> scores (B, k) and boxes (B, k, 4) in renderer px of the
    network input, best first."""
    B, h, w, _ = out.shape
    heat = jax.nn.sigmoid(out[..., 0])
    peak = jax.lax.reduce_window(heat, -jnp.inf, jax.lax.max, (1, 3, 3), (1, 1, 1), "SAME")
    heat = jnp.where(heat >= peak, heat, 0.0).reshape(B, -1)
    scores, index = jax.lax.top_k(heat, top_k)
    reg = jnp.take_along_axis(out[..., 1:].reshape(B, -1, 4), index[..., None], axis=1)
    i, j = index // w, index % w
    cx, cy = j + reg[..., 2], i + reg[..., 3]
    bw, bh = jnp.exp(jnp.clip(reg[..., 0], -3, 6)), jnp.exp(jnp.clip(reg[..., 1], -3, 6))
    boxes = jnp.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], axis=-1) * STRIDE - 0.5
    return scores, boxes


def _suppress(dets: list[Detection]) -> list[Detection]:
    """Greedy non-maximum suppression (IoU above ``PYRAMID_NMS_IOU``), best first."""
    if len(dets) < 2:
        return dets
    xywh = [[float(d.box[0]), float(d.box[1]), float(d.box[2] - d.box[0]), float(d.box[3] - d.box[1])] for d in dets]
    keep = cv2.dnn.NMSBoxes(xywh, [d.score for d in dets], 0.0, PYRAMID_NMS_IOU)
    keep = sorted(np.asarray(keep, int).reshape(-1).tolist(), key=lambda i: -dets[i].score)
    return [dets[i] for i in keep]


# --- the detector -----------------------------------------------------------------------------


def check_image(image) -> np.ndarray:
    """Raise unless ``image`` is an (H, W, 3) uint8 RGB array with H, W >= 8."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise PerceptionError(f"detect takes an (H, W, 3) uint8 RGB image, got {image.dtype} {image.shape}")
    if image.shape[0] < 8 or image.shape[1] < 8:
        raise PerceptionError(f"image {image.shape[1]} x {image.shape[0]} px is too small to detect in (at least 8 x 8)")
    return image


@dataclass(frozen=True)
class RegionSettings:
    """How :meth:`CNNDetector.detect_region` looks around an expected target."""

    input_px: int = 192            # px, side of the network input (a multiple of 32)
    target_px: float = 48.0        # px, the expected target's longer side at the network's scale
    min_window_px: float = 96.0    # px of the image, the smallest window side (room for prediction errors)
    max_candidates: int = 4        # first-stage candidates the second stage looks at, best first
    max_level: float | None = None  # largest scale (x the pyramid's level 1) for a small target; None: the pyramid's
    teammate_gate: float = 1.5     # a detection fitting a teammate's expected box below this, and better than the
    teammate_margin: float = 0.5   # target's by this margin, is the teammate's (detect.team.fit: centre offset /
                                   # side + |log size ratio|; chosen on the selection draw, docs/detector.md)
    hint_candidate: bool = False   # the second stage also looks at the expected box itself (a square of the
    hint_score: float = 0.3        # expected side at the expected centre) as a candidate of this first-stage
    hint_overlap: float = 0.1      # score; its detection is dropped where it overlaps a better one at this IoU

    def __post_init__(self):
        if self.input_px < PAD_TO or self.input_px % PAD_TO:
            raise PerceptionError(f"region input_px must be a positive multiple of {PAD_TO}, got {self.input_px}")
        if self.max_candidates < 1:
            raise PerceptionError(f"region max_candidates must be at least 1, got {self.max_candidates}")
        if not (self.target_px > 0 and self.min_window_px > 0):
            raise PerceptionError(f"region target_px and min_window_px must be positive, got "
                                  f"{self.target_px}, {self.min_window_px}")
        if not (self.teammate_gate >= 0 and self.teammate_margin >= 0):
            raise PerceptionError(f"region teammate_gate and teammate_margin must be >= 0, got "
                                  f"{self.teammate_gate}, {self.teammate_margin}")
        if not (0 < self.hint_score <= 1 and 0 <= self.hint_overlap <= 1):
            raise PerceptionError(f"region hint_score must be in (0, 1] and hint_overlap in [0, 1], got "
                                  f"{self.hint_score}, {self.hint_overlap}")


@dataclass
class CNNDetector:
    """The learned detector (see the module doc). ``min_score``: detections below it are dropped."""

    params: dict
    widths: tuple[int, ...] = (16, 32, 48, 64, 96)
    input_width: int = 640          # px, images are resized to this width
    min_score: float = 0.3
    top_k: int = 10
    pyramid: tuple[float, ...] = (1.0,)   # image scales (x input_width) the network runs at; see the module doc
    pyramid_band_px: tuple[float, float] = (24.0, 96.0)   # box sides (network px) a level keeps; see the module doc
    flip_test: bool = False         # also run each level on the mirrored image and average; see the module doc
    refiner: object | None = None   # the second stage (refine.Refiner); None: the first stage alone
    region: RegionSettings = RegionSettings()   # region mode (detect_region) when not given there

    def __post_init__(self):
        self.pyramid = tuple(float(s) for s in self.pyramid)
        if not self.pyramid or any(not 0.0 < s <= 4.0 for s in self.pyramid):
            raise PerceptionError(f"detector pyramid levels must be scales in (0, 4], got {self.pyramid}")
        if len(set(self.pyramid)) != len(self.pyramid):
            raise PerceptionError(f"detector pyramid levels must differ, got {self.pyramid}")
        self.pyramid_band_px = tuple(float(x) for x in self.pyramid_band_px)
        if len(self.pyramid_band_px) != 2 or not 0.0 <= self.pyramid_band_px[0] < self.pyramid_band_px[1]:
            raise PerceptionError(f"detector pyramid_band_px must be (lo, hi) px with 0 <= lo < hi, "
                                  f"got {self.pyramid_band_px}")
        self.model = CenterNet(widths=tuple(self.widths))
        self._forward = jax.jit(lambda p, x: decode(self.model.apply({"params": p}, normalise(x)), self.top_k))
        self._forward_flip = jax.jit(self._flip_averaged, static_argnums=3)

    def _flip_averaged(self, params, x, x_mirrored, cells: int):
        """Decoded detections of ``x`` with the heatmap and box sizes averaged with those of
        ``x_mirrored`` (each image mirrored before padding, so its first ``cells`` output
        columns are the image's, in reverse order); offsets are the unmirrored pass's."""
        both = self.model.apply({"params": params}, normalise(jnp.concatenate([x, x_mirrored])))
        out, mirrored = both[: x.shape[0]], both[x.shape[0]:]
        back = mirrored[:, :, :cells][:, :, ::-1]
        heat = 0.5 * (jax.nn.sigmoid(out[..., :cells, 0]) + jax.nn.sigmoid(back[..., 0]))
        heat = jnp.clip(heat, 1e-6, 1 - 1e-6)
        merged = out[:, :, :cells].at[..., 0].set(jnp.log(heat) - jnp.log1p(-heat))
        merged = merged.at[..., 1:3].set(0.5 * (out[..., :cells, 1:3] + back[..., 1:3]))
        out = out.at[:, :, :cells].set(merged)
        return decode(out, self.top_k)

    def _level_width(self, level: float) -> int:
        """Network input width (px, before padding) at pyramid ``level``: a multiple of
        ``STRIDE`` with ``flip_test``, so the mirrored image's output cells line up."""
        w = max(int(round(self.input_width * level)), 8)
        return max(STRIDE * round(w / STRIDE), STRIDE * 2) if self.flip_test else w

    def _prepare(self, image, level: float = 1.0) -> tuple[np.ndarray, float, float, np.ndarray | None]:
        """The network input at ``level`` (resized, padded), the x and y scales back to the
        image, and with ``flip_test`` the mirrored input (mirrored before padding)."""
        H, W = image.shape[:2]
        w = self._level_width(level)
        h = max(int(round(H * w / W)), 1)
        x = image if (w, h) == (W, H) else cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA if w < W else cv2.INTER_LINEAR)
        ph, pw = -h % PAD_TO, -w % PAD_TO

        def pad(a):
            return cv2.copyMakeBorder(a, 0, ph, 0, pw, cv2.BORDER_REPLICATE) if ph or pw else a

        mirrored = pad(np.ascontiguousarray(x[:, ::-1])) if self.flip_test else None
        return pad(x), W / w, H / h, mirrored

    def detect_batch(self, images: list[np.ndarray], min_score: float | None = None) -> list[list[Detection]]:
        """:meth:`detect` of several images of one size (one network call)."""
        images = [check_image(im) for im in images]
        if len({im.shape for im in images}) > 1:
            raise PerceptionError("detect_batch takes images of one size")
        floor = self.min_score if min_score is None else min_score
        final_floor = floor
        if self.refiner is not None:       # the first stage proposes, the second decides
            floor = self.refiner.settings.candidate_min_score
        H, W = images[0].shape[:2]
        several = len(self.pyramid) > 1
        lo, hi = self.pyramid_band_px
        out = [[] for _ in images]
        for level in self.pyramid:
            keep_lo = -np.inf if level == max(self.pyramid) else lo     # the finest level keeps the smallest
            keep_hi = np.inf if level == min(self.pyramid) else hi      # the coarsest keeps the largest
            prepared = [self._prepare(im, level) for im in images]
            x = np.stack([p[0] for p in prepared])
            if self.flip_test:
                scores, boxes = self._forward_flip(self.params, x, np.stack([p[3] for p in prepared]),
                                                   self._level_width(level) // STRIDE)
            else:
                scores, boxes = self._forward(self.params, x)
            scores, boxes = np.asarray(scores), np.asarray(boxes, dtype=float)
            for dets, (_, sx, sy, _), sc, bx in zip(out, prepared, scores, boxes):
                scale = np.array([sx, sy, sx, sy])
                for s, b in zip(sc, bx):
                    if s < floor:
                        break
                    side = max(b[2] - b[0], b[3] - b[1])          # network px of this level
                    if several and not keep_lo <= side <= keep_hi:
                        continue
                    box = (b + 0.5) * scale - 0.5                     # back to the input image's px
                    box = np.clip(box, -0.5, [W - 0.5, H - 0.5, W - 0.5, H - 0.5])
                    if box[2] > box[0] and box[3] > box[1]:
                        dets.append(Detection(box=box, score=float(s)))
        out = [_suppress(d) for d in out] if several else out
        if self.refiner is not None:
            out = [[d for d in _suppress(r) if d.score >= final_floor] for r in self.refiner.refine(images, out)]
        return out

    def detect(self, image: np.ndarray, min_score: float | None = None) -> list[Detection]:
        """Detections in ``image`` ((H, W, 3) uint8 RGB, any size), best first, scores >= ``min_score``
        (default: the detector's)."""
        return self.detect_batch([image], min_score)[0]

    def region_window(self, image_shape, centre, side_px: float, region: RegionSettings) -> tuple[np.ndarray, float]:
        """The square window ``(x0, y0, side)`` (image px, edge coordinates) that
        :meth:`detect_region` looks in for a target expected at ``centre`` with a box of
        longer side ``side_px``, and its scale (network px per image px). Centred on
        ``centre`` and then moved inside the image along each axis where it fits; a window
        wider than the image is centred on it."""
        lo = min(self.pyramid)
        hi = max(self.pyramid) if region.max_level is None else region.max_level
        scale_of_level = self.input_width / image_shape[1]      # network px per image px at level 1
        scale = float(np.clip(region.target_px / max(float(side_px), 1.0), lo * scale_of_level, hi * scale_of_level))
        side = region.input_px / scale
        if side < region.min_window_px:          # a near-centred small target: widen the window, coarser scale
            side = float(region.min_window_px)
            scale = region.input_px / side
        # centred on the expected target, then moved inside the image where it fits (the image's
        # own pixels rather than repeated border pixels around a target near the border)
        H, W = image_shape[:2]
        x0 = float(centre[0]) + 0.5 - side / 2
        y0 = float(centre[1]) + 0.5 - side / 2
        x0 = min(max(x0, 0.0), W - side) if side <= W else (W - side) / 2
        y0 = min(max(y0, 0.0), H - side) if side <= H else (H - side) / 2
        return np.array([x0, y0, side]), scale

    def detect_region(self, image: np.ndarray, centre, side_px: float, region: RegionSettings | None = None,
                      min_score: float | None = None, teammates: np.ndarray | None = None) -> list[Detection]:
        """Detections near where a tracker expects the target (region-of-interest mode).

        ``centre``: (2,) px, the expected box centre; ``side_px``: the expected box's longer
        side (px). One square window around ``centre`` (:meth:`region_window`) is resized to
        ``region.input_px`` so that the expected target spans about ``region.target_px``
        network pixels (within the scales of the pyramid), and the network runs on it once
        (with the flip test when the detector has it); the candidates go through the second
        stage on the full image as in :meth:`detect`. Boxes are in ``image``'s pixels, best
        first. Far cheaper than :meth:`detect` (one small input instead of the pyramid); a
        target outside the window is not found, so a tracker without a usable hint uses
        :meth:`detect`.

        ``teammates``: (K, 4) px boxes where the team's own UAVs are expected in ``image``
        (:func:`~mysim_jax.perception.detect.team.expected_boxes`); detections that a
        teammate explains better than the expected target
        (:func:`~mysim_jax.perception.detect.team.explained_by_teammates`,
        ``region.teammate_gate`` and ``teammate_margin``) are dropped, and a second stage
        with the teammate channel (:attr:`~mysim_jax.perception.detect.refine.Refiner.uses_teammates`)
        sees them as its fourth input.

        ``region.hint_candidate`` (with a second stage): the expected box itself (the square of
        side ``side_px`` at ``centre``) is one more candidate, of first-stage score
        ``region.hint_score``. A first-stage box on a target partly hidden behind a teammate
        often covers both, and the second stage's window around it is then off; the window
        around the expected box is on the target. Its detection is kept unless it overlaps one
        of the others that scores higher at IoU ``region.hint_overlap`` or more (then the
        first stage had the target already), so it adds a box where the candidates missed,
        not a duplicate. It leans on the hint: where the track's prediction is off, so is this
        window, and the second stage has to reject what it shows."""
        image = check_image(image)
        region = self.region if region is None else region
        if not (np.all(np.isfinite(np.asarray(centre, float))) and np.isfinite(side_px) and side_px > 0):
            raise PerceptionError(f"detect_region needs a finite centre and a positive box side, got {centre}, {side_px}")
        floor = self.min_score if min_score is None else min_score
        first_floor = self.refiner.settings.candidate_min_score if self.refiner is not None else floor
        (x0, y0, side), scale = self.region_window(image.shape, centre, side_px, region)
        n = region.input_px
        # the window resized to n x n (window px j <-> edge coordinate x0 + (j + 0.5) / scale), the
        # image's edge pixels repeated beyond it; when shrinking, the image is area-averaged first
        # (as the pyramid does) and the map starts from that smaller image (sx, sy: its scale)
        src, sx, sy = image, 1.0, 1.0
        if scale < 1.0:
            src = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            sx, sy = src.shape[1] / image.shape[1], src.shape[0] / image.shape[0]
        M = np.array([[scale / sx, 0.0, 0.5 * scale / sx - x0 * scale - 0.5],
                      [0.0, scale / sy, 0.5 * scale / sy - y0 * scale - 0.5]])
        x = cv2.warpAffine(src, M, (n, n), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        x = x[None]
        if self.flip_test:
            scores, boxes = self._forward_flip(self.params, x, np.ascontiguousarray(x[:, :, ::-1]), n // STRIDE)
        else:
            scores, boxes = self._forward(self.params, x)
        H, W = image.shape[:2]
        dets = []
        for s, b in zip(np.asarray(scores)[0], np.asarray(boxes, float)[0]):
            if s < first_floor:
                break
            box = (b + 0.5) / scale + np.array([x0, y0, x0, y0]) - 0.5     # window px -> image px
            box = np.clip(box, -0.5, [W - 0.5, H - 0.5, W - 0.5, H - 0.5])
            if box[2] > box[0] and box[3] > box[1]:
                dets.append(Detection(box=box, score=float(s)))
        if self.refiner is not None:
            dets = [d for d in _suppress(self._refine_region(image, dets[: region.max_candidates], centre, side_px,
                                                             region, teammates)) if d.score >= floor]
        if teammates is not None and dets:
            theirs = explained_by_teammates(np.array([d.box for d in dets]), centre, side_px, teammates,
                                            region.teammate_gate, region.teammate_margin)
            dets = [d for d, t in zip(dets, theirs) if not t]
        return dets

    def _refine_region(self, image, candidates, centre, side_px, region: RegionSettings, teammates):
        """The second stage on region mode's first-stage ``candidates`` (and, with
        ``region.hint_candidate``, on the expected box in the same batch; see
        :meth:`detect_region`): detections best first, before suppression."""
        cands = [candidates]
        if region.hint_candidate:
            c, h = np.asarray(centre, float), 0.5 * float(side_px)
            cands.append([Detection(box=np.array([c[0] - h, c[1] - h, c[0] + h, c[1] + h]), score=region.hint_score)])
        refined = self.refiner.refine([image] * len(cands), cands,
                                      teammates=None if teammates is None else [teammates] * len(cands))
        dets = refined[0]
        if region.hint_candidate:
            extra = [d for d in refined[1]
                     if not any(a.score > d.score and iou(a.box, d.box) >= region.hint_overlap for a in dets)]
            dets = sorted(dets + extra, key=lambda d: -d.score)
        return dets

    # --- files --------------------------------------------------------------------------------

    def save(self, path: str | Path) -> Path:
        """Write the parameters and architecture as one msgpack file."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = json.dumps(dict(widths=list(self.widths), input_width=self.input_width, min_score=self.min_score,
                               top_k=self.top_k, stride=STRIDE, pyramid=list(self.pyramid),
                               pyramid_band_px=list(self.pyramid_band_px), flip_test=self.flip_test,
                               refine=None if self.refiner is None else self.refiner.settings.to_dict()))
        as_np = lambda tree: jax.tree.map(lambda a: np.asarray(a, np.float32), tree)
        blob = {"meta": meta, "params": as_np(self.params)}
        if self.refiner is not None:      # the second stage's networks: refine_params, refine_params_1, ...
            for k, member in enumerate(self.refiner.members):
                blob["refine_params" if k == 0 else f"refine_params_{k}"] = as_np(member)
        path.write_bytes(serialization.msgpack_serialize(blob))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "CNNDetector":
        """A detector from a file written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise PerceptionError(f"no detector weights at {path}; train them with scripts/train_detector.py "
                                  f"configs/detector.yaml, or pass the path of a detector.msgpack")
        try:
            blob = serialization.msgpack_restore(path.read_bytes())
            meta = json.loads(blob["meta"])
            params = blob["params"]
        except Exception as exc:     # a corrupt or foreign file: say which
            raise PerceptionError(f"{path} is not a detector weights file ({type(exc).__name__}: {exc})") from None
        if meta.get("stride") != STRIDE:
            raise PerceptionError(f"{path} was written for output stride {meta.get('stride')}, this code uses {STRIDE}")
        refiner = None
        if meta.get("refine") is not None:
            settings = RefineSettings.from_dict(meta["refine"])
            try:
                members = [blob["refine_params" if k == 0 else f"refine_params_{k}"] for k in range(settings.members)]
            except KeyError as exc:
                raise PerceptionError(f"{path} lacks the second stage's network {exc}") from None
            refiner = Refiner(members, settings)
        return cls(refiner=refiner, params=params, widths=tuple(meta["widths"]), input_width=int(meta["input_width"]),
                   min_score=float(meta["min_score"]), top_k=int(meta["top_k"]),
                   pyramid=tuple(meta.get("pyramid", (1.0,))),
                   pyramid_band_px=tuple(meta.get("pyramid_band_px", (24.0, 96.0))),
                   flip_test=bool(meta.get("flip_test", False)))


def load_detector(path: str | Path | None = None) -> CNNDetector:
    """The learned detector with weights from ``path`` (default: the committed ones,
    :func:`~mysim_jax.perception.detect.default_weights_path`)."""
    return CNNDetector.load(default_weights_path() if path is None else path)
