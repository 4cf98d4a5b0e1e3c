"""Descriptor adapters: small learned maps applied to a frozen extractor's descriptors.

``aliked-ft-nn`` (see :mod:`pixie.matching.registry`) is ALIKED-n16 whose descriptors go through the
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
from pixie.features import Features
from pixie.geometry.rotations import check_image, check_mask, in_mask
from pixie.matching.aliked import AlikedExtractor

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
    return Path(__file__).resolve().parents[1] / "data" / "weights" / f"{name}.pt"


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


def grid_points(mask: np.ndarray, stride: int, avoid: np.ndarray | None = None, min_dist: float = 2.0) -> np.ndarray:
    """(N, 2) float32 pixel centres of a regular ``stride`` grid inside ``mask`` (none within ``min_dist`` of ``avoid``)."""
    h, w = mask.shape
    off = stride // 2
    ys, xs = np.mgrid[off:h:stride, off:w:stride]
    keep = mask[ys, xs]
    pts = np.stack([xs[keep], ys[keep]], 1).astype(np.float32)
    if avoid is not None and len(avoid) and len(pts):
        d = np.abs(pts[:, None, :] - np.asarray(avoid, np.float32)[None]).max(-1).min(1)
        pts = pts[d >= min_dist]
    return pts


@torch.inference_mode()
def aliked_extract(net, rgb: np.ndarray, mask: np.ndarray | None = None, grid: int = 0,
                   extra_xy: np.ndarray | None = None):
    """ALIKED detections (like kornia's ``forward_laf`` with the mask on the score map), plus, for a masked
    image and ``grid > 0``, a regular grid of keypoints inside the mask, all described from one backbone pass.

    Returns ``(keypoints (N, 2), descriptors (N, D), scores (N,), extra descriptors at extra_xy or None)``;
    with ``extra_xy="describer"`` the last item is a function ``xy -> descriptors`` on the same feature map.
    Grid keypoints follow the detections; their score is the score map's value there.
    """
    h, w = rgb.shape[:2]
    dev = next(net.parameters()).device
    x = torch.from_numpy(np.ascontiguousarray(rgb)).to(dev).permute(2, 0, 1)[None].float().div_(255.0)
    fmap, smap = net.extract_dense_map(x)
    if mask is not None:
        smap = smap * torch.from_numpy(mask).to(dev).float()[None, None]
    kps, scores, _ = net.dkd(smap)
    wh = torch.tensor([w - 1, h - 1], dtype=torch.float32, device=dev)
    kp = (wh * (kps[0] + 1) / 2).float().cpu().numpy()
    sc = scores[0].float().cpu().numpy()
    if mask is not None:  # drop detections off the mask (nearest pixel), as pixie's extractors do
        on = in_mask(kp, mask)
        kp, sc = kp[on], sc[on]
        if grid and grid > 0:
            g = grid_points(mask, int(grid), avoid=kp)
            gs = smap[0, 0, g[:, 1].astype(int), g[:, 0].astype(int)].float().cpu().numpy() if len(g) else np.zeros(0)
            kp = np.concatenate([kp, g]).astype(np.float32)
            sc = np.concatenate([sc, gs]).astype(np.float32)

    @torch.inference_mode()
    def describe(xy):
        if len(xy) == 0:
            return np.zeros((0, fmap.shape[1]), np.float32)
        t = torch.from_numpy(np.asarray(xy, np.float32)).to(dev).reshape(-1, 2)
        t = torch.stack([t[:, 0].clamp(0, w - 1), t[:, 1].clamp(0, h - 1)], 1)
        return net.desc_head(fmap, [t / wh * 2 - 1])[0][0].float().cpu().numpy()

    if isinstance(extra_xy, str) and extra_xy == "describer":
        return kp, describe(kp), sc, describe
    return kp, describe(kp), sc, (None if extra_xy is None else describe(extra_xy))


class GridAlikedExtractor:
    """ALIKED-n16 (+ optional reference grid, see :func:`aliked_extract`) + optional adapter; a pixie extractor.

    Defaults: ``detection_threshold=0`` (the ``max_keypoints`` strongest maxima; measured best on LM-O) and
    no grid. With ``grid > 0`` reference images, always extracted with their mask, get extra keypoints on a
    regular grid inside the mask (it helped the 0.2-threshold detector, not the top-k one).
    """

    def __init__(self, device: torch.device, *, max_keypoints: int = 1024, detection_threshold: float | None = 0.0,
                 grid: int = 0, adapter: DescriptorAdapter | None = None, weights=None, allow_download: bool = False,
                 model: str = "aliked-n16"):
        self._base = AlikedExtractor(device, model=model, max_keypoints=max_keypoints,
                                     detection_threshold=detection_threshold, weights=weights,
                                     allow_download=allow_download)
        self.net = self._base.net
        self.device = device
        self.grid = int(grid or 0)
        self.adapter = None if adapter is None else adapter.to(device).eval()
        self.dim = self._base.dim if adapter is None else adapter.dim

    def __call__(self, image: np.ndarray, mask: np.ndarray | None = None):
        rgb = check_image(image)
        h, w = rgb.shape[:2]
        m = check_mask(mask, (h, w))
        if m is not None and not m.any():
            return Features.empty(self.dim, (h, w))
        kp, desc, sc, _ = aliked_extract(self.net, rgb, m, self.grid)
        if self.adapter is not None:
            desc = self.adapter.apply_np(desc)
        return Features(kp, desc, sc, (h, w))
