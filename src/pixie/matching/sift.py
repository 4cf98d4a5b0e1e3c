"""OpenCV SIFT extractor with RootSIFT descriptors (no weights)."""

from __future__ import annotations

import cv2
import numpy as np

from pixie.matching.base import Extractor, _no_features
from pixie.matching.checkpoints import WeightsArg


class SiftExtractor(Extractor):
    """OpenCV SIFT with RootSIFT descriptors (L1-normalise, square root: unit L2 norm)."""

    dim = 128
    default_threshold = 0.04  # OpenCV's contrastThreshold

    def _build(self, weights: WeightsArg, allow_download: bool) -> None:  # no weights
        self.sift = cv2.SIFT_create(nfeatures=self.max_keypoints, contrastThreshold=self.threshold)

    def _extract(self, rgb: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        cv_mask = None if mask is None else mask.astype(np.uint8) * 255
        kps, desc = self.sift.detectAndCompute(grey, cv_mask)
        if not kps or desc is None:
            return _no_features(self.dim)
        kp = np.array([k.pt for k in kps], dtype=np.float32)
        resp = np.array([k.response for k in kps], dtype=np.float32)
        order = np.argsort(-resp, kind="stable")[: self.max_keypoints]
        d = desc[order].astype(np.float32)
        d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-12)
        return kp[order], np.sqrt(d), resp[order]
