"""The classical baseline: an orange colour threshold, then connected blobs (OpenCV).

What a robotics user tries first for a target of a known colour: both capture targets show
the target orange (:data:`mysim_jax.perception.render_models.TARGET`; the sphere all over, the
evading drone on its front arms). The image is converted to HSV, pixels of orange hue
(OpenCV hue ``hue`` range, i.e. 10-42 deg, which leaves out the UAVs' red front arms and the
yellow tethers) with enough saturation and value are kept, closed with a small ellipse (so a
drone's two front arms merge into one blob), and every connected component (8-connected)
of at least ``min_area_px`` pixels gives a box. Its score grows with the blob's area and mean
saturation: ``(1 - exp(-area / 30)) * mean_saturation``.

Limits (by design, not bugs): it finds only the orange parts, so a drone's box covers its
front arms and not its dark hull and rear arms; lighting that shifts the hue (a warm evening
sky) or darkens the target below ``min_value`` loses it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mysim_jax.perception.detect import Detection
from mysim_jax.perception.detect.model import check_image


@dataclass(frozen=True)
class ColourBlobDetector:
    """Orange blobs (see the module doc). Kernel and area sizes are for a 640 px wide image and
    scale with the image width."""

    hue: tuple[int, int] = (5, 21)        # OpenCV hue (0-180) range of the target orange
    min_saturation: int = 110             # 0-255
    min_value: int = 40                   # 0-255
    close_px: int = 5                     # closing kernel (640 px image)
    min_area_px: float = 3.0              # smallest blob (640 px image)
    min_score: float = 0.0
    max_detections: int = 10

    def detect(self, image: np.ndarray, min_score: float | None = None) -> list[Detection]:
        """Detections in ``image`` ((H, W, 3) uint8 RGB, any size), best first."""
        image = check_image(image)
        H, W = image.shape[:2]
        scale = W / 640.0
        hsv = cv2.cvtColor(image, cv2.COLOR_RGB2HSV)
        mask = cv2.inRange(hsv, (self.hue[0], self.min_saturation, self.min_value), (self.hue[1], 255, 255))
        k = max(int(round(self.close_px * scale)) | 1, 1)
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        floor = self.min_score if min_score is None else min_score
        dets = []
        for i in range(1, n):
            x, y, w, h, area = stats[i]
            a = area / scale ** 2
            if a < self.min_area_px:
                continue
            sat = float(hsv[..., 1][labels == i].mean()) / 255.0
            score = float((1.0 - np.exp(-a / 30.0)) * sat)
            if score >= floor:
                dets.append(Detection(box=np.array([x - 0.5, y - 0.5, x + w - 0.5, y + h - 0.5]), score=score))
        dets.sort(key=lambda d: -d.score)
        return dets[: self.max_detections]
