"""Target detection in camera images: a learned single-class detector (a small CenterNet-style
CNN in flax) and a classical OpenCV baseline, with one interface.

Interface (what trackers code against)::

    from mysim_jax.perception.detect import Detection, load_detector, ColourBlobDetector

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

This module imports NumPy only; JAX/flax load when a learned detector is built.
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


def load_detector(path: str | Path | None = None):
    """The learned detector with weights from ``path`` (default: the committed ones,
    :func:`default_weights_path`). Returns a :class:`~mysim_jax.perception.detect.model.CNNDetector`."""
    # imported here: the model imports JAX and flax, this module NumPy only (and the model
    # imports Detection from here)
    from mysim_jax.perception.detect.model import CNNDetector

    return CNNDetector.load(default_weights_path() if path is None else path)


def __getattr__(name):
    # the baseline imports OpenCV, the CNN imports JAX: both only when asked for (and both
    # import Detection from here)
    if name == "ColourBlobDetector":
        from mysim_jax.perception.detect.classical import ColourBlobDetector
        return ColourBlobDetector
    if name == "CNNDetector":
        from mysim_jax.perception.detect.model import CNNDetector
        return CNNDetector
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["Detection", "Detector", "load_detector", "default_weights_path", "ColourBlobDetector", "CNNDetector"]
