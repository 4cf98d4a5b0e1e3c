"""SuperPoint: the network (magicleap parameter names) and its extractor (MINIMA / LightGlue settings)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pixie.matching.base import Extractor, _grey_tensor, _no_features, _np, _sample, select_keypoints
from pixie.matching.checkpoints import WeightsArg, superpoint_state


class SuperPointNet(nn.Module):
    """The SuperPoint network (DeTone et al. 2018), parameter names as in magicleap's ``superpoint_v1.pth``.

    Input ``(B, 1, H, W)`` grey in ``[0, 1]`` with ``H, W`` multiples of 8. Output: 65-channel detector logits
    and L2-normalised 256-D descriptors, both at 1/8 resolution.
    """

    def __init__(self) -> None:
        super().__init__()
        chans = [(1, 64), (64, 64), (64, 64), (64, 64), (64, 128), (128, 128), (128, 128), (128, 128)]
        names = ["conv1a", "conv1b", "conv2a", "conv2b", "conv3a", "conv3b", "conv4a", "conv4b"]
        for name, (cin, cout) in zip(names, chans):
            setattr(self, name, nn.Conv2d(cin, cout, 3, padding=1))
        self.convPa = nn.Conv2d(128, 256, 3, padding=1)
        self.convPb = nn.Conv2d(256, 65, 1)
        self.convDa = nn.Conv2d(128, 256, 3, padding=1)
        self.convDb = nn.Conv2d(256, 256, 1)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        for block in ("1", "2", "3", "4"):
            x = F.relu(getattr(self, f"conv{block}a")(x))
            x = F.relu(getattr(self, f"conv{block}b")(x))
            if block != "4":
                x = F.max_pool2d(x, 2, 2)
        logits = self.convPb(F.relu(self.convPa(x)))
        desc = F.normalize(self.convDb(F.relu(self.convDa(x))), dim=1)
        return logits, desc


def _superpoint_grid(xy: torch.Tensor, hc: int, wc: int, cell: int = 8) -> torch.Tensor:
    """Descriptor sampling grid of the SuperPoint used to train (MINIMA-)LightGlue (cvg convention).

    Pixel ``p`` maps to ``2 (p - cell/2 + 0.5) / (size*cell - cell/2 - 0.5) - 1``, used with
    ``align_corners=True``.
    """
    denom = torch.tensor([wc * cell - cell / 2 - 0.5, hc * cell - cell / 2 - 0.5], device=xy.device)
    return (2.0 * (xy.float() - cell / 2 + 0.5) / denom - 1.0)[None, :, None, :]


class SuperPointExtractor(Extractor):
    """SuperPoint: NMS radius 4, border 4, detection threshold 0.0005 (the MINIMA / LightGlue settings)."""

    dim = 256
    default_threshold = 0.0005

    def __init__(self, device: torch.device, *, nms_radius: int = 4, border: int = 4, **kwargs: Any) -> None:
        self.nms_radius, self.border = int(nms_radius), int(border)
        super().__init__(device, **kwargs)

    def _build(self, weights: WeightsArg, allow_download: bool) -> None:
        self.net = self._load_net(SuperPointNet(), "superpoint", weights, allow_download, prepare=superpoint_state)

    def _extract(self, rgb: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = _grey_tensor(rgb, self.device)
        h, w = x.shape[-2:]
        ph, pw = (-h) % 8, (-w) % 8
        x = F.pad(x, (0, pw, 0, ph), mode="replicate") if (ph or pw) else x
        logits, dense = self.net(x)
        score = F.pixel_shuffle(torch.softmax(logits, 1)[:, :64], 8)[0, 0, :h, :w]
        xy, vals = select_keypoints(score, radius=self.nms_radius, threshold=self.threshold,
                                    max_keypoints=self.max_keypoints, border=self.border,
                                    mask=self._mask_tensor(mask))
        if len(xy) == 0:
            return _no_features(self.dim)
        hc, wc = dense.shape[-2:]
        desc = F.normalize(_sample(dense, _superpoint_grid(xy, hc, wc), "bilinear", True), dim=-1)
        return _np(xy), _np(desc), _np(vals)
