"""DISK extractor (kornia U-Net, official depth-save.pth weights)."""

from __future__ import annotations

import numpy as np
import torch.nn.functional as F

from pixie.matching.base import Extractor, _image_tensor, _kornia_feature, _no_features, _np, select_keypoints
from pixie.matching.checkpoints import WeightsArg, disk_state


class DiskExtractor(Extractor):
    """DISK (kornia's U-Net) with the official ``depth-save.pth`` weights; NMS window 5, logits above threshold."""

    dim = 128
    default_threshold = 0.0

    def _build(self, weights: WeightsArg, allow_download: bool) -> None:
        self.net = self._load_net(_kornia_feature().DISK(), "disk_depth", weights, allow_download, prepare=disk_state)

    def _extract(self, rgb: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = _image_tensor(rgb, self.device)
        h, w = x.shape[-2:]
        ph, pw = (-h) % 16, (-w) % 16
        x = F.pad(x, (0, pw, 0, ph), mode="replicate") if (ph or pw) else x
        heat, dense = self.net.heatmap_and_dense_descriptors(x)
        heat, dense = heat[0, 0, :h, :w], dense[0, :, :h, :w]
        xy, vals = select_keypoints(
            heat, radius=2, threshold=self.threshold, max_keypoints=self.max_keypoints,
            mask=self._mask_tensor(mask),
        )
        if len(xy) == 0:
            return _no_features(self.dim)
        desc = F.normalize(dense[:, xy[:, 1], xy[:, 0]].t(), dim=-1)
        return _np(xy), _np(desc), _np(vals)
