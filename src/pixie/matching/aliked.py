"""ALIKED extractor (kornia network, official Shiaoming/ALIKED weights)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from pixie.errors import ConfigError
from pixie.matching.base import Extractor, _image_tensor, _kornia_feature, _np
from pixie.matching.checkpoints import WeightsArg


ALIKED_MODELS = ("aliked-n16", "aliked-n16rot", "aliked-n32", "aliked-t16")


class AlikedExtractor(Extractor):
    """ALIKED (kornia's network) with the official Shiaoming/ALIKED weights.

    ``detection_threshold > 0`` keeps score-map maxima above it (at most ``max_keypoints``); ``<= 0`` keeps
    the ``max_keypoints`` strongest maxima. The mask multiplies the score map before detection.
    """

    dim = 128
    default_threshold = 0.2

    def __init__(self, device: torch.device, *, model: str = "aliked-n16", **kwargs: Any) -> None:
        if model not in ALIKED_MODELS:
            raise ConfigError(f"unknown ALIKED model {model!r}; choose one of {', '.join(ALIKED_MODELS)}")
        self.model = model
        super().__init__(device, **kwargs)

    def _build(self, weights: WeightsArg, allow_download: bool) -> None:
        net = _kornia_feature().ALIKED(model_name=self.model, max_num_keypoints=self.max_keypoints,
                                       detection_threshold=self.threshold)
        # dkd.hw_grid is a derived buffer the weight files do not carry
        self.net = self._load_net(net, self.model, weights, allow_download, ignore=("dkd.hw_grid",))
        self.dim = int(self.net.desc_head.sf_conv.out_channels)
        # channels-last on CPU: the convolutions and the per-pixel normalisation of the dense map run ~1.7x
        # faster on one thread (bench/RESULTS.md, session 13); keypoints and descriptors agree to rounding
        self._channels_last = torch.device(self.device).type == "cpu"
        if self._channels_last:
            self.net = self.net.to(memory_format=torch.channels_last)

    def _extract(self, rgb: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = _image_tensor(rgb, self.device)
        if self._channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        m = None if mask is None else torch.from_numpy(mask).to(self.device, torch.float32)[None, None]
        lafs, responses, descs = self.net.forward_laf(x, mask=m, compute_affine=False)
        kp = lafs[0, :, :, 2]
        return _np(kp), _np(descs[0]), _np(responses[0, :, 0])
