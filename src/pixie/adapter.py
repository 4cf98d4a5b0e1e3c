"""Descriptor adapters: small learned maps applied to a frozen extractor's descriptors.

``aliked-ft-nn`` (see :mod:`pixie.matching`) is ALIKED-n16 whose descriptors go through the
:class:`DescriptorAdapter` shipped in ``pixie/data/weights/aliked_n16_geoadapter.pt``, trained on synthetic
photo <-> geometry-render pairs of procedural parts (:mod:`pixie.train.finetune`; model card next to the
weights). The same adapter is applied to query photos and to reference renders.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pixie.errors import WeightsError

DEFAULT_ADAPTER = "aliked_n16_geoadapter"


class DescriptorAdapter(nn.Module):
    """Residual MLP on L2-normalised descriptors, ``normalize(d + mlp(d))``; the identity at initialisation."""

    def __init__(self, dim: int = 128, hidden: int = 256, layers: int = 2):
        super().__init__()
        self.dim, self.hidden, self.layers = int(dim), int(hidden), int(layers)
        mods: list[nn.Module] = []
        d = dim
        for _ in range(layers - 1):
            mods += [nn.Linear(d, hidden), nn.GELU()]
            d = hidden
        last = nn.Linear(d, dim)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        mods.append(last)
        self.mlp = nn.Sequential(*mods)

    def forward(self, d: torch.Tensor) -> torch.Tensor:
        return F.normalize(d + self.mlp(d), dim=-1)

    def config(self) -> dict:
        return {"dim": self.dim, "hidden": self.hidden, "layers": self.layers}

    @torch.inference_mode()
    def apply_np(self, desc: np.ndarray) -> np.ndarray:
        """Adapt ``(N, D)`` float descriptors (numpy in, numpy float32 out)."""
        if len(desc) == 0:
            return np.asarray(desc, np.float32)
        dev = next(self.parameters()).device
        return self(torch.from_numpy(np.asarray(desc, np.float32)).to(dev)).float().cpu().numpy()


def shipped_adapter_path(name: str = DEFAULT_ADAPTER) -> Path:
    """``pixie/data/weights/<name>.pt`` inside the installed package."""
    return Path(__file__).resolve().parent / "data" / "weights" / f"{name}.pt"


def load_adapter(path: str | Path | None = None, device: torch.device | str = "cpu") -> DescriptorAdapter:
    """Load an adapter file (default: the one shipped in the package).

    Raises
    ------
    WeightsError
        If the file is missing or does not hold an adapter.
    """
    path = Path(path) if path is not None else shipped_adapter_path()
    if not path.is_file():
        raise WeightsError(f"descriptor adapter not found: {path}")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
        model = DescriptorAdapter(**ck["config"])
        model.load_state_dict(ck["state_dict"])
    except Exception as exc:  # noqa: BLE001 - torch raises many types for a bad file
        raise WeightsError(f"{path} is not a pixie descriptor adapter: {type(exc).__name__}: {exc}") from exc
    return model.eval().to(device)


class AdaptedExtractor:
    """Wraps a pixie extractor: same keypoints, descriptors passed through an adapter.

    Behaves like :class:`pixie.matching.Extractor` (``__call__(image, mask) -> Features``, ``dim``, ``device``).
    """

    def __init__(self, inner, adapter: DescriptorAdapter):
        self.inner = inner
        self.adapter = adapter.to(inner.device).eval()
        self.device = inner.device
        self.dim = adapter.dim

    def __call__(self, image: np.ndarray, mask: np.ndarray | None = None):
        f = self.inner(image, mask)
        f.descriptors = self.adapter.apply_np(f.descriptors)
        return f
