"""The extractor base class and what every extractor shares.

:class:`Extractor` turns one checked RGB image (+ optional mask) into :class:`pixie.features.Features`;
:func:`select_keypoints` picks keypoints on dense score maps (SuperPoint, XFeat, DISK); :class:`RefBank`
stacks many reference features for batched matching.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
import sys
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pixie.features import Features
from pixie.geometry.rotations import check_image, check_mask, in_mask
from pixie.matching.checkpoints import WeightsArg, load_strict, load_weights
from pixie.threads import imports_without_gc

_FAR = 1.0e6  # keypoint coordinate of padding entries: outside every window


def _image_tensor(rgb: np.ndarray, device: torch.device) -> torch.Tensor:
    """``uint8 HxWx3`` -> float ``(1, 3, H, W)`` in ``[0, 1]``."""
    return torch.from_numpy(rgb).to(device).permute(2, 0, 1)[None].float().div_(255.0)


def _grey_tensor(rgb: np.ndarray, device: torch.device) -> torch.Tensor:
    """``uint8 HxWx3`` -> float ``(1, 1, H, W)`` luminance (ITU-R BT.601 weights) in ``[0, 1]``."""
    x = _image_tensor(rgb, device)
    w = torch.tensor([0.299, 0.587, 0.114], device=device).view(1, 3, 1, 1)
    return (x * w).sum(1, keepdim=True)


# --------------------------------------------------------------------------------------------------------------
# Keypoint selection on score maps (shared by the SuperPoint, XFeat and DISK extractors)
# --------------------------------------------------------------------------------------------------------------


def local_maxima(score: torch.Tensor, radius: int) -> torch.Tensor:
    """Boolean map of the positions equal to the maximum of their ``(2r+1)^2`` window; ``score`` is ``(H, W)``."""
    k = 2 * radius + 1
    pooled = F.max_pool2d(score[None, None], kernel_size=k, stride=1, padding=radius)[0, 0]
    return score == pooled


def select_keypoints(
    score: torch.Tensor,
    *,
    radius: int,
    threshold: float,
    max_keypoints: int | None,
    border: int = 0,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pick keypoints on a dense score map.

    Parameters
    ----------
    score
        ``(H, W)`` score map.
    radius
        Non-maximum suppression radius (window ``2r+1``).
    threshold
        A keypoint's score must be strictly above it.
    max_keypoints
        Keep the strongest ones; ``None`` or ``<= 0`` keeps all.
    border
        Pixels at the image border that hold no keypoint.
    mask
        ``(H, W)`` boolean; only positions inside are candidates. Masked pixels are set to the lowest
        value first, so they neither become keypoints nor suppress keypoints inside the mask.

    Returns
    -------
    xy, values
        ``(N, 2)`` int64 ``(x, y)`` and ``(N,)`` scores, strongest first.
    """
    if mask is not None:
        floor = torch.finfo(score.dtype).min
        score = score.masked_fill(~mask, floor)
    keep = local_maxima(score, radius) & (score > threshold)
    if mask is not None:
        keep &= mask
    if border > 0:
        keep[:border] = False
        keep[-border:] = False
        keep[:, :border] = False
        keep[:, -border:] = False
    yx = keep.nonzero()
    values = score[yx[:, 0], yx[:, 1]]
    order = torch.argsort(values, descending=True, stable=True)
    if max_keypoints is not None and max_keypoints > 0:
        order = order[:max_keypoints]
    return yx[order].flip(1), values[order]


# --------------------------------------------------------------------------------------------------------------
# Extractors
# --------------------------------------------------------------------------------------------------------------


class Extractor:
    """Base class: turns one checked RGB image (+ optional mask) into :class:`Features`.

    Subclasses set :attr:`dim` and :attr:`default_threshold`, build their network in :meth:`_build` and
    implement :meth:`_extract`.

    Parameters
    ----------
    device : torch.device
    max_keypoints : int
        At most this many keypoints per image.
    detection_threshold : float, optional
        Detector threshold in the backend's own units; ``None``: :attr:`default_threshold`.
    weights : WeightsArg
        Explicit weight location (see :func:`weights_for`); else the search of :func:`pixie.weights.resolve_weights`.
    allow_download : bool
        Whether a missing weight file may be fetched from its official URL.
    """

    dim: int = 0
    default_threshold: float = 0.0

    def __init__(
        self,
        device: torch.device,
        *,
        max_keypoints: int = 1024,
        detection_threshold: float | None = None,
        weights: WeightsArg = None,
        allow_download: bool = False,
    ) -> None:
        self.device = device
        self.max_keypoints = int(max_keypoints)
        self.threshold = self.default_threshold if detection_threshold is None else float(detection_threshold)
        self._build(weights, allow_download)

    def _build(self, weights: WeightsArg, allow_download: bool) -> None:
        """Create the network (``self.net``) or detector; called once by ``__init__``."""
        raise NotImplementedError

    def __call__(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        rgb = check_image(image)
        h, w = rgb.shape[:2]
        m = check_mask(mask, (h, w))
        if m is not None and not m.any():
            return Features.empty(self.dim, (h, w))
        with torch.inference_mode():
            kp, desc, scores = self._extract(rgb, m)
        keep = in_mask(kp, m)
        return Features(kp[keep], desc[keep], scores[keep], (h, w))

    def _extract(self, rgb: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _mask_tensor(self, mask: np.ndarray | None) -> torch.Tensor | None:
        return None if mask is None else torch.from_numpy(mask).to(self.device)

    def _load_net(
        self,
        net: nn.Module,
        name: str,
        weights: WeightsArg,
        allow_download: bool,
        *,
        prepare: Callable[[dict[str, Any]], Mapping[str, Any]] | None = None,
        ignore: Sequence[str] = (),
    ) -> nn.Module:
        """Load the weight file ``name`` into ``net``; return ``net`` in eval mode on this extractor's device.

        Parameters
        ----------
        net : nn.Module
        name : str
            Weight name (see :data:`pixie.weights.KNOWN_WEIGHTS`); error messages name it.
        weights : WeightsArg
            Explicit location (see :func:`weights_for`); else the search of :func:`pixie.weights.resolve_weights`.
        allow_download : bool
        prepare : callable, optional
            Turns the loaded checkpoint into the network's state dict (unwrap, strip key prefixes).
        ignore : sequence of str
            Entries the network has but the file may lack (derived buffers).

        Raises
        ------
        WeightsError
            When the file is not found or unreadable, or does not fit the network.
        """
        state = load_weights(name, weights, allow_download)
        if prepare is not None:
            state = prepare(state)
        load_strict(net, state, name, ignore=ignore, stacklevel=4)
        return net.eval().to(self.device)


def _kornia_feature() -> Any:
    if "kornia.feature" in sys.modules:  # imported already: no pause, no second freeze
        return sys.modules["kornia.feature"]
    with imports_without_gc():  # kornia imports ~600 modules (pixie.threads)
        import kornia.feature as KF

    return KF


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().cpu().numpy()


def _no_features(dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros((0, 2), np.float32), np.zeros((0, dim), np.float32), np.zeros(0, np.float32)


@dataclass
class RefBank:
    """Many reference :class:`Features` stacked for repeated matching on one device.

    Build it once with :meth:`Matcher.prepare_refs` and reuse it for every query (passing a list to
    ``match_many`` builds one on the fly). The padded tensors are built lazily and cached.
    """

    features: list[Features]
    device: torch.device
    _padded: dict[str, torch.Tensor] | None = field(default=None, repr=False)
    _by_row: dict[str, torch.Tensor] | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.features)

    @property
    def dim(self) -> int:
        """Descriptor dimension (0 when no reference has features)."""
        dims = {f.dim for f in self.features if len(f)}
        if len(dims) > 1:
            raise ValueError(f"references have different descriptor dimensions {sorted(dims)}")
        return dims.pop() if dims else 0

    def padded(self) -> dict[str, torch.Tensor]:
        """``desc (B, M, D)``, ``kp (B, M, 2)``, ``sqnorm (B, M)``, ``valid (B, M)``, padded to the largest ``M``.

        Padding has zero descriptors and keypoints at ``_FAR`` (outside any window).
        """
        if self._padded is None:
            counts = np.array([len(f) for f in self.features], dtype=np.int64)
            b, m, d = len(self.features), int(counts.max(initial=0)), self.dim
            desc = np.zeros((b, m, d), np.float32)
            kp = np.full((b, m, 2), _FAR, np.float32)
            for i, f in enumerate(self.features):
                desc[i, : len(f)] = f.descriptors
                kp[i, : len(f)] = f.keypoints
            valid = np.arange(m)[None, :] < counts[:, None]
            kp_t = torch.from_numpy(kp).to(self.device)
            self._padded = {
                "desc": torch.from_numpy(desc).to(self.device),
                "kp": kp_t,
                "sqnorm": (kp_t.double() ** 2).sum(-1).float(),
                "valid": torch.from_numpy(valid).to(self.device),
            }
        return self._padded

    def padded_by_row(self) -> dict[str, torch.Tensor]:
        """``desc``, ``kp``, ``sqnorm`` of :meth:`padded` with each reference's keypoints sorted by image row (``y``;
        padding last), ``rows (B, M)`` those rows, and ``order (B, M)``: the position in :meth:`padded` of each
        sorted entry. Banded window matching (:func:`pixie.matching.mnn.mutual_nn_match_many`) takes one
        contiguous range of them per band of rows."""
        if self._by_row is None:
            p = self.padded()
            order = torch.argsort(p["kp"][..., 1], dim=1, stable=True)
            take = order[..., None]
            self._by_row = {
                "desc": torch.gather(p["desc"], 1, take.expand(-1, -1, p["desc"].shape[2])),
                "kp": torch.gather(p["kp"], 1, take.expand(-1, -1, 2)),
                "sqnorm": torch.gather(p["sqnorm"], 1, order),
                "order": order,
            }
            self._by_row["rows"] = self._by_row["kp"][..., 1].contiguous()
        return self._by_row


def _sample(dense: torch.Tensor, grid: torch.Tensor, mode: str, align_corners: bool) -> torch.Tensor:
    """Sample ``(1, C, h, w)`` at a ``(1, N, 1, 2)`` grid -> ``(N, C)``."""
    return F.grid_sample(dense, grid, mode=mode, align_corners=align_corners)[0, :, :, 0].t()
