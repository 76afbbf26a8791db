"""Detectors of the target in a tracking camera's frames: the interface the gimbal trackers
use (``Frame -> list[Detection]``, best first), the learned detector adapted to frames
(:func:`image_detector`) or run where the tracker expects the target (:class:`RegionDetector`,
told by a :class:`RegionHint`), and the :class:`OracleDetector` stand-in built from the
renderer's ground-truth box. The hints themselves come from
:mod:`mysim_jax.perception.track_cues`.
"""

from __future__ import annotations

import inspect
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from mysim_jax.perception.camera import PerceptionError
from mysim_jax.perception.detect import Detection
from mysim_jax.perception.render_io import Frame


FrameDetector = Callable[[Frame], list]     # Frame -> detections, best first


def image_detector(detector) -> FrameDetector:
    """Adapt an image detector (``detector.detect(image (H, W, 3) uint8 RGB) -> list``) to frames."""
    if not hasattr(detector, "detect"):
        raise PerceptionError(f"a detector needs a detect(image) method; got {type(detector).__name__}")
    return lambda frame: detector.detect(frame.image)


@dataclass(frozen=True)
class RegionHint:
    """Where a camera's tracker expects the target in its next image."""

    centre: np.ndarray      # (2,) px, the expected box centre
    side: float             # px, the expected box's longer side
    teammates: np.ndarray | None = None   # (K, 4) px, where the team's own UAVs are expected (detect.team)


# the hint that the target is expected outside the image (behind the camera or beyond its
# border): a detector that takes hints does not look at all
OUT_OF_VIEW = RegionHint(centre=np.full(2, np.nan), side=0.0)


class RegionDetector:
    """A frame detector that looks where the tracker expects the target (region-of-interest
    mode) and at the whole image otherwise.

    Called as ``detector(frame, hint)``: with a :class:`RegionHint` it runs
    ``detector.detect_region(image, hint.centre, hint.side, region)`` (the learned
    detector's :meth:`~mysim_jax.perception.detect.model.CNNDetector.detect_region`; with
    the hint's ``teammates`` too, when it has them and ``detect_region`` takes them);
    without a hint, ``detector.detect(image)`` on the whole image; with :data:`OUT_OF_VIEW`
    nothing (the target is expected outside this image). With ``fallback_full``,
    a region that finds nothing is followed by the whole image in the same frame (off by
    default: the hint is where the target is expected, so a miss there is mostly a hidden
    target, and the tracker's recovery and the team's cue take over). :meth:`stats` gives
    the calls of each kind and the detection time per frame (wall clock of the detector
    alone, not the rendering)."""

    accepts_hints = True

    def __init__(self, detector, region=None, fallback_full: bool = False):
        if not (hasattr(detector, "detect") and hasattr(detector, "detect_region")):
            raise PerceptionError(f"region mode needs a detector with detect and detect_region; "
                                  f"got {type(detector).__name__}")
        self.detector, self.region, self.fallback_full = detector, region, fallback_full
        try:        # told where the teammates are only if it takes them (a detector of one's own may not)
            self.takes_teammates = "teammates" in inspect.signature(detector.detect_region).parameters
        except (TypeError, ValueError):
            self.takes_teammates = False
        self.seconds: list[float] = []
        self.kinds: list[str] = []          # "region", "region+full" (the fallback ran), "full"

    def __call__(self, frame: Frame, hint: RegionHint | None = None) -> list:
        if hint is OUT_OF_VIEW:
            self.seconds.append(0.0)
            self.kinds.append("skipped")
            return []
        t0 = time.perf_counter()
        kind = "full"
        if hint is not None:
            team = {"teammates": hint.teammates} if hint.teammates is not None and self.takes_teammates else {}
            found = self.detector.detect_region(frame.image, hint.centre, hint.side, self.region, **team)
            kind = "region"
            if not found and self.fallback_full:
                found, kind = self.detector.detect(frame.image), "region+full"
        else:
            found = self.detector.detect(frame.image)
        self.seconds.append(time.perf_counter() - t0)
        self.kinds.append(kind)
        return found

    def stats(self) -> dict:
        """Calls by kind and detection time (median ms, and frames/s from the mean time),
        over the frames the detector looked at, and per kind; ``skipped``: frames in which
        the target was expected outside the image (not looked at)."""
        sec, kinds = np.asarray(self.seconds), np.asarray(self.kinds)

        def summary(sel):
            t = sec[sel]
            return {"calls": int(t.size), "median_ms": float(1e3 * np.median(t)) if t.size else None,
                    "frames_per_s": float(1.0 / t.mean()) if t.size else None}

        out = {"all": summary(kinds != "skipped")}
        for kind in ("region", "region+full", "full"):
            out[kind] = summary(kinds == kind)
        out["skipped"] = int(np.sum(kinds == "skipped"))
        out["note"] = ("frames/s = 1 / mean detection time per camera frame looked at (the detector alone, one "
                       "image at a time); 'region+full': the region found nothing and the whole image was "
                       "searched; 'skipped': frames in which the target was expected outside the image")
        return out


class OracleDetector:
    """Stand-in detector from the renderer's ground truth: the visible target's box
    (``TargetView.box``) with Gaussian pixel noise on each edge, missed with probability
    ``miss_rate`` and whenever fewer than ``min_visible_px`` target pixels show.

    ``noise_px``: standard deviation of each box edge (px); ``seed``: the noise's seed.
    """

    def __init__(self, noise_px: float = 1.0, miss_rate: float = 0.0, min_visible_px: int = 4, seed: int = 0):
        if not noise_px >= 0:
            raise PerceptionError(f"noise_px must be >= 0, got {noise_px}")
        if not 0.0 <= miss_rate <= 1.0:
            raise PerceptionError(f"miss_rate must be in [0, 1], got {miss_rate}")
        self.noise_px = float(noise_px)
        self.miss_rate = float(miss_rate)
        self.min_visible_px = int(min_visible_px)
        self.rng = np.random.default_rng(seed)

    def __call__(self, frame: Frame) -> list[Detection]:
        tv = frame.target
        if tv is None:
            raise PerceptionError("the oracle detector needs a scene with a target (frame.target is None)")
        if tv.box is None or tv.visible_px < self.min_visible_px or self.rng.random() < self.miss_rate:
            return []
        box = tv.box + self.rng.normal(0.0, self.noise_px, 4)
        box = np.array([min(box[0], box[2]), min(box[1], box[3]), max(box[0], box[2]), max(box[1], box[3])])
        return [Detection(box=box, score=1.0)]


def box_centre(box) -> np.ndarray:
    """(2,) px centre of a box (u_min, v_min, u_max, v_max)."""
    b = np.asarray(box, float)
    return np.array([(b[0] + b[2]) / 2, (b[1] + b[3]) / 2])
