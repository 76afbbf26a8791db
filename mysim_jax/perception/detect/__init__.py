"""Target detection in camera images: a learned single-class detector (a small CenterNet-style
CNN in flax) and a classical OpenCV baseline, with one interface.

Interface (what trackers code against)::

    from mysim_jax.perception.detect.classical import ColourBlobDetector
    from mysim_jax.perception.detect.model import load_detector

    detector = load_detector()               # the committed trained CNN (docs/detector/)
    dets = detector.detect(image)            # image: (H, W, 3) uint8 RGB, any size
    best = dets[0] if dets else None         # best first
    best.box                                 # (4,) px (u_min, v_min, u_max, v_max)
    best.score                               # in [0, 1]

Boxes follow the renderer's convention (:mod:`mysim_jax.perception.render`): pixel
coordinates of the input image, the centre of the top-left pixel at (0, 0), and a box
encloses whole pixels (``u_min`` is the left edge of its leftmost pixel). A detector
resizes internally, so it works at any image size; its boxes are always in the pixels of
the image passed in.

This module (the interface) imports NumPy only; the learned detector's module
(``detect.model``) imports JAX and flax, the baseline's (``detect.classical``) OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class Detection:
    """One detected target."""

    box: np.ndarray     # (4,) float px (u_min, v_min, u_max, v_max) in the input image
    score: float        # confidence in [0, 1]; higher is more confident


@runtime_checkable
class Detector(Protocol):
    """Anything with ``detect(image) -> list[Detection]`` (best first)."""

    def detect(self, image: np.ndarray) -> list[Detection]:
        """Detections in ``image`` ((H, W, 3) uint8 RGB, any size), best first."""
        ...


def default_weights_path() -> Path:
    """The committed trained weights: ``docs/detector/detector.msgpack`` in the repository."""
    return Path(__file__).resolve().parents[3] / "docs" / "detector" / "detector.msgpack"
