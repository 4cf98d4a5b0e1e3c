"""The keypoint data contract shared by references, matching and pose.

:class:`Features` (keypoints, descriptors, scores of one image) and :class:`Matches` (index pairs and
confidences); :func:`pack_features` / :func:`unpack_features` store many :class:`Features` compactly in one
``.npz``-ready dictionary (descriptors as float16). Plain NumPy: no torch, so that reference sets can be
read without the matching backends.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pixie.errors import ReferenceSetError

__all__ = ["Features", "Matches", "matched_keypoints", "pack_features", "unpack_features"]


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
