"""XFeat extractor (kornia backbone, official verlab weights)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from pixie.matching.base import Extractor, _image_tensor, _kornia_feature, _no_features, _np, _sample, select_keypoints
from pixie.matching.checkpoints import WeightsArg


def _xfeat_grid(pos: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """XFeat's sampling grid: ``2 p / (size - 1) - 1`` (used with ``align_corners=False``, as trained)."""
    scale = torch.tensor([w - 1, h - 1], device=pos.device, dtype=torch.float32)
    return (2.0 * pos.float() / scale - 1.0)[None, :, None, :]


class XFeatExtractor(Extractor):
    """XFeat (kornia's backbone) with the official verlab weights; sparse keypoints like ``detectAndCompute``.

    The image is resized to multiples of 32; keypoints are maxima (5x5) of the keypoint heatmap above
    ``detection_threshold`` (default 0.05), ranked by heatmap x reliability; descriptors are 64-D.
    """

    dim = 64
    default_threshold = 0.05

    def _build(self, weights: WeightsArg, allow_download: bool) -> None:
        self.net = self._load_net(_kornia_feature().XFeatModel(), "xfeat", weights, allow_download)

    def _extract(self, rgb: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = _image_tensor(rgb, self.device)
        h, w = x.shape[-2:]
        h32, w32 = max(32, h // 32 * 32), max(32, w // 32 * 32)
        if (h32, w32) != (h, w):
            x = F.interpolate(x, (h32, w32), mode="bilinear", align_corners=False)
        feats, logits, reliability = self.net(x)
        heat = F.pixel_shuffle(torch.softmax(logits, 1)[:, :64], 8)[0, 0]
        m = self._mask_tensor(mask)
        if m is not None and (h32, w32) != (h, w):
            m = F.interpolate(m[None, None].float(), (h32, w32), mode="nearest")[0, 0] > 0.5
        xy, heat_vals = select_keypoints(heat, radius=2, threshold=self.threshold, max_keypoints=None,
                                         border=2, mask=m)
        if len(xy) == 0:
            return _no_features(self.dim)
        grid = _xfeat_grid(xy, h32, w32)
        scores = heat_vals * _sample(reliability, grid, "bilinear", False)[:, 0]
        order = torch.argsort(scores, descending=True, stable=True)[: self.max_keypoints]
        order = order[scores[order] > 0]
        xy, scores, grid = xy[order], scores[order], grid[:, order]
        desc = F.normalize(_sample(F.normalize(feats, dim=1), grid, "bicubic", False), dim=-1)
        kp = xy.float() * torch.tensor([w / w32, h / h32], device=xy.device)
        return _np(kp), _np(desc), _np(scores)
