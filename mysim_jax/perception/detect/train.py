"""Training and evaluation of the learned detector, and the run's outputs.

:func:`run` does what ``scripts/train_detector.py`` does, in order:

1. renders (or reuses from ``OUT/cache``) three sets of frames: ``train`` (split TRAIN),
   ``eval_in`` (split TRAIN, other frames: in-distribution) and ``eval_held_out`` (split
   HELD_OUT), with ``data.workers`` processes, into ``.npy`` files read as memory maps;
2. trains :class:`~mysim_jax.perception.detect.model.CenterNet` with AdamW (linear warm-up,
   cosine decay) on square crops of the training frames (``train.crop`` px; with
   ``p_target_crop`` placed on the target, its centre at ``crop_centre_range`` of the crop,
   which may be beyond the crop's edge, so the crop cuts it as the image border would),
   augmented by a random rescale (``scale_range``), horizontal flips, a random gamma,
   contrast and saturation, brightness gain and offset, and per-channel (white balance) gains;
   the crops are cut in a background thread while the network trains;
3. evaluates the CNN and the classical baseline on both evaluation sets (precision, recall,
   mean IoU at ``eval.min_score``; AP@``iou_threshold``; frames per second, median of per-frame
   times) and writes ``OUT/detector.msgpack``, ``OUT/metrics.json``, ``OUT/pr_curve.png``,
   ``OUT/examples/*.png``, ``OUT/config.yaml``, and per target of each set the CNN's best
   box and whether it was found (``OUT/targets/SET.json``, :func:`target_rows`) with the
   missed ones drawn (``OUT/targets/misses_SET.png``, :func:`plot_misses`).

With ``weights`` given, step 2 is skipped and those weights are evaluated instead, with the
config's inference settings (``model.pyramid``, ``model.pyramid_band_px``, ``model.flip_test``,
``eval.min_score``).
"""

from __future__ import annotations

from dataclasses import replace
import hashlib
import json
import time
from itertools import zip_longest
import multiprocessing as mp
from pathlib import Path

import cv2
import jax
import numpy as np
import optax
from tqdm.auto import tqdm
import yaml
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mysim_jax.perception.camera import PerceptionError, intrinsics
from mysim_jax.perception.detect.classical import ColourBlobDetector
from mysim_jax.perception.detect.config import DetectorConfig
from mysim_jax.perception.detect.dataset import DatasetSpec, is_ignored, render_sample
from mysim_jax.perception.detect.metrics import iou, match, pr_curve, summary
from mysim_jax.perception.detect.model import CNNDetector, CenterNet, encode_targets, loss_fn
from mysim_jax.perception.detect.refine import RefineSettings, Refiner, normalise
from mysim_jax.perception.detect.refine_train import SamplePool, cached_candidates, train_refiner
from mysim_jax.perception.detect.steps import photometric, prefetch, run_steps, truths
from mysim_jax.perception.detect.team import (TEAM_ATTITUDE_SIGMA_RAD, TEAM_POSITION_SIGMA_M, frame_team,
                                              noisy_team_boxes)

SETS = {"train": "train", "eval_in": "train", "eval_held_out": "held_out"}
# frame indices of the in-distribution evaluation set start here (after any training frame)
EVAL_IN_OFFSET = 1_000_000


# --- data -------------------------------------------------------------------------------------


def spec_of(cfg: DetectorConfig, which: str) -> DatasetSpec:
    d = cfg.data
    n = d.train_images if which == "train" else d.eval_images
    seed = d.seed if which == "train" or d.eval_seed is None else d.eval_seed
    p_occluder = d.train_p_occluder if which == "train" and d.train_p_occluder is not None else d.p_occluder
    return DatasetSpec(split=SETS[which], n_images=n, seed=seed, width=d.width, height=d.height, p_empty=d.p_empty,
                       p_occluder=p_occluder, p_distractors=d.p_distractors, p_drone=d.p_drone,
                       p_onboard=d.p_onboard, p_random_palette=d.p_random_palette,
                       min_visible_px=d.min_visible_px, min_visible_fraction=d.min_visible_fraction)


# bumped when the labels of a rendered set change meaning, so older cached sets are not reused
LABELS_VERSION = 3


def _label(s) -> dict:
    return dict(box=None if s.box is None else [float(x) for x in s.box], ignore=s.ignore, kind=s.kind,
                distance=s.distance, visible_fraction=s.visible_fraction, visible_px=s.visible_px,
                truncation=s.truncation, meta=s.meta)


def _render_chunk(args):
    spec, path, first, indices = args
    images = None if path is None else np.load(path, mmap_mode="r+")
    labels, masks = [], []
    for i in indices:
        s = render_sample(spec, i + first)
        if images is not None:
            images[i] = s.image
        labels.append(_label(s))
        masks.append(s.mask)
    if images is not None:
        images.flush()
    return indices, labels, masks


def _save_masks(path: Path, masks: list) -> None:
    """``masks`` (per frame an (h, w) bool array or None) as one ``.npz``: shapes (-1: none)
    and every mask's bits in order."""
    shapes = np.array([(-1, -1) if m is None else m.shape for m in masks], np.int32)
    flat = np.concatenate([m.reshape(-1) for m in masks if m is not None] + [np.zeros(0, bool)])
    tmp = path.with_suffix(".part.npz")
    np.savez(tmp, shapes=shapes, bits=np.packbits(flat), n=np.int64(flat.size))
    tmp.rename(path)


def _read_masks(path: Path) -> list:
    with np.load(path) as z:
        shapes, flat = z["shapes"], np.unpackbits(z["bits"], count=int(z["n"])).astype(bool)
    out, k = [], 0
    for h, w in shapes:
        if h < 0:
            out.append(None)
            continue
        out.append(flat[k:k + h * w].reshape(h, w))
        k += h * w
    return out


def _render_all(spec: DatasetSpec, path: str | None, first: int, workers: int, desc: str, progress: bool):
    """Render every frame of ``spec`` (into the image file ``path`` unless None): labels and masks."""
    n = spec.n_images
    labels: list = [None] * n
    masks: list = [None] * n
    chunks = [list(range(k, min(k + 25, n))) for k in range(0, n, 25)]
    jobs = [(spec, path, first, c) for c in chunks]
    bar = tqdm(total=n, desc=desc, unit="frame", disable=not progress)

    def take(result):
        indices, labs, ms = result
        for i, lab, m in zip(indices, labs, ms):
            labels[i], masks[i] = lab, m
        bar.update(len(indices))

    if workers > 1:
        with mp.get_context("spawn").Pool(workers) as pool:
            for result in pool.imap_unordered(_render_chunk, jobs):
                take(result)
    else:
        for job in jobs:
            take(_render_chunk(job))
    bar.close()
    return labels, masks


def set_key(spec: DatasetSpec, first: int = 0) -> str:
    """The cache key of a rendered set (:func:`build_set`)."""
    return hashlib.sha1(repr((spec, first, LABELS_VERSION)).encode()).hexdigest()[:12]


def load_masks(spec: DatasetSpec, folder: Path, name: str, first: int = 0, workers: int = 1,
               progress: bool = True) -> list:
    """Per frame of the set :func:`build_set` renders, the target's visible pixels over its box
    (``Sample.mask``; None: no target in view), read from ``folder/NAME_KEY_masks.npz`` or, for a
    set rendered before the masks were kept, rendered again (the same frames) and written there."""
    path = Path(folder) / f"{name}_{set_key(spec, first)}_masks.npz"
    if path.is_file():
        return _read_masks(path)
    Path(folder).mkdir(parents=True, exist_ok=True)
    _, masks = _render_all(spec, None, first, workers, f"masks {name}", progress)
    _save_masks(path, masks)
    return masks


def build_set(spec: DatasetSpec, folder: Path, name: str, first: int = 0, workers: int = 1,
              progress: bool = True) -> tuple[np.ndarray, list[dict]]:
    """Render frames ``first .. first + n - 1`` of ``spec`` into ``folder/NAME.npy`` (uint8
    (n, H, W, 3)) and ``folder/NAME.json`` (labels), or read them if already there for the
    same spec. Returns the images (a read-only memory map) and the labels."""
    folder.mkdir(parents=True, exist_ok=True)
    key = set_key(spec, first)
    npy, js = folder / f"{name}_{key}.npy", folder / f"{name}_{key}.json"
    if npy.is_file() and js.is_file():
        return np.load(npy, mmap_mode="r"), json.loads(js.read_text())
    images = np.lib.format.open_memmap(npy.with_suffix(".part.npy"), mode="w+", dtype=np.uint8,
                                       shape=(spec.n_images, spec.height, spec.width, 3))
    del images
    labels, masks = _render_all(spec, str(npy.with_suffix(".part.npy")), first, workers, f"render {name}", progress)
    npy.with_suffix(".part.npy").rename(npy)
    js.write_text(json.dumps(labels))
    _save_masks(folder / f"{name}_{key}_masks.npz", masks)
    return np.load(npy, mmap_mode="r"), labels


# --- crops and augmentation -------------------------------------------------------------------


def make_crop(image: np.ndarray, label: dict, cfg: DetectorConfig, rng: np.random.Generator):
    """One augmented square training crop of a frame: (crop, crop, 3) uint8 and its
    [(box, ignore, weight)]: the weight of the box's heatmap positive is
    1 + ``train.hidden_weight`` * (the share of the target's silhouette the crop does not show:
    occluded, beyond the image border or the crop's edge)."""
    t = cfg.train
    C = t.crop
    H, W = image.shape[:2]
    s = cfg.model.input_width / W * float(np.exp(rng.uniform(np.log(t.scale_range[0]), np.log(t.scale_range[1]))))
    # no draw without aspect jitter, so recipes without it get the same crops as before it existed
    a = 1.0 if t.aspect_range[0] == t.aspect_range[1] == 1.0 else \
        float(np.exp(rng.uniform(np.log(t.aspect_range[0]), np.log(t.aspect_range[1]))))
    w, h = max(int(round(W * s)), C), max(int(round(H * s * a)), 1)
    sx, sy = w / W, h / H
    img = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA if sx < 1 else cv2.INTER_LINEAR)
    # pad right / bottom by repeating edges, as inference pads to multiples of 32
    ph = max(C - h, 0) + int(rng.integers(0, 33))
    img = cv2.copyMakeBorder(img, 0, ph, 0, 0, cv2.BORDER_REPLICATE)
    box = None if label["box"] is None else (np.asarray(label["box"]) + 0.5) * [sx, sy, sx, sy] - 0.5
    Hp = img.shape[0]
    if box is not None and rng.random() < t.p_target_crop:
        cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
        x0 = int(np.clip(cx - rng.uniform(*t.crop_centre_range) * C, 0, w - C))
        y0 = int(np.clip(cy - rng.uniform(*t.crop_centre_range) * C, 0, Hp - C))
    else:
        x0, y0 = int(rng.integers(0, w - C + 1)), int(rng.integers(0, Hp - C + 1))
    crop = np.ascontiguousarray(img[y0:y0 + C, x0:x0 + C])
    boxes = []
    if box is not None:
        b = box - [x0, y0, x0, y0]
        area = (b[2] - b[0]) * (b[3] - b[1])
        cb = np.clip(b, -0.5, C - 0.5)
        carea = max(cb[2] - cb[0], 0) * max(cb[3] - cb[1], 0)
        if carea > 0:
            # the share of the whole silhouette the crop shows, as the dataset counts targets
            # (the crop's edge cuts like the image border): too little is neither required nor false
            shown = label["visible_fraction"] * carea / area
            truncation = label.get("truncation", 0.0)
            cut = is_ignored(label["visible_px"], shown, truncation, cfg.data.min_visible_px,
                             cfg.data.min_visible_fraction)
            hidden = float(np.clip(1.0 - shown * (1.0 - truncation), 0.0, 1.0))
            boxes.append((cb, bool(label["ignore"]) or cut, 1.0 + t.hidden_weight * hidden))
    if t.hflip and rng.random() < 0.5:
        crop = crop[:, ::-1].copy()
        boxes = [(np.array([C - 1 - b[2], b[1], C - 1 - b[0], b[3]]), ig, wt) for b, ig, wt in boxes]
    return photometric(crop, t, rng), boxes


def batch_of(images, labels, idx, cfg: DetectorConfig, rng):
    crops, targets = [], []
    for i in idx:
        crop, boxes = make_crop(np.asarray(images[i]), labels[i], cfg, rng)
        crops.append(crop)
        targets.append(encode_targets(boxes, crop.shape[:2]))
    return np.stack(crops), {k: np.stack([t[k] for t in targets]) for k in targets[0]}


# --- training ---------------------------------------------------------------------------------


def make_trainer(cfg: DetectorConfig):
    """(model, optimiser, jitted step(params, opt_state, images, targets) -> (params, opt_state, loss, parts))."""
    t = cfg.train
    model = CenterNet(widths=tuple(cfg.model.widths))
    schedule = optax.warmup_cosine_decay_schedule(0.0, t.learning_rate, max(t.warmup_steps, 1), max(t.steps, 2),
                                                  end_value=0.02 * t.learning_rate)
    opt = optax.chain(optax.clip_by_global_norm(5.0), optax.adamw(schedule, weight_decay=t.weight_decay))

    @jax.jit
    def step(params, opt_state, images, targets):
        (loss, parts), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, model, images, targets, t.size_weight)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, parts

    return model, opt, step


def init_params(cfg: DetectorConfig, seed: int | None = None):
    model = CenterNet(widths=tuple(cfg.model.widths))
    C = cfg.train.crop
    key = jax.random.PRNGKey(cfg.train.seed if seed is None else seed)
    return model.init(key, normalise(np.zeros((1, C, C, 3), np.uint8)))["params"]


def init_from(cfg: DetectorConfig, path: str | Path):
    """The parameters of the weights file ``path`` to fine-tune from, checked against the
    config's network (:class:`~mysim_jax.perception.camera.PerceptionError` naming what is
    wrong: no such file, not a weights file, other ``model.widths``)."""
    start = CNNDetector.load(path)
    if tuple(start.widths) != tuple(cfg.model.widths):
        raise PerceptionError(f"{path}: its network has widths {list(start.widths)}, the config's model.widths "
                              f"are {list(cfg.model.widths)}")
    return start.params


def refine_init_from(cfg: DetectorConfig, path: str | Path) -> list | None:
    """With ``refine.fine_tune``, the second-stage networks of the weights file ``path`` to
    fine-tune from (one per ``refine.members``), checked against the config's second stage
    (:class:`~mysim_jax.perception.camera.PerceptionError` naming what is wrong); else None."""
    r = cfg.refine
    if r is None or not r.fine_tune:
        return None
    ref = CNNDetector.load(path).refiner
    if ref is None:
        raise PerceptionError(f"{path}: refine.fine_tune starts the second stage from this file's, but it has none "
                              f"(set refine.fine_tune: false to train it from a random init)")
    s = ref.settings
    mine = (tuple(r.widths), r.hidden, r.size, r.members)
    theirs = (tuple(s.widths), s.hidden, s.size, s.members)
    if mine != theirs:
        raise PerceptionError(f"{path}: its second stage (widths, hidden, size, members) is {theirs}, the config's "
                              f"refine section asks for {mine}")
    if ref.uses_teammates and not r.teammate_channel:
        raise PerceptionError(f"{path}: its second stage sees the teammate mask (4 input channels); set "
                              "refine.teammate_channel: true to fine-tune it")
    return list(ref.members)      # three channels with teammate_channel: widened to four (zero weights) in training


def train(cfg: DetectorConfig, images, labels, progress: bool = True, steps: int | None = None, log=None,
          params=None):
    """Train from scratch, or from ``params`` (fine-tuning); returns (params, loss history as a
    list of (step, loss))."""
    _, opt, step = make_trainer(cfg)
    params = init_params(cfg) if params is None else params
    rng = np.random.default_rng(cfg.train.seed)
    n = len(labels)
    steps = cfg.train.steps if steps is None else steps
    batches = prefetch(lambda: batch_of(images, labels, rng.integers(0, n, cfg.train.batch_size), cfg, rng), steps)
    return run_steps(step, params, opt.init(params), batches, steps, "train detector", "train.learning_rate",
                     ("focal",), progress=progress, log=log)


def refine_settings(cfg: DetectorConfig):
    """The second stage's settings of ``cfg.refine``."""
    r = cfg.refine
    return RefineSettings(widths=tuple(r.widths), hidden=r.hidden, size=r.size, context=r.context,
                          min_window_px=r.min_window_px, candidate_min_score=r.candidate_min_score,
                          max_candidates=r.max_candidates, flip_test=r.flip_test, score=r.score,
                          members=r.members)


def train_refine_stage(cfg: DetectorConfig, first_stage, images, labels, spec, cache: Path, progress: bool = True,
                       log=None, init_members: list | None = None):
    """Train the second stage on ``first_stage``'s candidates in the training frames (``spec``'s;
    the candidates are cached in ``cache``), from random inits or from ``init_members`` (one
    parameter tree per network). Returns (Refiner, loss history)."""
    weights_bytes = b"".join(np.asarray(a, np.float32).tobytes() for a in jax.tree.leaves(first_stage.params))
    candidates = cached_candidates(first_stage, weights_bytes, images, repr((spec, LABELS_VERSION)),
                                   cfg.refine.candidate_min_score, cache, progress=progress)
    masks = (load_masks(spec, cache, "train", workers=cfg.data.workers, progress=progress)
             if cfg.refine.mask_weight > 0 else None)
    pool = SamplePool(labels, candidates, masks)
    r = cfg.refine
    members, history = [], []
    for k in range(r.members):       # an ensemble: the same training from seeds seed, seed + 1, ...
        member_cfg = cfg.model_copy(update={"refine": r.model_copy(update={"seed": r.seed + k})})
        member_log = None if log is None else (lambda step, loss, parts, k=k: log(step, loss, dict(parts, member=k)))
        params, h = train_refiner(member_cfg, images, pool, progress=progress, log=member_log,
                                  params=None if init_members is None else init_members[k],
                                  desc="train refiner" + (f" {k + 1}/{r.members}" if r.members > 1 else ""))
        members.append(params)
        history += h
    return Refiner(members, refine_settings(cfg)), history


# --- evaluation -------------------------------------------------------------------------------


# Region-mode evaluation (:func:`region_hints`): the hint a tracker gives the detector, drawn
# around the truth with the errors of the tracker's prediction on the evading-drone tracking
# run (docs/detector.md, "Region mode: what gimbal tracking runs", gives them as fractions of
# the box's side). Per axis the centre is off by N(0, (HINT_CENTRE_REL * side +
# HINT_CENTRE_PX)^2) px (radial median ~0.07 side + 2 px, p95 ~0.15 side + 5 px); the side
# is the true one times exp(N(0, HINT_SIDE_LOG^2)). A frame without a counted target gets
# the hint at the pixel its target was drawn at (``meta["pixel"]``: an occluder drawn in
# front of the target is then inside the window), with a side drawn log-uniform in
# HINT_EMPTY_SIDE_PX.
HINT_CENTRE_REL, HINT_CENTRE_PX = 0.06, 2.0
HINT_SIDE_LOG = 0.1
HINT_EMPTY_SIDE_PX = (8.0, 120.0)


def region_hints(labels: list[dict], seed: int) -> list[tuple[np.ndarray, float]]:
    """Per frame ``(centre (2,) px, side px)``: where a tracker would expect the target (see
    the constants above); deterministic for ``seed``."""
    out = []
    for i, lab in enumerate(labels):
        rng = np.random.default_rng([seed, 7, i])
        if lab["box"] is not None:
            b = np.asarray(lab["box"], float)
            side = float(max(b[2] - b[0], b[3] - b[1]))
            centre = np.array([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2])
            centre = centre + rng.normal(0.0, HINT_CENTRE_REL * side + HINT_CENTRE_PX, 2)
            side *= float(np.exp(rng.normal(0.0, HINT_SIDE_LOG)))
        else:
            centre = np.asarray(lab["meta"]["pixel"], float)
            side = float(np.exp(rng.uniform(*np.log(HINT_EMPTY_SIDE_PX))))
        out.append((centre, max(side, 1.0)))
    return out


# Region mode told where the team's own UAVs are (:func:`teammate_hints`): each UAV drawn in
# a frame is expected where the team's estimates put it, with the VIO-like errors of
# :mod:`~mysim_jax.perception.detect.team` (TEAM_POSITION_SIGMA_M, TEAM_ATTITUDE_SIGMA_RAD).


def teammate_hints(labels: list[dict], seed: int, width: int, height: int) -> list[np.ndarray]:
    """Per frame (K, 4) px: the boxes where the team expects its UAVs drawn in the frame
    (``meta["uavs"]``; see the constants above); deterministic for ``seed``."""
    intr = intrinsics(width=width, height=height)
    out = []
    for i, lab in enumerate(labels):
        rng = np.random.default_rng([seed, 8, i])
        team = frame_team(lab)
        if team is None:
            raise PerceptionError("these frames' labels do not list the UAVs drawn (meta['uavs']): render them again")
        out.append(noisy_team_boxes(rng, intr, team, TEAM_POSITION_SIGMA_M, TEAM_ATTITUDE_SIGMA_RAD))
    return out


def evaluate(detector, images, labels, cfg: DetectorConfig, min_score: float, progress: bool = True,
             name: str = "", hints: list | None = None, teammates: list | None = None) -> tuple[dict, list, list[dict]]:
    """Metrics of ``detector`` on a set (detections down to score 0.01 for AP) and its speed:
    median over frames of one ``detect`` call, frames/s. With ``hints`` (per frame
    ``(centre, side)``, :func:`region_hints`) the detector runs in region mode
    (``detect_region``) instead of on the whole image, and with ``teammates`` (per frame
    (K, 4) px, :func:`teammate_hints`) it is told where the team's UAVs are. Returns the
    metrics, the detections per frame and the per-target rows (:func:`target_rows`)."""
    def run_one(i, img):
        if hints is None:
            return detector.detect(img, min_score=0.01)
        return detector.detect_region(img, hints[i][0], hints[i][1], min_score=0.01,
                                      **({} if teammates is None else {"teammates": teammates[i]}))

    dets, times = [], []
    run_one(0, np.asarray(images[0]))     # compile / warm up
    for i in tqdm(range(len(labels)), desc=f"evaluate {name}", unit="frame", disable=not progress, leave=False):
        img = np.asarray(images[i])
        t0 = time.perf_counter()
        d = run_one(i, img)
        times.append(time.perf_counter() - t0)
        dets.append(d)
    gts = truths(labels)
    out = summary(dets, gts, min_score, cfg.eval.iou_threshold)
    out["fps"] = float(1.0 / np.median(times))
    out["image_size"] = [int(images.shape[2]), int(images.shape[1])]
    # the same detections if targets however cut by the image border counted (see truths)
    cut = summary(dets, truths(labels, count_truncated=True, cfg=cfg), min_score, cfg.eval.iou_threshold)
    out["counting_truncated"] = dict(recall=cut["recall"], n_targets=cut["n_targets"], ap50=cut["ap50"])
    # per distance band and target kind: recall at the operating point
    rows = target_rows(dets, labels, min_score, cfg.eval.iou_threshold)
    out["recall_by"] = _recall_by(rows, labels)
    out["fps_mean"] = float(1.0 / np.mean(times))
    out["empty_frames"] = _empty_frames(dets, labels, min_score)
    return out, dets, rows


def _empty_frames(dets, labels, min_score: float) -> dict:
    """On frames without a target (none drawn): the share with no detection scoring >=
    ``min_score``, over all of them and over those showing UAVs (distractors, an occluder, an
    onboard view)."""
    empty = [i for i, lab in enumerate(labels) if lab["box"] is None]
    uavs = [i for i in empty if labels[i]["meta"]["scene"] != "none"]

    def clean(idx):
        return None if not idx else float(np.mean([not any(d.score >= min_score for d in dets[i]) for i in idx]))

    return {"frames": len(empty), "clean": clean(empty), "frames_with_uavs": len(uavs), "clean_with_uavs": clean(uavs)}


def _recall_by(rows: list[dict], labels: list[dict]) -> dict:
    """Recall of the per-target ``rows`` by kind, distance band, both, and scene."""
    groups: dict[str, list[bool]] = {}
    for r in rows:
        d = labels[r["frame"]]["distance"]
        band = "d<3" if d < 3 else "3<=d<10" if d < 10 else "10<=d<25" if d < 25 else "d>=25"
        for key in (r["kind"], band, f"{r['kind']}, {band}", f"scene={r['scene']}"):
            groups.setdefault(key, []).append(r["hit"])
    return {key: dict(recall=float(np.mean(hits)), n=len(hits)) for key, hits in sorted(groups.items())}


def target_rows(dets, labels, min_score: float, iou_threshold: float) -> list[dict]:
    """One row per counted target of a set (frames hold at most one): its frame, kind,
    distance (m), scene, visible fraction and box (px); the detection of any score that
    overlaps it most (``best_box``, ``best_iou``, ``best_score``; None, 0, 0 if none does);
    and ``hit``: a detection scoring >= ``min_score`` overlaps it at IoU >= ``iou_threshold``
    (a true positive of :func:`~mysim_jax.perception.detect.metrics.match`)."""
    rows = []
    for i, lab in enumerate(labels):
        if lab["box"] is None or lab["ignore"]:
            continue
        scored = [(iou(d.box, lab["box"]), d) for d in dets[i]]
        best_iou, best = max(scored, key=lambda x: x[0], default=(0.0, None))
        rows.append(dict(frame=i, kind=lab["kind"], distance=round(float(lab["distance"]), 3),
                         scene=lab["meta"]["scene"], visible_fraction=round(float(lab["visible_fraction"]), 3),
                         box=[round(float(x), 2) for x in lab["box"]],
                         best_box=None if best is None else [round(float(x), 2) for x in best.box],
                         best_iou=round(float(best_iou), 4), best_score=0.0 if best is None else round(best.score, 4),
                         hit=any(o >= iou_threshold and d.score >= min_score for o, d in scored)))
    return rows


def plot_misses(path: Path, images, rows: list[dict], n: int = 24, tile: int = 200) -> int:
    """A grid of the missed targets (rows with ``hit`` false, at most ``n``), each zoomed to
    ``tile`` px around its box: green the ground truth, red the detection overlapping it most,
    with frame, distance, scene, that detection's IoU and score. Returns how many are shown."""
    missed = [r for r in rows if not r["hit"]][:n]
    if not missed:
        return 0
    tiles = []
    for r in missed:
        img = np.ascontiguousarray(np.asarray(images[r["frame"]])[..., ::-1])
        H, W = img.shape[:2]
        g = np.asarray(r["box"])
        half = max(g[2] - g[0], g[3] - g[1]) * 1.2 + 6
        cx, cy = (g[0] + g[2]) / 2, (g[1] + g[3]) / 2
        x0, y0 = int(max(cx - half, 0)), int(max(cy - half, 0))
        x1, y1 = int(min(cx + half, W)), int(min(cy + half, H))
        z = (tile - 20) / max(x1 - x0, y1 - y0, 1)
        crop = cv2.resize(img[y0:y1, x0:x1], None, fx=z, fy=z, interpolation=cv2.INTER_NEAREST)

        def rect(b, colour):
            p0 = ((np.asarray(b[:2]) + 0.5 - [x0, y0]) * z).astype(int)
            p1 = ((np.asarray(b[2:]) + 0.5 - [x0, y0]) * z).astype(int) - 1
            cv2.rectangle(crop, tuple(int(v) for v in p0), tuple(int(v) for v in p1), colour, 1)

        rect(g, (0, 200, 0))
        if r["best_box"] is not None:
            rect(r["best_box"], (0, 0, 255))
        t = np.zeros((tile, tile, 3), np.uint8)
        t[:min(crop.shape[0], tile - 20), :min(crop.shape[1], tile)] = crop[:tile - 20, :tile]
        cv2.putText(t, f"#{r['frame']} {r['kind']} {r['distance']:.0f} m {r['scene']}", (2, tile - 11),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.33, (255, 255, 255), 1, cv2.LINE_AA)
        cv2.putText(t, f"IoU {r['best_iou']:.2f} score {r['best_score']:.2f}", (2, tile - 2),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.33, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(t)
    cols = min(6, len(tiles))
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % cols)
    grid = np.vstack([np.hstack(tiles[k:k + cols]) for k in range(0, len(tiles), cols)])
    cv2.imwrite(str(path), grid)
    return len(missed)


def write_examples(folder: Path, images, labels, results: dict, n: int) -> None:
    """Frames (spheres and drones in turn, and one without a target) with the ground truth
    (green) and each detector's best box and score (in the order of ``results``: red, blue,
    orange; BGR (0, 0, 255), (255, 80, 0), (0, 200, 255))."""
    folder.mkdir(parents=True, exist_ok=True)
    spheres = [i for i, lab in enumerate(labels) if lab["box"] is not None and lab["kind"] == "sphere"]
    drones = [i for i, lab in enumerate(labels) if lab["box"] is not None and lab["kind"] == "drone"]
    picks = [i for pair in zip_longest(spheres, drones) for i in pair if i is not None][: max(n - 1, 0)]
    picks += [i for i, lab in enumerate(labels) if lab["box"] is None][:1]
    for i in picks[:n]:
        img = np.ascontiguousarray(np.asarray(images[i])[..., ::-1])
        lab = labels[i]
        if lab["box"] is not None:
            b = np.round(lab["box"]).astype(int)
            cv2.rectangle(img, (b[0], b[1]), (b[2], b[3]), (0, 200, 0), 1)
        for colour, (name, dets) in zip(((0, 0, 255), (255, 80, 0), (0, 200, 255)), results.items()):
            for d in dets[i][:1]:
                if d.score < 0.3:
                    continue
                b = np.round(d.box).astype(int)
                cv2.rectangle(img, (b[0] - 2, b[1] - 2), (b[2] + 2, b[3] + 2), colour, 1)
                cv2.putText(img, f"{name} {d.score:.2f}", (max(b[0], 0), max(b[1] - 5, 10)),
                            cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1, cv2.LINE_AA)
        d = lab["distance"]
        cv2.putText(img, f"{lab['kind']} {d:.1f} m" if lab["box"] is not None else "no target", (5, 15),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        cv2.imwrite(str(folder / f"frame_{i:04d}.png"), img)


def plot_pr(path: Path, curves: dict) -> None:
    """Precision-recall curves: ``curves`` label -> (recall, precision)."""
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    for label, (r, p) in curves.items():
        ax.plot(r, p, label=label, ls="-" if "held" in label else "--")
    ax.set_xlabel("recall (IoU >= 0.5)")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1.01)
    ax.set_ylim(0, 1.01)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _evaluate_sets(cfg: DetectorConfig, cnn, sets: dict, out: Path, modes, metrics: dict, progress: bool) -> dict:
    """Evaluate the CNN (in each of ``modes``) and the colour-blob baseline on every set;
    the metrics go into ``metrics`` (``<detector>/<set>``), per-target rows, misses and
    examples into ``out``. Returns the precision-recall curves."""
    baseline = ColourBlobDetector()
    curves = {}
    for set_name, (images, labels) in sets.items():
        results = {}
        seed = spec_of(cfg, "eval_held_out").seed
        hints = region_hints(labels, seed) if {"region", "region_team", "region_team_hint"} & set(modes) else None
        team = (teammate_hints(labels, seed, cfg.data.width, cfg.data.height)
                if {"region_team", "region_team_hint"} & set(modes) else None)
        runs = [("cnn", cnn, cfg.eval.min_score, None, None)] if "full" in modes else []
        runs += [("cnn_region", cnn, cfg.eval.min_score, hints, None)] if "region" in modes else []
        runs += [("cnn_region_team", cnn, cfg.eval.min_score, hints, team)] if "region_team" in modes else []
        if "region_team_hint" in modes:
            hinted = replace(cnn, region=replace(cnn.region, hint_candidate=True))
            runs += [("cnn_region_team_hint", hinted, cfg.eval.min_score, hints, team)]
        for det_name, det, thr, h, tm in runs + [("baseline", baseline, 0.3, None, None)]:
            m, dets, rows = evaluate(det, images, labels, cfg, thr, progress=progress,
                                     name=f"{det_name} {set_name}", hints=h, teammates=tm)
            metrics[f"{det_name}/{set_name}"] = m
            results[det_name] = dets
            if det_name.startswith("cnn"):     # per-target diagnostics: which targets are missed, and how
                (out / "targets").mkdir(exist_ok=True)
                suffix = det_name[len("cnn"):]
                (out / "targets" / f"{set_name}{suffix}.json").write_text(json.dumps(rows))
                plot_misses(out / "targets" / f"misses_{set_name}{suffix}.png", images, rows)
            curves[f"{det_name}, {set_name.replace('_', '-')}"] = pr_curve(match(dets, truths(labels), cfg.eval.iou_threshold))
        if cfg.eval.n_examples:
            write_examples(out / "examples" / set_name, images, labels, results, cfg.eval.n_examples)
    return curves


def run(cfg: DetectorConfig, out: Path, progress: bool = True, cache: Path | None = None,
        weights: Path | None = None, init: Path | None = None, modes: tuple[str, ...] = ("full",)) -> dict:
    """Render, train, evaluate and write a run into ``out`` (see the module doc); returns the
    metrics. With ``weights`` (a detector.msgpack) nothing is trained: those weights are
    evaluated (and the training frames are not rendered). With ``init`` (a detector.msgpack of
    the same ``model.widths``) training starts from those weights instead of a random init.
    ``modes``: how the CNN is evaluated, ``"full"`` (the whole image, ``cnn/<set>``) and / or
    ``"region"`` (around a tracker's hint, :func:`region_hints` with the evaluation seed,
    ``cnn_region/<set>``) and ``"region_team"`` (the same, told where the team's UAVs are,
    :func:`teammate_hints`, ``cnn_region_team/<set>``) and ``"region_team_hint"`` (that, with
    the second stage also looking at the hint's box, ``RegionSettings.hint_candidate``,
    ``cnn_region_team_hint/<set>``)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False))
    cache = out / "cache" if cache is None else Path(cache)
    w = cfg.data.workers
    if weights is None:
        train_images, train_labels = build_set(spec_of(cfg, "train"), cache, "train", workers=w, progress=progress)
    sets = {"held_out": build_set(spec_of(cfg, "eval_held_out"), cache, "eval_held_out", workers=w, progress=progress),
            "in_distribution": build_set(spec_of(cfg, "eval_in"), cache, "eval_in", first=EVAL_IN_OFFSET, workers=w,
                                         progress=progress)}
    if weights is None:
        start = None if init is None else init_from(cfg, init)
        if start is None and cfg.train.steps == 0:
            raise ValueError("train.steps 0 trains no first stage: give the weights to start from (init)")
        log_lines = []
        t0 = time.time()
        params, history = start, []
        if cfg.train.steps > 0:
            params, history = train(cfg, train_images, train_labels, progress=progress, params=start,
                                    log=lambda k, loss, parts: log_lines.append(dict(step=k, loss=loss, **parts)))
        train_s = time.time() - t0
        cnn = CNNDetector(params=params, widths=tuple(cfg.model.widths), input_width=cfg.model.input_width,
                          min_score=cfg.eval.min_score, pyramid=tuple(cfg.model.pyramid),
                          pyramid_band_px=tuple(cfg.model.pyramid_band_px), flip_test=cfg.model.flip_test)
        metrics = dict(train_seconds=train_s, steps=cfg.train.steps, init=None if init is None else str(init),
                       final_loss=float(np.mean([l for _, l in history[-50:]])) if history else None)
        if cfg.refine is not None:
            t0 = time.time()
            cnn.refiner, refine_history = train_refine_stage(
                cfg, cnn, train_images, train_labels, spec_of(cfg, "train"), cache, progress=progress,
                log=lambda k, loss, parts: log_lines.append(dict(stage="refine", step=k, loss=loss, **parts)),
                init_members=None if init is None else refine_init_from(cfg, init))
            metrics.update(refine_seconds=time.time() - t0, refine_steps=cfg.refine.steps,
                           refine_final_loss=float(np.mean([l for _, l in refine_history[-50:]])))
        cnn.save(out / "detector.msgpack")
        (out / "train_log.json").write_text(json.dumps(log_lines))
        metrics["weights_bytes"] = (out / "detector.msgpack").stat().st_size
    else:
        cnn = CNNDetector.load(weights)
        refiner = cnn.refiner
        if refiner is not None and cfg.refine is not None:       # inference settings: the config's

            r = cfg.refine
            refiner = Refiner(refiner.members, replace(refiner.settings, candidate_min_score=r.candidate_min_score,
                                                      max_candidates=r.max_candidates, flip_test=r.flip_test, score=r.score))
        cnn = CNNDetector(params=cnn.params, widths=cnn.widths, input_width=cnn.input_width, top_k=cnn.top_k,
                          min_score=cfg.eval.min_score, pyramid=tuple(cfg.model.pyramid),
                          pyramid_band_px=tuple(cfg.model.pyramid_band_px),
                          flip_test=cfg.model.flip_test, refiner=refiner)   # inference settings: the config's
        metrics = dict(weights=str(weights), weights_bytes=Path(weights).stat().st_size,
                       refine=refiner is not None)
    curves = _evaluate_sets(cfg, cnn, sets, out, modes, metrics, progress)
    plot_pr(out / "pr_curve.png", curves)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics
