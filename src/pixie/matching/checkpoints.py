"""Weight files of the matching backends: where a backend's file is, loading it strictly, key remapping.

Every file is found by :func:`pixie.weights.resolve_weights`; nothing is downloaded unless ``allow_download``.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from pixie.errors import WeightsError
from pixie.weights import load_state_dict

WeightsArg = str | Path | Mapping[str, str | Path] | None


def load_weights(name: str, weights: WeightsArg, allow_download: bool) -> dict[str, Any]:
    """The state dict of weight ``name``: resolved (``weights`` first) and read with ``weights_only=True``."""
    return load_state_dict(name, weights_for(weights, name, primary=True), allow_download=allow_download)


def load_strict(
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


# --------------------------------------------------------------------------------------------------------------
# Weight helpers
# --------------------------------------------------------------------------------------------------------------


def weights_for(weights: WeightsArg, name: str, primary: bool = False) -> str | Path | None:
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


def disk_state(state: dict[str, Any]) -> Mapping[str, Any]:
    """The extractor's entries of an official DISK checkpoint (the file may also hold the matcher's)."""
    return state.get("extractor", state)


def superpoint_state(state: dict[str, Any]) -> dict[str, Any]:
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
