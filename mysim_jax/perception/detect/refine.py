"""The detector's second stage: each candidate box of the first stage is looked at again.

The first stage (:class:`~mysim_jax.perception.detect.model.CenterNet`) sees the whole
image at a few fixed scales, so a target 8 px across gets a handful of output cells, and an
occluder in front of it (the net's lines, a UAV) can cost it its score or its box. The
second stage (:class:`RefineNet`) takes a square *window* around each candidate, scaled to
``size`` x ``size`` px whatever the candidate's size (:func:`cut_windows`), and says whether
a target is there (a logit) and where its box is (the box's edges, as a change of the
candidate's, in window units). In the window every target has about the same size, so the
second stage need not learn sizes, and a far target is seen as large as a near one.

Windows (:func:`windows_of`). A candidate box of sides (w, h) px centred at c gets the
square window of side ``max(context * max(w, h), min_px)`` centred at c, rounded to whole
pixels; parts beyond the image repeat its edge pixels (as the first stage pads). The
window is resized to ``size`` px (area averaging when it shrinks, bilinear when it grows).

Coordinates. A box in window units is its edge coordinates (see
:mod:`~mysim_jax.perception.detect.model`) relative to the window's left / top edge,
divided by the window's side: the window spans [0, 1] x [0, 1].

Training samples (:func:`sample_labels`). A candidate on a frame with a counted target is a
positive if its IoU with the target's box is at least ``POS_IOU``, and then its box target
is the target's box; a candidate overlapping an ignored target (too hidden or too small to
count) by more than ``IGNORE_IOU``, or a counted one by an IoU between ``IGNORE_IOU`` and
``POS_IOU``, is neither (no classification loss); the rest are negatives. Loss
(:func:`loss_fn`): binary cross-entropy of the logit plus ``box_weight`` x L1 of the
positives' edges in window units.

Ensembles (``members``). The second stage may be several networks of the same shape trained
alike but from different seeds (``refine.seed``, ``seed + 1``, ...): each looks at the same
windows, and their probabilities and boxes are averaged (:func:`apply_members`).

Scores (``score``). ``"refined"``: a detection's score is the second stage's probability
alone; ``"geometric"``: the geometric mean of both stages' probabilities, sqrt(p1 * p2), so
a window the second stage likes but the first stage barely proposed (a background patch
that looks like a drone at 8 px) is not put above a target both stages see.

The team's UAVs as a fourth channel (``teammate_channel``). A teammate in front of the
target looks like it (both are small quadrotors), and the target's box is its visible part
only. A second stage with four input channels also sees, beside the window's colours, a mask
of where the team expects its own UAVs in that window (:func:`teammate_masks`: 255 inside a
teammate's expected box, :func:`~mysim_jax.perception.detect.team.expected_boxes`, 0
elsewhere), so it can tell the teammate's rotor discs from the target's. Without the team's
boxes (a whole-image search) the mask is empty. The network is the same but for its first
layer's input channels (:func:`input_channels`); :func:`widen_input` gives a three-channel
network's parameters a fourth channel of zero weights, which computes exactly what the
three-channel one did (a fine-tune's start).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import partial

import cv2
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from mysim_jax.core import rng
from mysim_jax.perception.camera import PerceptionError
from mysim_jax.perception.detect import Detection
from mysim_jax.perception.detect.metrics import iou

POS_IOU = 0.25       # a candidate at least this IoU with a counted target is a positive
IGNORE_IOU = 0.1     # below POS_IOU but above this (or above this with an ignored target): no label


class RefineNet(nn.Module):
    """(N, S, S, 3) windows in [-0.5, 0.5] -> (N, 5): target logit and the box's edge changes
    (u_min, v_min, u_max, v_max; window units) from the candidate's.

    ``with_mask=True`` also returns (N, S/2, S/2) logits of which window pixels show the
    target (the visible-pixel head, trained with ``refine.mask_weight``: its parameters are
    ``mask*``; a network without them computes the same logit and box)."""

    widths: tuple[int, ...] = (24, 32, 48, 64, 96)    # channels at strides 1, 2, 4, 8, 16
    hidden: int = 128
    mask_width: int = 32                              # channels of the visible-pixel head

    @nn.compact
    def __call__(self, x, with_mask: bool = False):
        conv = partial(nn.Conv, kernel_size=(3, 3), padding="SAME",
                       kernel_init=rng.as_matrix(nn.initializers.he_normal()))
        features = []
        for k, c in enumerate(self.widths):
            x = nn.relu(conv(c, strides=(1, 1) if k == 0 else (2, 2), name=f"down{k}")(x))
            if k > 0:
                x = nn.relu(conv(c, name=f"body{k}")(x))
            features.append(x)
        x = x.reshape(x.shape[0], -1)
        x = nn.relu(nn.Dense(self.hidden, kernel_init=nn.initializers.he_normal(), name="fc")(x))
        logit = nn.Dense(1, bias_init=nn.initializers.constant(-2.0), name="logit")(x)
        delta = nn.Dense(4, kernel_init=nn.initializers.normal(1e-3), name="box")(x)
        out = jnp.concatenate([logit, delta], axis=-1)
        if not with_mask:
            return out
        # a top-down path (as a feature pyramid's) from the coarsest map to stride 2
        lateral = partial(nn.Conv, self.mask_width, kernel_size=(1, 1))
        m = lateral(name="mask_lat_top")(features[-1])
        for k in range(len(self.widths) - 2, 0, -1):
            n, h, w, c = m.shape
            m = jax.image.resize(m, (n, 2 * h, 2 * w, c), "nearest") + lateral(name=f"mask_lat{k}")(features[k])
            m = nn.relu(conv(self.mask_width, name=f"mask_conv{k}")(m))
        mask = nn.Conv(1, kernel_size=(1, 1), name="mask_out")(m)[..., 0]
        return out, mask


# --- windows ----------------------------------------------------------------------------------


def normalise(images: np.ndarray | jnp.ndarray):
    """uint8 RGB (and the teammate mask, when there is one) -> float32 in [-0.5, 0.5]."""
    return jnp.asarray(images, jnp.float32) * (1.0 / 255.0) - 0.5


def input_channels(params) -> int:
    """The input channels of a second-stage network's parameters: 3 (the window's colours)
    or 4 (and the teammate mask)."""
    return int(np.shape(params["down0"]["kernel"])[2])


def widen_input(params, channels: int = 4):
    """``params`` with zero first-layer weights for input channels up to ``channels``: the
    network computes the same as before whatever the new channels hold."""
    kernel = np.asarray(params["down0"]["kernel"])
    if kernel.shape[2] > channels:
        raise PerceptionError(f"the second stage has {kernel.shape[2]} input channels, more than the {channels} asked for")
    pad = np.zeros(kernel.shape[:2] + (channels - kernel.shape[2],) + kernel.shape[3:], kernel.dtype)
    out = dict(params)
    out["down0"] = {**params["down0"], "kernel": np.concatenate([kernel, pad], axis=2)}
    return out


def teammate_masks(teammates, windows: np.ndarray, size: int) -> np.ndarray:
    """(N, size, size) uint8: for each (x0, y0, side) window of :func:`windows_of`, 255 on
    the window pixels (resized to ``size``) that a box of ``teammates`` ((K, 4) renderer
    boxes px, or None: none) covers, 0 elsewhere. A pixel is covered when its centre is
    inside the box."""
    windows = np.asarray(windows, np.int64).reshape(-1, 3)
    out = np.zeros((len(windows), size, size), np.uint8)
    tm = np.zeros((0, 4)) if teammates is None else np.asarray(teammates, float).reshape(-1, 4)
    if len(tm) == 0:
        return out
    e = tm + 0.5                                              # edge coordinates
    centres = np.arange(size) + 0.5                           # window pixel centres, window px
    for n, (x0, y0, side) in enumerate(windows):
        f = size / float(side)
        for u0, v0, u1, v1 in e:
            cols = (centres >= (u0 - x0) * f) & (centres < (u1 - x0) * f)
            rows = (centres >= (v0 - y0) * f) & (centres < (v1 - y0) * f)
            out[n][np.ix_(rows, cols)] = 255
    return out


def windows_of(boxes: np.ndarray, context: float, min_px: float) -> np.ndarray:
    """(N, 4) renderer boxes (px) -> (N, 3) integer windows (x0, y0, side) px: the left / top
    edge (edge coordinates) and the side of the square around each box (see the module doc)."""
    boxes = np.asarray(boxes, float).reshape(-1, 4)
    e = boxes + 0.5                                          # edge coordinates
    cx, cy = (e[:, 0] + e[:, 2]) / 2, (e[:, 1] + e[:, 3]) / 2
    side = np.ceil(np.maximum(context * np.maximum(e[:, 2] - e[:, 0], e[:, 3] - e[:, 1]), min_px))
    return np.stack([np.round(cx - side / 2), np.round(cy - side / 2), side], axis=-1).astype(np.int64)


def cut_windows(image: np.ndarray, windows: np.ndarray, size: int) -> np.ndarray:
    """(N, size, size, 3) uint8: each (x0, y0, side) window of ``image`` resized to ``size`` px;
    the image's edge pixels repeat beyond it."""
    H, W = image.shape[:2]
    out = np.empty((len(windows), size, size, 3), np.uint8)
    for n, (x0, y0, side) in enumerate(np.asarray(windows, np.int64)):
        x1, y1 = x0 + side, y0 + side
        a = image[max(y0, 0):max(min(y1, H), 0), max(x0, 0):max(min(x1, W), 0)]
        if a.size == 0:            # wholly outside: the nearest edge pixel
            a = image[int(np.clip(y0, 0, H - 1)):int(np.clip(y0, 0, H - 1)) + 1,
                      int(np.clip(x0, 0, W - 1)):int(np.clip(x0, 0, W - 1)) + 1]
            a = np.broadcast_to(a, (side, side, 3))
        else:
            pads = (max(-y0, 0), max(y1 - H, 0), max(-x0, 0), max(x1 - W, 0))
            if any(pads):
                a = cv2.copyMakeBorder(np.ascontiguousarray(a), *pads, cv2.BORDER_REPLICATE)
        out[n] = cv2.resize(np.ascontiguousarray(a), (size, size),
                            interpolation=cv2.INTER_AREA if side > size else cv2.INTER_LINEAR)
    return out


def to_window(boxes: np.ndarray, windows: np.ndarray) -> np.ndarray:
    """(N, 4) renderer boxes (px) -> window units of their (N, 3) windows."""
    boxes, windows = np.asarray(boxes, float), np.asarray(windows, float)
    origin = np.concatenate([windows[:, :2], windows[:, :2]], axis=-1)
    return (boxes + 0.5 - origin) / windows[:, 2:3]


def from_window(boxes: np.ndarray, windows: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_window`."""
    boxes, windows = np.asarray(boxes, float), np.asarray(windows, float)
    origin = np.concatenate([windows[:, :2], windows[:, :2]], axis=-1)
    return boxes * windows[:, 2:3] + origin - 0.5


def mirror_window_boxes(boxes):
    """Window-unit boxes of the horizontally mirrored windows."""
    return boxes[..., [2, 1, 0, 3]] * np.array([-1.0, 1.0, -1.0, 1.0]) + np.array([1.0, 0.0, 1.0, 0.0])


def apply(model: RefineNet, params, windows_u8, prior, flip: bool = False):
    """Probabilities (N,) and boxes (N, 4) in window units of ``windows_u8`` (N, S, S, C)
    uint8 (C = 3, or 4 with the teammate mask) whose candidates are ``prior`` (N, 4) window
    units. ``flip``: also run on the mirrored windows and average the two passes'
    probabilities and boxes."""
    out = model.apply({"params": params}, normalise(windows_u8))
    p = jax.nn.sigmoid(out[:, 0])
    box = prior + out[:, 1:]
    if flip:
        m = model.apply({"params": params}, normalise(windows_u8[:, :, ::-1]))
        p = 0.5 * (p + jax.nn.sigmoid(m[:, 0]))
        box = 0.5 * (box + mirror_window_boxes(mirror_window_boxes(prior) + m[:, 1:]))
    return p, box


def apply_members(model: RefineNet, members, windows_u8, prior, flip: bool = False):
    """:func:`apply` of each network of ``members`` (a sequence of parameters), averaged."""
    outs = [apply(model, params, windows_u8, prior, flip=flip) for params in members]
    return sum(o[0] for o in outs) / len(outs), sum(o[1] for o in outs) / len(outs)


# --- labels and loss --------------------------------------------------------------------------


def sample_labels(candidates: np.ndarray, truth: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Labels of one frame's (N, 4) candidate boxes against its ground truth [(box, ignore)]:
    (N,) label 1 / 0, (N,) weight 1 / 0 (no label), (N, 4) target box (px; the candidate's own
    where there is none). See the module doc."""
    n = len(candidates)
    label, weight = np.zeros(n, np.float32), np.ones(n, np.float32)
    target = np.asarray(candidates, float).copy()
    for k, c in enumerate(candidates):
        for box, ignore in truth:
            o = iou(c, box)
            if ignore:
                if o > IGNORE_IOU:
                    weight[k] = 0.0
            elif o >= POS_IOU:
                label[k], target[k] = 1.0, box
            elif o > IGNORE_IOU:
                weight[k] = 0.0
    return label, weight, target


def loss_fn(params, model: RefineNet, windows_u8, prior, label, weight, target, box_weight: float,
            mask=None, mask_on=None, mask_weight: float = 0.0):
    """BCE of the target logit (where ``weight``) + ``box_weight`` x L1 of the edges (positives)
    [+ ``mask_weight`` x the visible-pixel head's BCE against ``mask`` ((N, S/2, S/2) shares of
    each cell that show the target), averaged over its cells and the windows where ``mask_on``]."""
    if mask is None:
        out = model.apply({"params": params}, normalise(windows_u8))
    else:
        out, mask_logit = model.apply({"params": params}, normalise(windows_u8), with_mask=True)
    logit = out[:, 0]
    bce = -(label * jax.nn.log_sigmoid(logit) + (1 - label) * jax.nn.log_sigmoid(-logit))
    cls = jnp.sum(weight * bce) / jnp.maximum(jnp.sum(weight), 1.0)
    pos = label * weight
    l1 = jnp.sum(pos[:, None] * jnp.abs(prior + out[:, 1:] - target)) / jnp.maximum(jnp.sum(pos), 1.0)
    parts = dict(cls=cls, box=l1)
    loss = cls + box_weight * l1
    if mask is not None:
        cell = -(mask * jax.nn.log_sigmoid(mask_logit) + (1 - mask) * jax.nn.log_sigmoid(-mask_logit))
        per_window = jnp.mean(cell, axis=(1, 2))
        parts["mask"] = jnp.sum(mask_on * per_window) / jnp.maximum(jnp.sum(mask_on), 1.0)
        loss = loss + mask_weight * parts["mask"]
    return loss, parts


def window_masks(mask, box, windows: np.ndarray, size: int) -> np.ndarray:
    """(N, size, size) float32: the share of each cell of every (x0, y0, side) window (resized
    to ``size``) that shows the target, whose visible pixels are ``mask`` ((h, w) bool over the
    renderer box ``box``, inside the image; None: no target)."""
    windows = np.asarray(windows, np.int64).reshape(-1, 3)
    out = np.zeros((len(windows), size, size), np.float32)
    if mask is None or not np.any(mask):
        return out
    u0, v0 = (int(round(x + 0.5)) for x in np.asarray(box)[:2])
    h, w = mask.shape
    for n, (x0, y0, side) in enumerate(windows):
        ya, yb, xa, xb = max(y0, v0), min(y0 + side, v0 + h), max(x0, u0), min(x0 + side, u0 + w)
        if yb <= ya or xb <= xa:
            continue
        canvas = np.zeros((side, side), np.float32)
        canvas[ya - y0:yb - y0, xa - x0:xb - x0] = mask[ya - v0:yb - v0, xa - u0:xb - u0]
        out[n] = cv2.resize(canvas, (size, size), interpolation=cv2.INTER_AREA if side > size else cv2.INTER_LINEAR)
    return out


# --- inference --------------------------------------------------------------------------------


SCORES = ("refined", "geometric")    # how a detection's score is made; see the module doc


@dataclass(frozen=True)
class RefineSettings:
    """The second stage's network and how it is applied (see the module doc)."""

    widths: tuple[int, ...] = (24, 32, 48, 64, 96)   # channels at strides 1, 2, 4, 8, 16 of the window
    hidden: int = 128                 # units of the dense layer
    size: int = 64                    # px, side of the resized window
    context: float = 2.5              # window side / the candidate's longer side
    min_window_px: float = 16.0       # px, smallest window side (in the image)
    candidate_min_score: float = 0.02     # first-stage candidates scoring below this are not looked at
    max_candidates: int = 16          # per image, best first
    flip_test: bool = True            # also look at the mirrored window and average
    score: str = "geometric"          # "refined": the second stage's probability; "geometric": sqrt(p1 * p2)
    members: int = 1                  # networks averaged (an ensemble of seeds); see the module doc

    def __post_init__(self):
        if self.score not in SCORES:
            raise ValueError(f"refine score {self.score!r}: one of {', '.join(SCORES)}")
        if self.members < 1:
            raise ValueError(f"refine members {self.members}: at least one network")

    def to_dict(self) -> dict:
        return dict(widths=list(self.widths), hidden=self.hidden, size=self.size, context=self.context,
                    min_window_px=self.min_window_px, candidate_min_score=self.candidate_min_score,
                    max_candidates=self.max_candidates, flip_test=self.flip_test, score=self.score,
                    members=self.members)

    @classmethod
    def from_dict(cls, d: dict) -> "RefineSettings":
        return cls(widths=tuple(int(w) for w in d["widths"]), hidden=int(d["hidden"]), size=int(d["size"]),
                   context=float(d["context"]), min_window_px=float(d["min_window_px"]),
                   candidate_min_score=float(d["candidate_min_score"]), max_candidates=int(d["max_candidates"]),
                   flip_test=bool(d["flip_test"]), score=str(d.get("score", "refined")),
                   members=int(d.get("members", 1)))


BUCKETS = (4, 8, 16)    # windows are refined in batches padded to the smallest of these that holds them,
                        # or to a multiple of the largest (few compiled shapes)


def padded_count(n: int) -> int:
    """The batch size ``n`` windows are padded to (:data:`BUCKETS`)."""
    for b in BUCKETS:
        if n <= b:
            return b
    return BUCKETS[-1] * -(-n // BUCKETS[-1])


class Refiner:
    """The second stage with its networks' parameters (``members``: a sequence of
    ``settings.members`` parameter trees): ``refine(images, candidates)``."""

    def __init__(self, members, settings: RefineSettings = RefineSettings()):
        if isinstance(members, Mapping) or len(members) != settings.members:
            got = "one parameter tree" if isinstance(members, Mapping) else f"{len(members)}"
            raise PerceptionError(f"the second stage has {settings.members} network(s) (settings.members), "
                                  f"got {got}: pass a list of parameter trees, one per network")
        self.members = tuple(members)
        self.settings = settings
        channels = {input_channels(m) for m in self.members}
        if len(channels) != 1 or not channels <= {3, 4}:
            raise PerceptionError(f"the second stage's networks take {sorted(channels)} input channels; expected "
                                  "3 (colours) or 4 (and the teammate mask), the same for every network")
        self.channels = channels.pop()
        self.model = RefineNet(widths=tuple(settings.widths), hidden=settings.hidden)
        self._apply = jax.jit(partial(apply_members, self.model, flip=settings.flip_test))

    def windows(self, boxes: np.ndarray) -> np.ndarray:
        s = self.settings
        return windows_of(boxes, s.context, s.min_window_px)

    @property
    def uses_teammates(self) -> bool:
        """Whether the networks see the teammate mask (a fourth input channel)."""
        return self.channels == 4

    def refine(self, images: list[np.ndarray], candidates: list[list], teammates: list | None = None) -> list[list]:
        """Per image, its candidates (Detections, best first) looked at again: Detections with
        the second stage's box and score (``settings.score``), best first, before suppression.
        ``teammates``: per image, (K, 4) px boxes where the team expects its UAVs (or None),
        for a second stage that sees them (:attr:`uses_teammates`; others ignore them)."""
        s = self.settings
        picked = [c[: s.max_candidates] for c in candidates]
        owner = [i for i, c in enumerate(picked) for _ in c]
        if not owner:
            return [[] for _ in images]
        boxes = np.array([d.box for c in picked for d in c], float)
        first = np.array([d.score for c in picked for d in c], float)
        windows = self.windows(boxes)
        owner = np.asarray(owner)                         # image of each candidate, in order
        cut = np.concatenate([cut_windows(images[i], windows[owner == i], s.size) for i in np.unique(owner)])
        if self.uses_teammates:
            masks = np.concatenate([teammate_masks(None if teammates is None else teammates[i], windows[owner == i],
                                                   s.size) for i in np.unique(owner)])
            cut = np.concatenate([cut, masks[..., None]], axis=-1)
        prior = to_window(boxes, windows)
        n = len(owner)
        pad = padded_count(n) - n
        if pad:
            cut = np.concatenate([cut, np.zeros((pad,) + cut.shape[1:], np.uint8)])
            prior = np.concatenate([prior, np.tile([[0.3, 0.3, 0.7, 0.7]], (pad, 1))])
        p, box = self._apply(self.members, cut, prior.astype(np.float32))
        p, box = np.asarray(p[:n], float), from_window(np.asarray(box[:n], float), windows)
        if s.score == "geometric":
            p = np.sqrt(p * first)
        out = [[] for _ in images]
        for k in range(n):
            b = box[k]
            if b[2] > b[0] and b[3] > b[1]:
                out[owner[k]].append(Detection(box=b, score=float(p[k])))
        return [sorted(d, key=lambda x: -x.score) for d in out]
