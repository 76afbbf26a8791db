"""Training of the detector's second stage (:mod:`~mysim_jax.perception.detect.refine`).

The second stage learns from what the first stage proposes: :func:`collect_candidates` runs
the trained first stage over training frames and keeps every candidate box scoring at least
``refine.candidate_min_score`` (a cached file per frames and weights, as the frames are).
Each training sample (:func:`make_sample`) is then one window:

* a candidate that is a positive (:func:`~mysim_jax.perception.detect.refine.sample_labels`),
  with probability ``p_positive``;
* the frame's counted target box moved and resized at random (``synthetic_jitter``: the
  standard deviation of the shift, in box sides, and of the log of each side's scale), with
  probability ``p_synthetic``, so the second stage also sees candidates the first stage
  placed worse than it usually does;
* otherwise a candidate that is not (a negative).

With ``p_occluded`` set, a positive or synthetic sample comes from a frame whose target is
behind the net or a UAV (the frame's ``meta.scene`` is ``net`` or ``uav``) with that
probability, and from any other frame otherwise: hidden targets, a small share of the frames
and the ones the first stage finds worst, are seen more often than they come.

Every chosen box is jittered a little more (``jitter``) and labelled again against the
frame's ground truth; the window is cut around it, at a random lower resolution with
probability ``p_low_res`` (as if the target were up to ``low_res_max`` times farther: the
window is cut at that many times fewer pixels and enlarged back), mirrored with probability
0.5, and given the first stage's photometric augmentation (``train.gamma``,
``steps.photometric``, ...).

With ``teammate_channel`` the window gets its fourth channel, the mask of where the team
expects its UAVs (:func:`~mysim_jax.perception.detect.refine.teammate_masks`), drawn for
each sample afresh from the frame's UAVs with the team's estimation errors
(:func:`~mysim_jax.perception.detect.team.noisy_team_boxes`), mirrored with the window and
left out of the photometric changes. A three-channel start (``refine.fine_tune`` from
weights without the channel) gets zero weights for it (:func:`~mysim_jax.perception.detect.refine.widen_input`).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import jax
import numpy as np
import optax
from tqdm.auto import tqdm

from mysim_jax.perception.detect.config import DetectorConfig
from mysim_jax.perception.detect.dataset import OCCLUDED_SCENES
from mysim_jax.perception.camera import PerceptionError, intrinsics
from mysim_jax.perception.detect.refine import (RefineNet, cut_windows, input_channels, loss_fn, mirror_window_boxes,
                                                sample_labels, teammate_masks, to_window, widen_input, window_masks,
                                                windows_of)
from mysim_jax.perception.detect.team import frame_team, noisy_team_boxes
from mysim_jax.perception.detect.steps import photometric, prefetch, run_steps, truths


def collect_candidates(detector, images, floor: float, progress: bool = True, name: str = "") -> list[list]:
    """Per frame, the first stage's candidates: [(box (4,) px, score)] scoring >= ``floor``, best first."""
    out = []
    for i in tqdm(range(len(images)), desc=f"candidates {name}", unit="frame", disable=not progress):
        dets = detector.detect(np.asarray(images[i]), min_score=floor)
        out.append([([float(x) for x in d.box], float(d.score)) for d in dets])
    return out


def cached_candidates(detector, weights_bytes: bytes, images, set_key: str, floor: float, folder: Path,
                      progress: bool = True, name: str = "train") -> list[list]:
    """:func:`collect_candidates`, read from ``folder`` if it holds them for these weights,
    frames (``set_key``) and floor, else computed and written there (``name``: of the frames,
    for the progress bar)."""
    key = hashlib.sha1(weights_bytes + repr((set_key, floor, detector.pyramid, detector.pyramid_band_px,
                                             detector.flip_test, detector.input_width)).encode()).hexdigest()[:12]
    path = Path(folder) / f"candidates_{key}.json"
    if path.is_file():
        return json.loads(path.read_text())
    cands = collect_candidates(detector, images, floor, progress=progress, name=name)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".part")
    tmp.write_text(json.dumps(cands))
    tmp.rename(path)
    return cands


def _jitter(box: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """``box`` (px) shifted by N(0, sigma) box sides and each side scaled by exp(N(0, sigma))."""
    e = np.asarray(box, float) + 0.5
    w, h = max(e[2] - e[0], 1.0), max(e[3] - e[1], 1.0)
    cx = (e[0] + e[2]) / 2 + rng.normal(0, sigma) * w
    cy = (e[1] + e[3]) / 2 + rng.normal(0, sigma) * h
    w, h = w * np.exp(rng.normal(0, sigma)), h * np.exp(rng.normal(0, sigma))
    return np.array([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2]) - 0.5


class SamplePool:
    """The training frames' candidates sorted into positives and negatives (unjittered)."""

    def __init__(self, labels: list[dict], candidates: list[list], masks: list | None = None):
        self.truths = truths(labels)
        self.labels = labels
        self.masks = masks          # per frame the target's visible pixels over its box (None: not kept)
        self.team = [frame_team(lab) for lab in labels]       # per frame: its UAVs and camera (None: not listed)
        self.positives, self.negatives = [], []
        for i, (cands, truth) in enumerate(zip(candidates, self.truths)):
            if not cands:
                continue
            lab, wt, _ = sample_labels(np.array([c[0] for c in cands], float), truth)
            for k in range(len(cands)):
                if wt[k] > 0:
                    (self.positives if lab[k] else self.negatives).append((i, k))
        self.counted = [i for i, t in enumerate(self.truths) if any(not ign for _, ign in t)]
        self.candidates = candidates
        hidden = {i for i, lab in enumerate(labels) if (lab.get("meta") or {}).get("scene") in OCCLUDED_SCENES}
        # positives and counted frames split by whether the target is behind something: (hidden, others)
        self.positives_by = ([s for s in self.positives if s[0] in hidden], [s for s in self.positives if s[0] not in hidden])
        self.counted_by = ([i for i in self.counted if i in hidden], [i for i in self.counted if i not in hidden])

    def __repr__(self) -> str:
        return (f"SamplePool({len(self.positives)} positives ({len(self.positives_by[0])} hidden), "
                f"{len(self.negatives)} negatives, {len(self.counted)} frames with a counted target "
                f"({len(self.counted_by[0])} hidden))")


def _pick(everything: list, by: tuple[list, list], p_hidden: float | None, rng: np.random.Generator):
    """One item of ``everything``, or with ``p_hidden`` set, of ``by[0]`` (hidden targets) with
    that probability and of ``by[1]`` otherwise (either one when the other is empty)."""
    group = everything
    if p_hidden is not None and by[0] and by[1]:
        group = by[0] if rng.random() < p_hidden else by[1]
    return group[rng.integers(len(group))]


def make_sample(images, pool: SamplePool, cfg: DetectorConfig, rng: np.random.Generator):
    """One training window: (S, S, 3) uint8, prior (4,) and target (4,) window units, label, weight."""
    r = cfg.refine
    u = rng.random()
    if u < r.p_synthetic and pool.counted:
        i = _pick(pool.counted, pool.counted_by, r.p_occluded, rng)
        box = next(np.asarray(b, float) for b, ign in pool.truths[i] if not ign)
        box = _jitter(box, r.synthetic_jitter, rng)
    else:
        if (u < r.p_synthetic + r.p_positive and pool.positives) or not pool.negatives:
            i, k = _pick(pool.positives, pool.positives_by, r.p_occluded, rng)
        else:
            i, k = pool.negatives[rng.integers(len(pool.negatives))]
        box = np.asarray(pool.candidates[i][k][0], float)
    box = _jitter(box, r.jitter, rng)
    label, weight, target = sample_labels(box[None], pool.truths[i])
    window = windows_of(box[None], r.context, r.min_window_px)
    image = np.asarray(images[i])
    side = int(window[0, 2])
    res = r.size
    if rng.random() < r.p_low_res:
        f = float(np.exp(rng.uniform(0.0, np.log(r.low_res_max))))
        res = int(np.clip(round(min(side, r.size) / f), 4, r.size))
    cut = cut_windows(image, window, res)[0]
    if res != r.size:
        cut = cv2.resize(cut, (r.size, r.size), interpolation=cv2.INTER_LINEAR)
    mask = None
    if r.teammate_channel:
        if pool.team[i] is None:
            raise PerceptionError("refine.teammate_channel: these training frames' labels do not list the UAVs drawn "
                                  "(meta['uavs']): render them again")
        intr = intrinsics(width=image.shape[1], height=image.shape[0])
        mask = teammate_masks(noisy_team_boxes(rng, intr, pool.team[i]), window, r.size)[0]
    prior, tgt = to_window(box[None], window)[0], to_window(target, window)[0]
    visible, visible_on = np.zeros((r.size // 2, r.size // 2), np.float32), 0.0
    if r.mask_weight > 0:
        if pool.masks is None:
            raise PerceptionError("refine.mask_weight: the training frames' visible-pixel masks were not loaded")
        lab = pool.labels[i]
        if not (lab["box"] is not None and lab["ignore"]):     # an ignored target's pixels: no mask label
            visible = window_masks(pool.masks[i], lab["box"], window, r.size // 2)[0]
            visible_on = float(weight[0] > 0)
    flip = rng.random() < 0.5
    if flip:
        cut = np.ascontiguousarray(cut[:, ::-1])
        mask = None if mask is None else np.ascontiguousarray(mask[:, ::-1])
        visible = np.ascontiguousarray(visible[:, ::-1])
        prior, tgt = mirror_window_boxes(prior), mirror_window_boxes(tgt)
    cut = photometric(cut, cfg.train, rng)
    if mask is not None:
        cut = np.concatenate([cut, mask[..., None]], axis=-1)
    return cut, prior, tgt, float(label[0]), float(weight[0]), visible, visible_on


def batch_of(images, pool: SamplePool, cfg: DetectorConfig, rng: np.random.Generator):
    samples = [make_sample(images, pool, cfg, rng) for _ in range(cfg.refine.batch_size)]
    cut, prior, target, label, weight, visible, visible_on = zip(*samples)
    return (np.stack(cut), np.array(prior, np.float32), np.array(target, np.float32), np.array(label, np.float32),
            np.array(weight, np.float32), np.stack(visible), np.array(visible_on, np.float32))


def train_refiner(cfg: DetectorConfig, images, pool: SamplePool, progress: bool = True, log=None, params=None,
                  desc: str = "train refiner"):
    """Train the second stage from scratch (or from ``params``, widened to the teammate
    channel when the config has it and they do not); returns (params, [(step, loss)])."""
    r = cfg.refine
    model = RefineNet(widths=tuple(r.widths), hidden=r.hidden)
    channels = 4 if r.teammate_channel else 3
    with_mask = r.mask_weight > 0
    fresh = model.init(jax.random.PRNGKey(r.seed), np.zeros((1, r.size, r.size, channels), np.float32),
                       with_mask=with_mask)["params"]
    if params is None:
        params = fresh
    else:
        if input_channels(params) != channels:
            params = widen_input(params, channels)
        if with_mask:      # a start without the visible-pixel head: the head from a random init
            params = {**{k: v for k, v in fresh.items() if k.startswith("mask")}, **params}
    warmup = max(min(r.warmup_steps, r.steps - 1), 1)
    schedule = optax.warmup_cosine_decay_schedule(0.0, r.learning_rate, warmup, max(r.steps, warmup + 1),
                                                  end_value=0.02 * r.learning_rate)
    opt = optax.chain(optax.clip_by_global_norm(5.0), optax.adamw(schedule, weight_decay=r.weight_decay))
    opt_state = opt.init(params)

    @jax.jit
    def step(params, opt_state, cut, prior, target, label, weight, visible, visible_on):
        (loss, parts), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            params, model, cut, prior, label, weight, target, r.box_weight,
            mask=visible if with_mask else None, mask_on=visible_on, mask_weight=r.mask_weight)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, parts

    rng = np.random.default_rng(r.seed)
    batches = prefetch(lambda: batch_of(images, pool, cfg, rng), r.steps)
    return run_steps(step, params, opt_state, batches, r.steps, desc, "refine.learning_rate",
                     ("cls", "box") + (("mask",) if with_mask else ()), progress=progress, log=log)
