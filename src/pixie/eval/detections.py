"""External 2D detections in the BOP format: the boxes (and masks) a detector such as CNOS gave, per target.

The BOP'23 default-detections files (and any detector writing the BOP / COCO results format) are a JSON list of

    {"scene_id": 48, "image_id": 1, "category_id": 5, "score": 0.87, "bbox": [x, y, w, h], "time": 0.3,
     "segmentation": {"counts": ..., "size": [height, width]}}

``category_id`` is the object id; ``segmentation`` (optional) a COCO run-length encoding, its ``counts`` a list of
run lengths or COCO's compressed string; ``time`` (optional) the detector's seconds for the image. As in BOP's
unseen-object protocol, a target with ``inst_count`` instances takes the ``inst_count`` top-scoring detections of
its object in its image (:meth:`DetectionSet.for_target`); a target without any is a miss.

Boxes: with a segmentation the box is the mask's own (pixel-exact, :func:`pixie.pipeline.query.bbox_from_mask`);
without one, ``bbox`` is read as BOP's ``bbox_visib`` is (``w`` = last − first column, :func:`box_from_bop`).

>>> dets = load_detections("cnos-fastsam_lmo-test.json")
>>> [d.box_xywh for d in dets.for_target(scene_id=2, image_id=3, obj_id=5, n=1)]
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pixie.errors import DatasetError
from pixie.eval.datasets import box_from_bop
from pixie.pipeline.query import bbox_from_mask

__all__ = ["Detection", "DetectionSet", "load_detections", "rle_decode", "rle_encode"]


@dataclass(kw_only=True)
class Detection:
    """One detection: the object's box in pixie's convention (x, y, w, h; w counts pixels), its score and mask."""

    scene_id: int
    image_id: int
    obj_id: int
    score: float
    box_xywh: np.ndarray
    rle: dict | None = field(default=None, repr=False)  # COCO run-length encoding, decoded by :meth:`mask`
    time: float | None = None
    index: int = -1  # position in the file (for messages)

    def mask(self) -> np.ndarray | None:
        """(H, W) bool mask of the segmentation, None without one."""
        return None if self.rle is None else rle_decode(self.rle)


@dataclass(kw_only=True)
class DetectionSet:
    """Detections of one file, by (scene, image, object), best score first."""

    path: Path
    sha256: str
    by_target: dict[tuple[int, int, int], list[Detection]]

    def __len__(self) -> int:
        return sum(len(v) for v in self.by_target.values())

    def for_target(self, scene_id: int, image_id: int, obj_id: int, n: int = 1) -> list[Detection]:
        """The ``n`` top-scoring detections of object ``obj_id`` in the image (fewer when the detector gave fewer)."""
        return self.by_target.get((int(scene_id), int(image_id), int(obj_id)), [])[: max(int(n), 0)]


# ------------------------------------------------------------------------------------------ run-length encoding


def rle_encode(mask: np.ndarray) -> dict:
    """COCO run-length encoding (uncompressed ``counts``) of a (H, W) bool mask: runs of 0 then 1 ... in column-major
    order, starting with a (possibly empty) run of zeros."""
    m = np.asarray(mask, bool)
    flat = m.ravel(order="F")
    edges = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    runs = np.diff(np.r_[0, edges, flat.size]).tolist()
    if flat.size and flat[0]:
        runs = [0] + runs
    return {"size": [int(m.shape[0]), int(m.shape[1])], "counts": [int(c) for c in runs]}


def _decode_counts_string(s: str) -> list[int]:
    """COCO's compressed ``counts`` (pycocotools ``rleToString``): 5 bits per character from '0' (48), a
    continuation bit 0x20, sign extension of the last group, and every count after the second stored as the
    difference to the count two before."""
    counts: list[int] = []
    i = 0
    while i < len(s):
        x, k, more = 0, 0, True
        while more:
            if i >= len(s):
                raise ValueError("truncated compressed counts")
            c = ord(s[i]) - 48
            if c < 0 or c > 63:
                raise ValueError(f"character {s[i]!r} is not in COCO's RLE alphabet")
            x |= (c & 0x1F) << (5 * k)
            more = bool(c & 0x20)
            i += 1
            k += 1
            if not more and (c & 0x10):
                x |= -1 << (5 * k)
        if len(counts) > 2:
            x += counts[-2]
        counts.append(x)
    return counts


def rle_decode(rle: dict) -> np.ndarray:
    """(H, W) bool mask of a COCO run-length encoding (``counts`` a list of runs or COCO's compressed string)."""
    if not isinstance(rle, dict) or "size" not in rle or "counts" not in rle:
        raise ValueError("a segmentation is {'size': [height, width], 'counts': ...}")
    size = rle["size"]
    if not (isinstance(size, (list, tuple)) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
        raise ValueError(f"segmentation size must be [height, width] (positive integers), got {size!r}")
    h, w = size
    counts = rle["counts"]
    if isinstance(counts, (bytes, str)):
        counts = _decode_counts_string(counts.decode() if isinstance(counts, bytes) else counts)
    elif not (isinstance(counts, list) and all(isinstance(c, int) and c >= 0 for c in counts)):
        raise ValueError("segmentation counts must be run lengths (non-negative integers) or a compressed string")
    if any(c < 0 for c in counts) or sum(counts) != h * w:
        raise ValueError(f"segmentation runs cover {sum(counts)} pixels, its size {h} x {w} has {h * w}")
    values = np.zeros(len(counts), bool)
    values[1::2] = True
    flat = np.repeat(values, counts)
    return flat.reshape((w, h)).T


# ------------------------------------------------------------------------------------------ the file


def _entry(i: int, d, where: str) -> Detection:
    def bad(msg: str) -> DatasetError:
        return DatasetError(f"{where} entry {i}: {msg}")

    if not isinstance(d, dict):
        raise bad(f"a detection is an object with scene_id, image_id, category_id, score and bbox, got {type(d).__name__}")
    missing = [k for k in ("scene_id", "image_id", "category_id", "score", "bbox") if k not in d]
    if missing:
        raise bad(f"missing {', '.join(missing)} (BOP detections: scene_id, image_id, category_id, score, bbox "
                  "[x, y, w, h], optional segmentation and time)")
    ids = {}
    for k in ("scene_id", "image_id", "category_id"):
        v = d[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v != int(v) or v < 0:
            raise bad(f"{k} must be a non-negative integer, got {v!r}")
        ids[k] = int(v)
    score = d["score"]
    if isinstance(score, bool) or not isinstance(score, (int, float)) or not math.isfinite(score):
        raise bad(f"score must be a finite number, got {score!r}")
    b = d["bbox"]
    if not (isinstance(b, (list, tuple)) and len(b) == 4
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in b)):
        raise bad(f"bbox must be 4 numbers [x, y, w, h], got {b!r}")
    if b[2] < 0 or b[3] < 0:
        raise bad(f"bbox width and height must be >= 0, got {list(b)}")
    rle = d.get("segmentation")
    box = box_from_bop(b)
    if rle is not None:
        try:
            m = rle_decode(rle)
        except ValueError as exc:
            raise bad(f"segmentation: {exc}") from exc
        if not m.any():
            raise bad("segmentation is empty (no pixel of the object)")
        box = bbox_from_mask(m)
    t = d.get("time")
    if t is not None and (isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t)):
        raise bad(f"time must be a number of seconds, got {t!r}")
    return Detection(scene_id=ids["scene_id"], image_id=ids["image_id"], obj_id=ids["category_id"], score=float(score),
                     box_xywh=box, rle=rle, time=None if t is None else float(t), index=i)


def load_detections(path: str | Path) -> DetectionSet:
    """Read and check a BOP detections JSON file; :class:`DatasetError` names the file and the entry at fault."""
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"detections file not found: {p}")
    raw = p.read_bytes()
    try:
        data = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{p} is not JSON: {exc}") from exc
    if not isinstance(data, list):
        raise DatasetError(f"{p}: BOP detections are a JSON list of detections, got a {type(data).__name__}")
    by: dict[tuple[int, int, int], list[Detection]] = {}
    for i, d in enumerate(data):
        det = _entry(i, d, str(p))
        by.setdefault((det.scene_id, det.image_id, det.obj_id), []).append(det)
    for v in by.values():
        v.sort(key=lambda det: (-det.score, det.index))
    return DetectionSet(path=p, sha256=hashlib.sha256(raw).hexdigest(), by_target=by)
