"""Local features and 2D-2D matching between a query photo and reference renders.

Data records
    :class:`Features` (keypoints, descriptors, scores of one image) and :class:`Matches` (index pairs and
    confidences); :func:`pack_features` / :func:`unpack_features` store many :class:`Features` compactly
    in one ``.npz``-ready dictionary (descriptors as float16).

Matchers
    :func:`get_matcher` builds a :class:`Matcher` by backend name (see :func:`available_matchers`):

    ``aliked-nn``, ``disk-nn``, ``xfeat-nn``, ``sift-nn``, ``superpoint-nn``
        detector/descriptor + mutual nearest neighbour, with an optional spatial ``window`` (pixels), ratio
        test and minimum cosine similarity. One query against hundreds of references runs batched in torch
        (chunks of references, one matrix product each).
    ``aliked-lg``, ``disk-lg``
        kornia's LightGlue with the LightGlue weights of the cvg release.
    ``xfeat-lighterglue``
        XFeat + LighterGlue (kornia's LightGlue network in the XFeat configuration).
    ``minima-sp-lg``
        SuperPoint + the MINIMA LightGlue weights (``minima_lightglue.pth``) of the pixie paper.
    ``aliked-ft-nn``
        ALIKED-n16 (top-k detections) whose descriptors pass through the adapter fine-tuned on synthetic
        photo/geometry pairs (``pixie/data/weights/aliked_n16_geoadapter.pt``); optional reference-mask grid.

Every weight file is found by :func:`pixie.weights.resolve_weights`; nothing is downloaded unless
``allow_download`` is true (the default of :func:`get_matcher`, a user-facing loader).

Conventions: keypoints are ``(x, y)`` pixels with integer values at pixel centres (OpenCV and kornia);
images are ``uint8`` ``HxW`` or ``HxWx3`` RGB; masks are boolean ``HxW``.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pixie.errors import ConfigError, ImageError, ReferenceSetError, WeightsError
from pixie.weights import load_state_dict

__all__ = [
    "Features",
    "Matches",
    "RefBank",
    "Matcher",
    "pack_features",
    "unpack_features",
    "matched_keypoints",
    "mutual_nn_match_many",
    "get_matcher",
    "available_matchers",
    "SuperPointNet",
]

WeightsArg = str | Path | Mapping[str, str | Path] | None

# --------------------------------------------------------------------------------------------------------------
# Data records
# --------------------------------------------------------------------------------------------------------------


def _as_2d_float32(a: Any, cols: int | None, what: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float32)
    if arr.ndim != 2 or (cols is not None and arr.shape[1] != cols):
        want = f"(N, {cols})" if cols is not None else "(N, D)"
        raise ValueError(f"{what} must have shape {want}, got {arr.shape}")
    return np.ascontiguousarray(arr)


@dataclass
class Features:
    """Local features of one image.

    Attributes
    ----------
    keypoints
        ``(N, 2)`` float32 ``(x, y)`` pixels in the image they were extracted from.
    descriptors
        ``(N, D)`` float32 descriptors (L2-normalised for every pixie backend). Float16 input is accepted
        and converted, so callers always get float32.
    scores
        ``(N,)`` float32 detection scores (backend-specific scale).
    image_size
        ``(h, w)`` of that image.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    scores: np.ndarray
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        self.keypoints = _as_2d_float32(self.keypoints, 2, "keypoints")
        self.descriptors = _as_2d_float32(self.descriptors, None, "descriptors")
        self.scores = np.ascontiguousarray(np.asarray(self.scores, dtype=np.float32).reshape(-1))
        n = len(self.keypoints)
        if len(self.descriptors) != n or len(self.scores) != n:
            raise ValueError(
                f"keypoints ({n}), descriptors ({len(self.descriptors)}) and scores ({len(self.scores)}) "
                "must have the same length"
            )
        h, w = (int(v) for v in self.image_size)
        self.image_size = (h, w)

    def __len__(self) -> int:
        return len(self.keypoints)

    @property
    def dim(self) -> int:
        """Descriptor dimension ``D``."""
        return int(self.descriptors.shape[1])

    def subset(self, index: np.ndarray) -> Features:
        """The features selected by a boolean mask or an index array."""
        return Features(self.keypoints[index], self.descriptors[index], self.scores[index], self.image_size)

    def to_arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        """Plain arrays for ``np.savez`` (descriptors as float16)."""
        return {
            f"{prefix}keypoints": self.keypoints,
            f"{prefix}descriptors": self.descriptors.astype(np.float16),
            f"{prefix}scores": self.scores,
            f"{prefix}image_size": np.asarray(self.image_size, dtype=np.int32),
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], prefix: str = "") -> Features:
        """Inverse of :meth:`to_arrays`."""
        try:
            return cls(
                arrays[f"{prefix}keypoints"],
                arrays[f"{prefix}descriptors"],
                arrays[f"{prefix}scores"],
                tuple(int(v) for v in np.asarray(arrays[f"{prefix}image_size"]).reshape(2)),  # type: ignore[arg-type]
            )
        except KeyError as exc:
            raise ReferenceSetError(f"feature arrays lack {exc.args[0]!r}") from exc

    @classmethod
    def empty(cls, dim: int, image_size: tuple[int, int]) -> Features:
        """No features, with descriptor dimension ``dim``."""
        return cls(np.zeros((0, 2)), np.zeros((0, dim)), np.zeros(0), image_size)


@dataclass
class Matches:
    """Correspondences between a query and a reference :class:`Features`.

    Attributes
    ----------
    idx_q, idx_r
        ``(M,)`` int64 indices into the query and reference features.
    scores
        ``(M,)`` float32 confidences (cosine similarity for the NN backends, LightGlue's match probability).
    """

    idx_q: np.ndarray
    idx_r: np.ndarray
    scores: np.ndarray

    def __post_init__(self) -> None:
        self.idx_q = np.asarray(self.idx_q, dtype=np.int64).reshape(-1)
        self.idx_r = np.asarray(self.idx_r, dtype=np.int64).reshape(-1)
        self.scores = np.asarray(self.scores, dtype=np.float32).reshape(-1)
        if not len(self.idx_q) == len(self.idx_r) == len(self.scores):
            raise ValueError("idx_q, idx_r and scores must have the same length")

    def __len__(self) -> int:
        return len(self.idx_q)

    @classmethod
    def empty(cls) -> Matches:
        """No matches."""
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32))


def matched_keypoints(q: Features, r: Features, m: Matches) -> tuple[np.ndarray, np.ndarray]:
    """``(M, 2)`` query and reference keypoints of the matches ``m``."""
    return q.keypoints[m.idx_q], r.keypoints[m.idx_r]


def pack_features(features: Sequence[Features], prefix: str = "feat_") -> dict[str, np.ndarray]:
    """Concatenate many :class:`Features` into a few arrays (descriptors float16), for one ``.npz``.

    Keys (with ``prefix``): ``keypoints`` ``(T, 2)`` float32, ``descriptors`` ``(T, D)`` float16,
    ``scores`` ``(T,)`` float32, ``offsets`` ``(K + 1,)`` int64 (features ``k`` are rows
    ``offsets[k]:offsets[k + 1]``), ``image_sizes`` ``(K, 2)`` int32 ``(h, w)``.
    """
    dims = {f.dim for f in features}
    if len(dims) > 1:
        raise ValueError(f"all features must have the same descriptor dimension, got {sorted(dims)}")
    dim = dims.pop() if dims else 0
    counts = np.array([len(f) for f in features], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)

    def cat(parts: list[np.ndarray], shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype)

    return {
        f"{prefix}keypoints": cat([f.keypoints for f in features], (0, 2), np.float32),
        f"{prefix}descriptors": cat([f.descriptors for f in features], (0, dim), np.float16),
        f"{prefix}scores": cat([f.scores for f in features], (0,), np.float32),
        f"{prefix}offsets": offsets,
        f"{prefix}image_sizes": np.array([f.image_size for f in features], dtype=np.int32).reshape(-1, 2),
    }


def unpack_features(arrays: Mapping[str, np.ndarray], prefix: str = "feat_") -> list[Features]:
    """Inverse of :func:`pack_features`.

    Raises
    ------
    ReferenceSetError
        If a key is missing or the arrays disagree in length.
    """
    try:
        kp = np.asarray(arrays[f"{prefix}keypoints"])
        desc = np.asarray(arrays[f"{prefix}descriptors"])
        scores = np.asarray(arrays[f"{prefix}scores"])
        offsets = np.asarray(arrays[f"{prefix}offsets"], dtype=np.int64)
        sizes = np.asarray(arrays[f"{prefix}image_sizes"]).reshape(-1, 2)
    except KeyError as exc:
        raise ReferenceSetError(f"packed features lack {exc.args[0]!r}") from exc
    total = len(kp)
    if (
        len(offsets) != len(sizes) + 1
        or offsets[0] != 0
        or offsets[-1] != total
        or np.any(np.diff(offsets) < 0)
        or len(desc) != total
        or len(scores) != total
    ):
        raise ReferenceSetError(
            f"packed features are inconsistent: {total} keypoints, {len(desc)} descriptors, {len(scores)} scores, "
            f"{len(offsets)} offsets for {len(sizes)} images"
        )
    return [
        Features(kp[a:b], desc[a:b], scores[a:b], (int(s[0]), int(s[1])))
        for a, b, s in zip(offsets[:-1], offsets[1:], sizes)
    ]


# --------------------------------------------------------------------------------------------------------------
# Image checks and conversions
# --------------------------------------------------------------------------------------------------------------


def check_image(image: Any) -> np.ndarray:
    """Validate an image and return it as ``uint8`` ``HxWx3`` RGB (grey is repeated).

    Raises
    ------
    ImageError
        If it is not a uint8 numpy array of shape ``HxW``, ``HxWx1`` or ``HxWx3``, or is empty.
    """
    if not isinstance(image, np.ndarray):
        raise ImageError(f"image must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise ImageError(f"image must be uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ImageError(f"image must be HxW or HxWx3 (RGB), got shape {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ImageError(f"image is empty (shape {image.shape})")
    return np.ascontiguousarray(image)


def check_mask(mask: Any, shape: tuple[int, int]) -> np.ndarray | None:
    """Validate an optional mask against an image ``(h, w)``; return a boolean ``HxW`` array or ``None``.

    Raises
    ------
    ImageError
        On a shape mismatch or a non-numeric mask.
    """
    if mask is None:
        return None
    arr = np.asarray(mask)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.shape != tuple(shape):
        raise ImageError(f"mask shape {arr.shape} does not match the image size {tuple(shape)}")
    if arr.dtype != np.bool_:
        if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
            raise ImageError(f"mask must be boolean, got {arr.dtype}")
        arr = arr != 0
    return arr


def _image_tensor(rgb: np.ndarray, device: torch.device) -> torch.Tensor:
    """``uint8 HxWx3`` -> float ``(1, 3, H, W)`` in ``[0, 1]``."""
    return torch.from_numpy(rgb).to(device).permute(2, 0, 1)[None].float().div_(255.0)


def _grey_tensor(rgb: np.ndarray, device: torch.device) -> torch.Tensor:
    """``uint8 HxWx3`` -> float ``(1, 1, H, W)`` luminance (ITU-R BT.601 weights) in ``[0, 1]``."""
    x = _image_tensor(rgb, device)
    w = torch.tensor([0.299, 0.587, 0.114], device=device).view(1, 3, 1, 1)
    return (x * w).sum(1, keepdim=True)


def _keep_in_mask(kp: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """Boolean selector of the keypoints whose nearest pixel lies inside ``mask`` (all if no mask)."""
    if mask is None or len(kp) == 0:
        return np.ones(len(kp), dtype=bool)
    h, w = mask.shape
    ix = np.clip(np.rint(kp[:, 0]).astype(np.int64), 0, w - 1)
    iy = np.clip(np.rint(kp[:, 1]).astype(np.int64), 0, h - 1)
    return mask[iy, ix]


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
        Explicit weight location (see :func:`_weights_for`); else the search of :func:`pixie.weights.resolve_weights`.
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
        keep = _keep_in_mask(kp, m)
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
            Explicit location (see :func:`_weights_for`); else the search of :func:`pixie.weights.resolve_weights`.
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
        state = _load_weights(name, weights, allow_download)
        if prepare is not None:
            state = prepare(state)
        _load_strict(net, state, name, ignore=ignore, stacklevel=4)
        return net.eval().to(self.device)


def _kornia_feature() -> Any:
    import kornia.feature as KF

    return KF


def _load_weights(name: str, weights: WeightsArg, allow_download: bool) -> dict[str, Any]:
    """The state dict of weight ``name``: resolved (``weights`` first) and read with ``weights_only=True``."""
    return load_state_dict(name, _weights_for(weights, name, primary=True), allow_download=allow_download)


def _load_strict(
    module: nn.Module, state: Mapping[str, torch.Tensor], what: str, ignore: Sequence[str] = (), stacklevel: int = 3
) -> None:
    """Load ``state`` into ``module``; unused entries are warned about at ``stacklevel``.

    Raises
    ------
    WeightsError
        When a learned entry is missing or has another shape (a file of another network). Entries the
        network does not have are only warned about.
    """
    try:
        result = module.load_state_dict(dict(state), strict=False)
    except RuntimeError as exc:  # shape mismatches
        first = (str(exc).splitlines() or [""])[0]
        raise WeightsError(f"{what}: the weight file does not fit the network ({first} ...)") from exc
    missing = [k for k in result.missing_keys if k not in ignore]
    if missing:
        raise WeightsError(
            f"{what}: the weight file does not fit the network: {len(missing)} entries missing "
            f"({', '.join(missing[:5])}{', ...' if len(missing) > 5 else ''})"
        )
    if result.unexpected_keys:
        extra = result.unexpected_keys
        warnings.warn(
            f"{what}: ignoring {len(extra)} weight entries the network does not use "
            f"({', '.join(extra[:5])}{', ...' if len(extra) > 5 else ''})",
            stacklevel=stacklevel,
        )


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

    def _extract(self, rgb: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = _image_tensor(rgb, self.device)
        m = None if mask is None else torch.from_numpy(mask).to(self.device, torch.float32)[None, None]
        lafs, responses, descs = self.net.forward_laf(x, mask=m, compute_affine=False)
        kp = lafs[0, :, :, 2]
        return _np(kp), _np(descs[0]), _np(responses[0, :, 0])


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().cpu().numpy()


def _no_features(dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros((0, 2), np.float32), np.zeros((0, dim), np.float32), np.zeros(0, np.float32)


class DiskExtractor(Extractor):
    """DISK (kornia's U-Net) with the official ``depth-save.pth`` weights; NMS window 5, logits above threshold."""

    dim = 128
    default_threshold = 0.0

    def _build(self, weights: WeightsArg, allow_download: bool) -> None:
        self.net = self._load_net(_kornia_feature().DISK(), "disk_depth", weights, allow_download, prepare=_disk_state)

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


def _xfeat_grid(pos: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """XFeat's sampling grid: ``2 p / (size - 1) - 1`` (used with ``align_corners=False``, as trained)."""
    scale = torch.tensor([w - 1, h - 1], device=pos.device, dtype=torch.float32)
    return (2.0 * pos.float() / scale - 1.0)[None, :, None, :]


def _sample(dense: torch.Tensor, grid: torch.Tensor, mode: str, align_corners: bool) -> torch.Tensor:
    """Sample ``(1, C, h, w)`` at a ``(1, N, 1, 2)`` grid -> ``(N, C)``."""
    return F.grid_sample(dense, grid, mode=mode, align_corners=align_corners)[0, :, :, 0].t()


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


class SiftExtractor(Extractor):
    """OpenCV SIFT with RootSIFT descriptors (L1-normalise, square root: unit L2 norm)."""

    dim = 128
    default_threshold = 0.04  # OpenCV's contrastThreshold

    def _build(self, weights: WeightsArg, allow_download: bool) -> None:  # no weights
        import cv2

        self._cv2 = cv2
        self.sift = cv2.SIFT_create(nfeatures=self.max_keypoints, contrastThreshold=self.threshold)

    def _extract(self, rgb: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        grey = self._cv2.cvtColor(rgb, self._cv2.COLOR_RGB2GRAY)
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
        self.net = self._load_net(SuperPointNet(), "superpoint", weights, allow_download, prepare=_superpoint_state)

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


# --------------------------------------------------------------------------------------------------------------
# Weight helpers
# --------------------------------------------------------------------------------------------------------------


def _weights_for(weights: WeightsArg, name: str, primary: bool = False) -> str | Path | None:
    """The explicit location for weight ``name``.

    ``weights`` may be a dict ``{name: path}``, a folder (searched first for every weight), or a file
    (used for the ``primary`` weight of a backend only).
    """
    if weights is None:
        return None
    if isinstance(weights, Mapping):
        return weights.get(name)
    if Path(weights).expanduser().is_dir():
        return weights
    return weights if primary else None


def _unwrap_state(state: Mapping[str, Any]) -> dict[str, Any]:
    """Return the tensor dict of a checkpoint that may wrap it in ``state_dict`` / ``model``."""
    for key in ("state_dict", "model"):
        inner = state.get(key)
        if isinstance(inner, Mapping) and inner and all(isinstance(v, torch.Tensor) for v in inner.values()):
            return dict(inner)
    return dict(state)


def _disk_state(state: dict[str, Any]) -> Mapping[str, Any]:
    """The extractor's entries of an official DISK checkpoint (the file may also hold the matcher's)."""
    return state.get("extractor", state)


def _superpoint_state(state: dict[str, Any]) -> dict[str, Any]:
    """SuperPoint entries with the wrappers and key prefixes of other training code removed."""
    return _strip_prefixes(_unwrap_state(state), ("module.", "extractor.", "net."))


def _strip_prefixes(state: Mapping[str, Any], prefixes: Sequence[str]) -> dict[str, Any]:
    out = {}
    for k, v in state.items():
        for p in prefixes:
            if k.startswith(p):
                k = k[len(p):]
                break
        out[k] = v
    return out


_OLD_LG_KEY = re.compile(r"^(self_attn|cross_attn)\.(\d+)\.")
_UNUSED_LG_KEY = re.compile(r"^log_assignment\.\d+\.r$")  # a constant 1.0 of the v0.1 files, never used


def remap_lightglue_state(state: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """Bring a LightGlue checkpoint to kornia's key layout.

    Handles checkpoints wrapped in ``state_dict``/``model``, the ``matcher.`` prefix of XFeat's LighterGlue
    file (whose ``extractor.*`` entries are dropped) and the old layout ``self_attn.N.*`` /
    ``cross_attn.N.*`` (-> ``transformers.N.self_attn.*``), whose unused ``log_assignment.N.r`` are dropped.
    """
    state = _unwrap_state(state)
    out: dict[str, torch.Tensor] = {}
    for key, value in state.items():
        if key.startswith("extractor."):
            continue
        key = _strip_prefixes({key: None}, ("module.", "matcher.", "net."))
        key = next(iter(key))
        if _UNUSED_LG_KEY.match(key):
            continue
        key = _OLD_LG_KEY.sub(lambda m: f"transformers.{m.group(2)}.{m.group(1)}.", key)
        out[key] = value
    return out


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
        _load_strict(model, remap_lightglue_state(state), f"{kind} LightGlue", ignore=("confidence_thresholds",))
    return model.eval().to(device)


# --------------------------------------------------------------------------------------------------------------
# Reference banks and mutual nearest neighbour matching
# --------------------------------------------------------------------------------------------------------------


_NEG = -4.0  # below any cosine similarity: marks pairs that are not candidates
_FAR = 1.0e6  # keypoint coordinate of padding entries: outside every window


@dataclass
class RefBank:
    """Many reference :class:`Features` stacked for repeated matching on one device.

    Build it once with :meth:`Matcher.prepare_refs` and reuse it for every query (passing a list to
    ``match_many`` builds one on the fly). The padded tensors are built lazily and cached.
    """

    features: list[Features]
    device: torch.device
    _padded: dict[str, torch.Tensor] | None = field(default=None, repr=False)

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


def _as_bank(refs: Sequence[Features] | RefBank, device: torch.device) -> RefBank:
    if isinstance(refs, RefBank):
        return refs
    return RefBank(list(refs), device)


def _pairs_to_matches(
    q_idx: torch.Tensor, ref_idx: torch.Tensor, r_idx: torch.Tensor, sims: torch.Tensor, n_refs: int
) -> list[Matches]:
    """Split flat match lists (sorted by reference) into one :class:`Matches` per reference."""
    q, b, r, s = (t.cpu().numpy() for t in (q_idx, ref_idx, r_idx, sims))
    bounds = np.searchsorted(b, np.arange(n_refs + 1))
    return [Matches(q[x:y], r[x:y], s[x:y]) for x, y in zip(bounds[:-1], bounds[1:])]


def _accept(
    best: torch.Tensor, second: torch.Tensor | None, ratio: float | None, min_sim: float | None
) -> torch.Tensor:
    """Candidate exists, minimum similarity, and ratio test on descriptor distances ``sqrt(2 - 2 s)``."""
    ok = best > _NEG / 2
    if min_sim is not None:
        ok &= best >= min_sim
    if ratio is not None and second is not None:
        d1 = torch.sqrt(torch.clamp(2 - 2 * best, min=0))
        d2 = torch.sqrt(torch.clamp(2 - 2 * second, min=0))
        # a missing second candidate (similarity _NEG) has distance sqrt(10) > 2 and passes
        ok &= d1 < ratio * d2
    return ok


def _mnn_chunk(
    q_desc: torch.Tensor,
    q_kp: torch.Tensor,
    q_sqnorm: torch.Tensor,
    desc: torch.Tensor,
    kp: torch.Tensor,
    sqnorm: torch.Tensor,
    valid: torch.Tensor,
    window: float | None,
    ratio: float | None,
    min_sim: float | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mutual NN of one query against a chunk of ``b`` padded references.

    Returns ``(ref_in_chunk, q_idx, r_idx, similarity)`` of the accepted pairs, sorted by reference.
    """
    b = desc.shape[0]
    sim = torch.matmul(q_desc, desc.transpose(1, 2))  # (b, N, M)
    if window is not None:
        # squared distances in one fused kernel: |q|^2 + |r|^2 - 2 q.r
        d2 = torch.baddbmm(
            q_sqnorm[None, :, None] + sqnorm[:, None, :], q_kp[None].expand(b, -1, -1), kp.transpose(1, 2),
            alpha=-2.0,
        )
        sim = torch.where(d2 < window * window, sim, _NEG)  # padding lies far outside every window
    else:
        sim = torch.where(valid[:, None, :], sim, _NEG)
    second = None
    if ratio is not None and sim.shape[2] >= 2:
        top = sim.topk(2, dim=2)
        best, fwd, second = top.values[..., 0], top.indices[..., 0], top.values[..., 1]
    else:
        best, fwd = sim.max(dim=2)
    col_best = sim.amax(dim=1)  # (b, M): best similarity of each reference keypoint over the query
    ok = (best >= torch.gather(col_best, 1, fwd)) & _accept(best, second, ratio, min_sim)
    bb, qq = ok.nonzero(as_tuple=True)
    return bb, qq, fwd[bb, qq], best[bb, qq]


def _mnn_dense(
    q_desc: torch.Tensor,
    q_kp: torch.Tensor,
    bank: RefBank,
    window: float | None,
    ratio: float | None,
    min_sim: float | None,
    chunk_elems: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mutual NN against all references of ``bank``, in chunks of about ``chunk_elems`` similarities."""
    pad = bank.padded()
    b_all, m, _ = pad["desc"].shape
    n = q_desc.shape[0]
    per = max(1, chunk_elems // max(1, n * m))
    q_sqnorm = (q_kp.double() ** 2).sum(-1).float()
    out_q, out_b, out_r, out_s = [], [], [], []
    for s0 in range(0, b_all, per):
        sl = slice(s0, s0 + per)
        bb, qq, rr, ss = _mnn_chunk(
            q_desc, q_kp, q_sqnorm, pad["desc"][sl], pad["kp"][sl], pad["sqnorm"][sl], pad["valid"][sl],
            window, ratio, min_sim,
        )
        out_b.append(bb + s0)
        out_q.append(qq)
        out_r.append(rr)
        out_s.append(ss)
    return torch.cat(out_q), torch.cat(out_b), torch.cat(out_r), torch.cat(out_s)


def mutual_nn_match_many(
    q: Features,
    refs: Sequence[Features] | RefBank,
    *,
    window: float | None = None,
    ratio: float | None = None,
    min_similarity: float | None = None,
    device: torch.device | str = "cpu",
    chunk_elems: int | None = None,
) -> list[Matches]:
    """Mutual nearest neighbours (cosine similarity) between one query and many references.

    Parameters
    ----------
    q, refs
        The query features and the references (a list, or a prepared :class:`RefBank`). Descriptors are
        expected L2-normalised (every pixie extractor does so).
    window
        Only pairs whose keypoints are closer than ``window`` pixels are candidates (query and references
        share a pixel frame, e.g. equally sized object-centred crops). ``None``: no spatial limit.
    ratio
        Lowe's ratio on descriptor distances among the candidates of one query keypoint in one reference.
    min_similarity
        Minimum cosine similarity of a match.
    device
        Where to compute (a :class:`RefBank` keeps its own device).
    chunk_elems
        Similarities computed per chunk of references (default 2**21 on CPU, 2**26 on CUDA).

    Returns
    -------
    list[Matches]
        One per reference, sorted by query index; scores are cosine similarities.
    """
    bank = _as_bank(refs, torch.device(device))
    dev = bank.device
    if len(bank) == 0:
        return []
    if len(q) == 0 or bank.dim == 0:
        return [Matches.empty() for _ in range(len(bank))]
    if bank.dim != q.dim:
        raise ValueError(f"query descriptors are {q.dim}-D but references are {bank.dim}-D")
    if chunk_elems is None:
        chunk_elems = 1 << (26 if dev.type == "cuda" else 21)
    with torch.inference_mode():
        q_desc = torch.from_numpy(q.descriptors).to(dev)
        q_kp = torch.from_numpy(q.keypoints).to(dev)
        win = None if window is None else float(window)
        res = _mnn_dense(q_desc, q_kp, bank, win, ratio, min_similarity, int(chunk_elems))
        return _pairs_to_matches(*res, n_refs=len(bank))


# --------------------------------------------------------------------------------------------------------------
# Assigners (the matching half of a backend)
# --------------------------------------------------------------------------------------------------------------


class MutualNNAssigner:
    """Mutual nearest neighbour assignment with optional window / ratio / min similarity."""

    def __init__(
        self,
        device: torch.device,
        *,
        window: float | None = None,
        ratio: float | None = None,
        min_similarity: float | None = None,
    ) -> None:
        self.device = device
        self.window = None if window is None else float(window)
        self.ratio = None if ratio is None else float(ratio)
        self.min_similarity = None if min_similarity is None else float(min_similarity)

    def match_many(self, q: Features, refs: Sequence[Features] | RefBank) -> list[Matches]:
        return mutual_nn_match_many(
            q, refs, window=self.window, ratio=self.ratio, min_similarity=self.min_similarity,
            device=self.device,
        )


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


# --------------------------------------------------------------------------------------------------------------
# Matcher and registry
# --------------------------------------------------------------------------------------------------------------


class Matcher:
    """A matching backend: an extractor plus an assignment strategy.

    Use :func:`get_matcher` to build one.
    """

    def __init__(self, name: str, extractor: Extractor, assigner: MutualNNAssigner | LightGlueAssigner) -> None:
        self.name = name
        self.extractor = extractor
        self.assigner = assigner
        self.device = extractor.device

    def __repr__(self) -> str:
        return f"Matcher({self.name!r}, device={self.device})"

    @property
    def descriptor_dim(self) -> int:
        """Descriptor dimension of the extractor."""
        return self.extractor.dim

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        """Local features of ``image`` (uint8 ``HxW`` or ``HxWx3`` RGB), only inside ``mask`` if given.

        Raises
        ------
        ImageError
            For a wrong dtype/shape, an empty image, or a mask of another size.
        """
        return self.extractor(image, mask)

    def prepare_refs(self, refs: Sequence[Features]) -> RefBank:
        """Stack references once for repeated :meth:`match_many` calls."""
        return RefBank(list(refs), self.device)

    def match(self, q: Features, r: Features) -> Matches:
        """Match one query against one reference."""
        return self.match_many(q, [r])[0]

    def match_many(self, q: Features, refs: Sequence[Features] | RefBank) -> list[Matches]:
        """Match one query against many references; one :class:`Matches` per reference, in order."""
        return self.assigner.match_many(q, refs)


def resolve_device(device: str | torch.device | None) -> torch.device:
    """``'cpu'`` (default), ``'cuda'`` when available (falls back to CPU with a warning), or ``'auto'``."""
    if device is None:
        return torch.device("cpu")
    if str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        warnings.warn("CUDA was asked for but is not available; pixie matches on the CPU", stacklevel=3)
        return torch.device("cpu")
    return dev


_EXTRACTORS: dict[str, type[Extractor]] = {
    "aliked": AlikedExtractor,
    "disk": DiskExtractor,
    "xfeat": XFeatExtractor,
    "sift": SiftExtractor,
    "superpoint": SuperPointExtractor,
}

_NN_OPTIONS = ("window", "ratio", "min_similarity")
_LG_OPTIONS = ("filter_threshold", "depth_confidence", "width_confidence", "flash")


def _split_options(name: str, options: dict[str, Any], allowed: Sequence[str]) -> dict[str, Any]:
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ConfigError(f"matcher {name!r} does not take option(s) {unknown}; it takes {sorted(allowed)}")
    return options


def _make_nn(kind: str) -> Callable[..., Matcher]:
    def factory(name: str, device: torch.device, weights: WeightsArg, allow_download: bool, **opts: Any) -> Matcher:
        extra = ("model",) if kind == "aliked" else ("nms_radius", "border") if kind == "superpoint" else ()
        _split_options(name, opts, ("max_keypoints", "detection_threshold", *extra, *_NN_OPTIONS))
        ext_opts = {k: opts[k] for k in ("max_keypoints", "detection_threshold", *extra) if k in opts}
        nn_opts = {k: opts[k] for k in _NN_OPTIONS if k in opts}
        extractor = _EXTRACTORS[kind](device, weights=weights, allow_download=allow_download, **ext_opts)
        return Matcher(name, extractor, MutualNNAssigner(device, **nn_opts))

    return factory


def _make_lg(kind: str, lg_weights: str) -> Callable[..., Matcher]:
    def factory(name: str, device: torch.device, weights: WeightsArg, allow_download: bool, **opts: Any) -> Matcher:
        _split_options(name, opts, ("max_keypoints", "detection_threshold", *_LG_OPTIONS))
        ext_opts = {k: opts[k] for k in ("max_keypoints", "detection_threshold") if k in opts}
        lg_opts = {k: opts[k] for k in _LG_OPTIONS if k in opts}
        # a plain file path names the LightGlue file; a dict or a folder also serves the extractor
        ext_weights = weights if weights is None or isinstance(weights, Mapping) or Path(weights).is_dir() else None
        extractor = _EXTRACTORS[kind](device, weights=ext_weights, allow_download=allow_download, **ext_opts)
        model = build_lightglue(kind, _load_weights(lg_weights, weights, allow_download), device, **lg_opts)
        return Matcher(name, extractor, LightGlueAssigner(model, device))

    return factory


def _make_ft_nn(adapter: str) -> Callable[..., Matcher]:
    """ALIKED-n16 (top-k detections by default) + a fine-tuned descriptor adapter (:mod:`pixie.adapter`), mutual NN.

    Options as ``aliked-nn`` plus ``grid`` (stride in px of extra keypoints put inside the mask of masked
    images, i.e. references; 0, the default, disables). ``weights`` may map the adapter name to another file.
    """

    def factory(name: str, device: torch.device, weights: WeightsArg, allow_download: bool, **opts: Any) -> Matcher:
        from pixie.adapter import GridAlikedExtractor, load_adapter, shipped_adapter_path

        _split_options(name, opts, ("max_keypoints", "detection_threshold", "grid", *_NN_OPTIONS))
        ext_opts = {k: opts[k] for k in ("max_keypoints", "detection_threshold", "grid") if k in opts}
        nn_opts = {k: opts[k] for k in _NN_OPTIONS if k in opts}
        path = _weights_for(weights, adapter) or shipped_adapter_path(adapter)
        extractor = GridAlikedExtractor(device, weights=_weights_for(weights, "aliked-n16"),
                                        allow_download=allow_download, adapter=load_adapter(path), **ext_opts)
        return Matcher(name, extractor, MutualNNAssigner(device, **nn_opts))  # type: ignore[arg-type]

    return factory


def _adapter_shipped(name: str) -> bool:
    from pixie.adapter import shipped_adapter_path

    return shipped_adapter_path(name).is_file()


def _kornia_has(*names: str) -> bool:
    try:
        KF = _kornia_feature()
    except Exception:  # noqa: BLE001 - kornia missing or broken: the backend is unavailable
        return False
    return all(hasattr(KF, n) for n in names)


def _cv2_has_sift() -> bool:
    try:
        import cv2
    except Exception:  # noqa: BLE001
        return False
    return hasattr(cv2, "SIFT_create")


# name -> (factory, code requirement, weight names needed)
_REGISTRY: dict[str, tuple[Callable[..., Matcher], Callable[[], bool], tuple[str, ...]]] = {
    "aliked-nn": (_make_nn("aliked"), lambda: _kornia_has("ALIKED"), ("aliked-n16",)),
    "disk-nn": (_make_nn("disk"), lambda: _kornia_has("DISK"), ("disk_depth",)),
    "xfeat-nn": (_make_nn("xfeat"), lambda: _kornia_has("XFeatModel"), ("xfeat",)),
    "sift-nn": (_make_nn("sift"), _cv2_has_sift, ()),
    "superpoint-nn": (_make_nn("superpoint"), lambda: True, ("superpoint",)),
    "aliked-lg": (_make_lg("aliked", "aliked_lightglue"), lambda: _kornia_has("ALIKED", "LightGlue"),
                  ("aliked-n16", "aliked_lightglue")),
    "disk-lg": (_make_lg("disk", "disk_lightglue"), lambda: _kornia_has("DISK", "LightGlue"),
                ("disk_depth", "disk_lightglue")),
    "xfeat-lighterglue": (_make_lg("xfeat", "xfeat_lighterglue"), lambda: _kornia_has("XFeatModel", "LightGlue"),
                          ("xfeat", "xfeat_lighterglue")),
    "minima-sp-lg": (_make_lg("superpoint", "minima_lightglue"), lambda: _kornia_has("LightGlue"),
                     ("superpoint", "minima_lightglue")),
    # fine-tuned on synthetic photo <-> geometry pairs (pixie.train.finetune; model card in pixie/data/weights)
    "aliked-ft-nn": (_make_ft_nn("aliked_n16_geoadapter"),
                     lambda: _kornia_has("ALIKED") and _adapter_shipped("aliked_n16_geoadapter"), ("aliked-n16",)),
}


def backend_weights() -> dict[str, tuple[str, ...]]:
    """Weight names (:func:`pixie.weights.known_weight_names`) each matching backend needs, by backend name."""
    return {name: needed for name, (_, _, needed) in sorted(_REGISTRY.items())}


def available_matchers(check_weights: bool = False) -> list[str]:
    """Backend names whose code is available here (sorted).

    With ``check_weights=True`` only those whose weight files are found locally (no download).
    """
    from pixie.weights import resolve_weights

    names = []
    for name, (_, code_ok, needed) in sorted(_REGISTRY.items()):
        if not code_ok():
            continue
        if check_weights:
            try:
                for w in needed:
                    resolve_weights(w, allow_download=False)
            except WeightsError:
                continue
        names.append(name)
    return names


def get_matcher(
    name: str,
    *,
    device: str | torch.device | None = "cpu",
    weights: WeightsArg = None,
    allow_download: bool = True,
    **options: Any,
) -> Matcher:
    """Build the matching backend ``name``.

    Parameters
    ----------
    name
        One of :func:`available_matchers`.
    device
        ``'cpu'`` (default), ``'cuda'`` (CPU with a warning when unavailable) or ``'auto'``.
    weights
        Explicit weight locations: a dict ``{weight name: path}`` (e.g. ``{"superpoint": ..., "minima_lightglue":
        ...}``), a folder searched first for every file, or one file for the backend's main weights (the
        LightGlue file of the LightGlue backends, the extractor file of ``*-nn``). Whatever is not given is
        resolved by :func:`pixie.weights.resolve_weights`.
    allow_download
        Let missing weights be downloaded from their official address into the user cache.
    **options
        ``max_keypoints`` (default 1024), ``detection_threshold`` (backend default when omitted);
        NN backends: ``window`` (px), ``ratio``, ``min_similarity`` (all off by default);
        ``aliked-nn``: ``model`` (``aliked-n16`` default, ``-n16rot``, ``-n32``, ``-t16``);
        LightGlue backends: ``filter_threshold`` (0.1), ``depth_confidence``, ``width_confidence``, ``flash``.

    Raises
    ------
    ConfigError
        Unknown backend or option, or a backend whose code is not available in this installation.
    WeightsError
        Missing weight files (the message lists where pixie looked).
    """
    entry = _REGISTRY.get(name)
    if entry is None:
        raise ConfigError(f"unknown matcher {name!r}; known: {', '.join(sorted(_REGISTRY))}")
    factory, code_ok, _ = entry
    if not code_ok():
        raise ConfigError(f"matcher {name!r} is not available: this kornia/OpenCV lacks the network it needs")
    options = dict(options)
    if options.get("max_keypoints") is None:
        options["max_keypoints"] = 1024
    return factory(name, resolve_device(device), weights, allow_download, **options)


def matcher_from_config(match_cfg: Any, ref_size: int) -> Matcher:
    """The matcher described by a :class:`pixie.config.MatchConfig`.

    ``match_cfg.window`` is a fraction of the reference image side ``ref_size``; NN backends get it
    in pixels. This is the one place where configs become matchers (estimator, runner, CLI).
    """
    opts: dict[str, Any] = {}
    if match_cfg.matcher.endswith("-nn"):
        opts["window"] = None if match_cfg.window is None else match_cfg.window * ref_size
    if match_cfg.detection_threshold is not None:
        opts["detection_threshold"] = match_cfg.detection_threshold
    return get_matcher(match_cfg.matcher, device=match_cfg.device, weights=match_cfg.weights_dir,
                       max_keypoints=match_cfg.max_keypoints, **opts)
