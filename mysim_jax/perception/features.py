"""Visual front end: corners tracked from image to image with pyramidal KLT.

Per grayscale image (``FeatureTracker.track``):

1. **Track** the previous image's features into this one with pyramidal Lucas-Kanade
   (``cv2.calcOpticalFlowPyrLK``), seeded by a predicted position when the caller gives
   one (e.g. the previous position moved by the rotation the gyro measured).
2. **Forward-backward check**: track the result back into the previous image; a feature
   whose round trip misses its start by more than ``forward_backward_px`` is dropped, as
   is one that left the image (less than ``border_px`` from an edge).
3. **Outlier rejection**: RANSAC on the essential matrix between the previous and this
   image (``cv2.findEssentialMat`` on calibrated coordinates, threshold ``ransac_px``).
   When the features barely moved (median flow under ``min_flow_for_ransac_px``) the
   epipolar geometry is undetermined and every tracked feature is kept. Views of a plane
   (the ground alone) fit a family of essential matrices, so a wrong match that happens
   to lie near one of them can pass; the back end's robust loss and reprojection check
   catch those.
4. **Replenish**: new Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) at least
   ``min_distance`` pixels from every surviving feature, up to ``max_features``, each
   with a new track id.

Tracks are identified by an integer id that never repeats: a feature lost once is never
found again under the same id. Pixels follow :mod:`mysim_jax.perception.camera`: u right,
v down, the top-left pixel's centre at (0, 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mysim_jax.perception.camera import Intrinsics, PerceptionError


@dataclass(frozen=True)
class FeatureTrackerConfig:
    """Settings of the KLT front end (pixels of the tracked image)."""

    max_features: int = 200              # features kept per image
    min_distance: float = 15.0           # px, between features (new corners keep this from old ones)
    quality_level: float = 0.01          # Shi-Tomasi threshold, fraction of the image's strongest corner
    block_size: int = 7                  # px, corner-detection neighbourhood
    window: int = 21                     # px, side of the KLT window
    pyramid_levels: int = 3              # KLT pyramid levels above the full image
    forward_backward_px: float = 0.5     # px, largest round-trip miss of a kept feature
    ransac_px: float = 1.0               # px, largest distance to an epipolar line of an inlier
    ransac_confidence: float = 0.999
    min_flow_for_ransac_px: float = 1.0  # px, median flow below which RANSAC is skipped
    border_px: int = 8                   # px, features closer to an edge are dropped

    def __post_init__(self):
        checks = {"max_features": self.max_features >= 8, "min_distance": self.min_distance > 0,
                  "quality_level": 0 < self.quality_level < 1, "block_size": self.block_size >= 3,
                  "window": self.window >= 5 and self.window % 2 == 1, "pyramid_levels": self.pyramid_levels >= 0,
                  "forward_backward_px": self.forward_backward_px > 0, "ransac_px": self.ransac_px > 0,
                  "ransac_confidence": 0 < self.ransac_confidence < 1, "border_px": self.border_px >= 0}
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise PerceptionError(f"FeatureTrackerConfig: invalid {', '.join(bad)} (max_features >= 8, window odd >= 5, "
                                  f"thresholds positive, confidence in (0, 1))")


@dataclass(frozen=True)
class FrameFeatures:
    """The features of one image after tracking, checking and replenishing."""

    ids: np.ndarray        # (n,) int64 track ids
    uv: np.ndarray         # (n, 2) float64 px
    n_tracked: int         # features that survived KLT, the forward-backward check and the border
    n_inliers: int         # of those, the RANSAC inliers (= n_tracked when RANSAC was skipped)
    n_new: int             # corners added to this image


class FeatureTracker:
    """Tracks corners through a sequence of grayscale images of one camera (see the module doc)."""

    def __init__(self, intr: Intrinsics, config: FeatureTrackerConfig = FeatureTrackerConfig()):
        self.intr = intr
        self.config = config
        self._prev: np.ndarray | None = None
        self._ids = np.zeros(0, dtype=np.int64)
        self._uv = np.zeros((0, 2), dtype=np.float32)
        self._next_id = 0
        c = config
        self._lk = dict(winSize=(c.window, c.window), maxLevel=c.pyramid_levels,
                        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))

    def _inside(self, uv: np.ndarray) -> np.ndarray:
        b = self.config.border_px
        return ((uv[:, 0] >= b) & (uv[:, 0] <= self.intr.width - 1 - b)
                & (uv[:, 1] >= b) & (uv[:, 1] <= self.intr.height - 1 - b))

    def track(self, image: np.ndarray, predicted: np.ndarray | None = None) -> FrameFeatures:
        """Track the features into ``image`` ((H, W) uint8) and return this image's features.

        ``predicted``: (n, 2) px, a guess of where the current features (``self.uv``, same
        order) are in ``image``; None starts KLT at their previous positions.
        """
        if image.ndim != 2 or image.dtype != np.uint8 or image.shape != (self.intr.height, self.intr.width):
            raise PerceptionError(f"FeatureTracker.track: expected a ({self.intr.height}, {self.intr.width}) uint8 "
                                  f"grayscale image, got {image.shape} {image.dtype}")
        c = self.config
        ids, uv = self._ids, self._uv
        n_tracked = n_inliers = 0
        if self._prev is not None and len(ids):
            guess = uv.copy() if predicted is None else np.asarray(predicted, dtype=np.float32).reshape(-1, 2)
            nxt, ok, _ = cv2.calcOpticalFlowPyrLK(self._prev, image, uv, guess.copy(),
                                                  flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._lk)
            back, ok_b, _ = cv2.calcOpticalFlowPyrLK(image, self._prev, nxt, uv.copy(),
                                                     flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._lk)
            keep = (ok.ravel() == 1) & (ok_b.ravel() == 1)
            keep &= np.linalg.norm(back - uv, axis=1) <= c.forward_backward_px
            keep &= self._inside(nxt)
            ids, prev_uv, uv = ids[keep], self._uv[keep], nxt[keep]
            n_tracked = len(ids)
            inl = self._epipolar_inliers(prev_uv, uv)
            ids, uv = ids[inl], uv[inl]
            n_inliers = len(ids)
        new_uv = self._detect(image, uv)
        new_ids = np.arange(self._next_id, self._next_id + len(new_uv), dtype=np.int64)
        self._next_id += len(new_uv)
        self._ids = np.concatenate([ids, new_ids])
        self._uv = np.concatenate([uv, new_uv]).astype(np.float32)
        self._prev = image
        return FrameFeatures(ids=self._ids.copy(), uv=self._uv.astype(np.float64), n_tracked=n_tracked,
                             n_inliers=n_inliers, n_new=len(new_ids))

    @property
    def uv(self) -> np.ndarray:
        """(n, 2) px, the current features (in the order of the last ``track`` result)."""
        return self._uv.astype(np.float64)

    def _epipolar_inliers(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(n,) bool: RANSAC inliers of the essential matrix between pixels ``a`` and ``b``."""
        c = self.config
        n = len(a)
        if n < 8 or np.median(np.linalg.norm(b - a, axis=1)) < c.min_flow_for_ransac_px:
            return np.ones(n, dtype=bool)
        K = self.intr.K
        E, mask = cv2.findEssentialMat(a.astype(np.float64), b.astype(np.float64), K, method=cv2.RANSAC,
                                       prob=c.ransac_confidence, threshold=c.ransac_px)
        if E is None or mask is None:
            return np.ones(n, dtype=bool)
        return mask.ravel().astype(bool)

    def _detect(self, image: np.ndarray, existing: np.ndarray) -> np.ndarray:
        """(m, 2) float32 px: new corners away from ``existing`` features and the border."""
        c = self.config
        room = c.max_features - len(existing)
        if room <= 0:
            return np.zeros((0, 2), dtype=np.float32)
        mask = np.zeros(image.shape, dtype=np.uint8)
        b = c.border_px
        mask[b:image.shape[0] - b, b:image.shape[1] - b] = 255
        r = int(np.ceil(c.min_distance))
        for u, v in np.round(existing).astype(int):
            cv2.circle(mask, (int(u), int(v)), r, 0, -1)
        corners = cv2.goodFeaturesToTrack(image, maxCorners=room, qualityLevel=c.quality_level,
                                          minDistance=c.min_distance, mask=mask, blockSize=c.block_size)
        if corners is None:
            return np.zeros((0, 2), dtype=np.float32)
        corners = corners.reshape(-1, 2)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)
        cv2.cornerSubPix(image, corners, (5, 5), (-1, -1), crit)
        return corners[self._inside(corners)].astype(np.float32)


def relative_rotation(intr: Intrinsics, uv_a: np.ndarray, uv_b: np.ndarray,
                      ransac_px: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotation and unit translation of camera b relative to camera a from matched pixels.

    Returns ``R_ab`` (3, 3), ``t_ab`` (3,) (unit length) with ``X_b = R_ab X_a + t_ab``
    in the OpenCV camera frames, and the (n,) bool inlier mask of the essential matrix
    (RANSAC, then ``cv2.recoverPose``).
    """
    uv_a = np.asarray(uv_a, dtype=np.float64)
    uv_b = np.asarray(uv_b, dtype=np.float64)
    if len(uv_a) < 5 or uv_a.shape != uv_b.shape:
        raise PerceptionError(f"relative_rotation: need at least 5 matched pixels in two equal (n, 2) arrays, "
                              f"got {uv_a.shape} and {uv_b.shape}")
    E, mask = cv2.findEssentialMat(uv_a, uv_b, intr.K, method=cv2.RANSAC, prob=0.999, threshold=ransac_px)
    if E is None:
        raise PerceptionError("relative_rotation: no essential matrix fits the matches")
    E = E[:3]
    _, R, t, mask_pose = cv2.recoverPose(E, uv_a, uv_b, intr.K, mask=mask.copy())
    return R, t.ravel() / max(np.linalg.norm(t), 1e-12), mask_pose.ravel() > 0
