"""LightGlue (kornia's network) with the cvg / XFeat / MINIMA weights, and its assigner."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from pixie.features import Features, Matches
from pixie.matching.base import RefBank, _kornia_feature, _np
from pixie.matching.checkpoints import load_strict, remap_lightglue_state


LIGHTGLUE_CONFIGS: dict[str, dict[str, Any]] = {
    "aliked": {"input_dim": 128},
    "disk": {"input_dim": 128},
    "superpoint": {"input_dim": 256},
    "xfeat": {
        "input_dim": 64,
        "descriptor_dim": 96,
        "n_layers": 6,
        "num_heads": 1,
        "depth_confidence": -1,
        "width_confidence": 0.95,
    },
}


def build_lightglue(
    kind: str,
    state: Mapping[str, Any] | None,
    device: torch.device,
    **overrides: Any,
) -> nn.Module:
    """kornia's LightGlue in configuration ``kind`` (see :data:`LIGHTGLUE_CONFIGS`) with ``state`` loaded.

    Nothing is downloaded: the network is built with ``features=None``. ``state=None`` keeps random weights.

    Raises
    ------
    WeightsError
        If the state dict does not fit the network.
    """
    KF = _kornia_feature()
    conf = {**LIGHTGLUE_CONFIGS[kind], **{k: v for k, v in overrides.items() if v is not None}}
    model = KF.LightGlue(features=None, **conf)
    if state is not None:
        load_strict(model, remap_lightglue_state(state), f"{kind} LightGlue", ignore=("confidence_thresholds",))
    return model.eval().to(device)


class LightGlueAssigner:
    """kornia LightGlue run pair by pair (on CPU pairs do not batch: point pruning sizes differ)."""

    def __init__(self, model: nn.Module, device: torch.device) -> None:
        self.model = model
        self.device = device

    def _side(self, f: Features) -> dict[str, torch.Tensor]:
        h, w = f.image_size
        return {
            "keypoints": torch.from_numpy(f.keypoints).to(self.device)[None],
            "descriptors": torch.from_numpy(f.descriptors).to(self.device)[None],
            "image_size": torch.tensor([[w, h]], device=self.device, dtype=torch.float32),
        }

    def match_many(self, q: Features, refs: Sequence[Features] | RefBank) -> list[Matches]:
        feats = refs.features if isinstance(refs, RefBank) else list(refs)
        out: list[Matches] = []
        if len(q) == 0:
            return [Matches.empty() for _ in feats]
        side_q = self._side(q)
        with torch.inference_mode():
            for r in feats:
                if len(r) == 0:
                    out.append(Matches.empty())
                    continue
                res = self.model({"image0": side_q, "image1": self._side(r)})
                pairs, scores = res["matches"][0], res["scores"][0]
                out.append(Matches(_np(pairs[:, 0]).astype(np.int64), _np(pairs[:, 1]).astype(np.int64),
                                   _np(scores)))
        return out
