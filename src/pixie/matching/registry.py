"""Matchers by name: :class:`Matcher` (extractor + assigner), the registry, :func:`get_matcher` and
:func:`matcher_from_config` (the one place where configs become matchers)."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from pixie.errors import ConfigError, WeightsError
from pixie.features import Features, Matches
from pixie.matching.adapter import GridAlikedExtractor, load_adapter, shipped_adapter_path
from pixie.matching.aliked import AlikedExtractor
from pixie.matching.base import Extractor, RefBank, _kornia_feature
from pixie.matching.checkpoints import WeightsArg, load_weights, weights_for
from pixie.matching.disk import DiskExtractor
from pixie.matching.lightglue import LightGlueAssigner, build_lightglue
from pixie.matching.mnn import MutualNNAssigner
from pixie.matching.sift import SiftExtractor
from pixie.matching.superpoint import SuperPointExtractor
from pixie.matching.xfeat import XFeatExtractor
from pixie.weights import resolve_weights


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
        model = build_lightglue(kind, load_weights(lg_weights, weights, allow_download), device, **lg_opts)
        return Matcher(name, extractor, LightGlueAssigner(model, device))

    return factory


def _make_ft_nn(adapter: str) -> Callable[..., Matcher]:
    """ALIKED-n16 (top-k detections by default) + a fine-tuned descriptor adapter (:mod:`pixie.matching.adapter`), mutual NN.

    Options as ``aliked-nn`` plus ``grid`` (stride in px of extra keypoints put inside the mask of masked
    images, i.e. references; 0, the default, disables). ``weights`` may map the adapter name to another file.
    """

    def factory(name: str, device: torch.device, weights: WeightsArg, allow_download: bool, **opts: Any) -> Matcher:
        _split_options(name, opts, ("max_keypoints", "detection_threshold", "grid", *_NN_OPTIONS))
        ext_opts = {k: opts[k] for k in ("max_keypoints", "detection_threshold", "grid") if k in opts}
        nn_opts = {k: opts[k] for k in _NN_OPTIONS if k in opts}
        path = weights_for(weights, adapter) or shipped_adapter_path(adapter)
        extractor = GridAlikedExtractor(device, weights=weights_for(weights, "aliked-n16"),
                                        allow_download=allow_download, adapter=load_adapter(path), **ext_opts)
        return Matcher(name, extractor, MutualNNAssigner(device, **nn_opts))  # type: ignore[arg-type]

    return factory


def _adapter_shipped(name: str) -> bool:
    return shipped_adapter_path(name).is_file()


def _kornia_has(*names: str) -> bool:
    try:
        KF = _kornia_feature()
    except Exception:  # noqa: BLE001 - kornia missing or broken: the backend is unavailable
        return False
    return all(hasattr(KF, n) for n in names)


def _cv2_has_sift() -> bool:
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
