"""Detection metrics: IoU, matching at an IoU threshold, precision, recall, mean IoU and AP.

Ground truth per image is a list of ``(box, ignore)`` (renderer boxes, px). Matching
(:func:`match`) follows PASCAL VOC: an image's detections, best score first, each take the
not yet matched counted box they overlap most if that IoU is >= ``iou_threshold`` (a true
positive); a detection that instead reaches the threshold on an *ignored* box (a target too
small or hidden to count, see :mod:`mysim_jax.perception.detect.dataset`) is dropped, neither
true nor false; every other detection is a false positive (duplicates included).

AP (:func:`average_precision`) is the all-point interpolated area under the
precision-recall curve of all detections of all images ranked by score (VOC 2010+):
precision is made monotone (each point takes the highest precision at any larger recall)
and summed over the recall steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def iou(a, b) -> float:
    """Intersection over union of two boxes (u_min, v_min, u_max, v_max) (any units; 0 if both are empty)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    iw = min(a[2], b[2]) - max(a[0], b[0])
    ih = min(a[3], b[3]) - max(a[1], b[1])
    inter = max(iw, 0.0) * max(ih, 0.0)
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0


@dataclass(frozen=True)
class Matched:
    """Detections of all images after matching."""

    scores: np.ndarray        # (D,) scores of the detections kept (ignored ones dropped)
    tp: np.ndarray            # (D,) bool, true positive
    ious: np.ndarray          # (D,) IoU with the matched box (0 for false positives)
    n_gt: int                 # counted ground-truth boxes


def match(detections: list, truths: list, iou_threshold: float = 0.5) -> Matched:
    """Match per image. ``detections[i]``: list of (box, score) (or Detection) of image i;
    ``truths[i]``: list of (box, ignore) of image i."""
    if len(detections) != len(truths):
        raise ValueError(f"{len(detections)} images of detections but {len(truths)} of ground truth")
    scores, tp, ious = [], [], []
    n_gt = 0
    for dets, gts in zip(detections, truths):
        dets = [(np.asarray(d.box if hasattr(d, "box") else d[0], float),
                 float(d.score if hasattr(d, "score") else d[1])) for d in dets]
        dets.sort(key=lambda d: -d[1])
        counted = [np.asarray(b, float) for b, ign in gts if not ign]
        ignored = [np.asarray(b, float) for b, ign in gts if ign]
        n_gt += len(counted)
        taken = [False] * len(counted)
        for box, score in dets:
            best, best_k = 0.0, -1
            for k, g in enumerate(counted):
                o = iou(box, g)
                if not taken[k] and o > best:
                    best, best_k = o, k
            if best_k >= 0 and best >= iou_threshold:
                taken[best_k] = True
                scores.append(score), tp.append(True), ious.append(best)
            elif any(iou(box, g) >= iou_threshold for g in ignored):
                continue
            else:
                scores.append(score), tp.append(False), ious.append(0.0)
    return Matched(scores=np.asarray(scores, float), tp=np.asarray(tp, bool), ious=np.asarray(ious, float), n_gt=n_gt)


def pr_curve(m: Matched) -> tuple[np.ndarray, np.ndarray]:
    """Recall and precision (each (D,)) after each detection in descending score order."""
    order = np.argsort(-m.scores, kind="stable")
    tp = np.cumsum(m.tp[order])
    fp = np.cumsum(~m.tp[order])
    recall = tp / max(m.n_gt, 1)
    precision = tp / np.maximum(tp + fp, 1)
    return recall, precision


def average_precision(m: Matched) -> float:
    """All-point interpolated AP (area under the monotone precision-recall curve)."""
    if m.n_gt == 0:
        return float("nan")
    recall, precision = pr_curve(m)
    r = np.concatenate([[0.0], recall, [recall[-1] if recall.size else 0.0]])
    p = np.concatenate([[1.0], precision, [0.0]])
    p = np.maximum.accumulate(p[::-1])[::-1]
    return float(np.sum((r[1:] - r[:-1]) * p[1:]))


def summary(detections: list, truths: list, min_score: float, iou_threshold: float = 0.5) -> dict:
    """Precision, recall and mean IoU of matched boxes of the detections scoring >= ``min_score``,
    and AP over all detections given (pass low-threshold detections for a full curve)."""
    full = match(detections, truths, iou_threshold)
    keep = [[d for d in dets if (d.score if hasattr(d, "score") else d[1]) >= min_score] for dets in detections]
    op = match(keep, truths, iou_threshold)
    n_tp = int(op.tp.sum())
    return dict(precision=float(n_tp / len(op.tp)) if len(op.tp) else float("nan"),
                recall=float(n_tp / op.n_gt) if op.n_gt else float("nan"),
                mean_iou=float(op.ious[op.tp].mean()) if n_tp else float("nan"),
                ap50=average_precision(full), n_images=len(truths), n_targets=op.n_gt, true_positives=n_tp,
                false_positives=int((~op.tp).sum()), min_score=float(min_score), iou_threshold=float(iou_threshold))
