"""Geometry → 8-bit images that image matchers can read.

Encodings (names used in configs):

- ``depth``: depth normalised inside the mask (near = 1), fixed colormap (turbo), black background.
- ``normal``: camera-frame normal map as RGB ((n_x, -n_y, -n_z) + 1) / 2.
- ``shade1`` / ``shade3``: grey Lambertian shading from normals with one headlight / three lights.
- ``*_edges`` (e.g. ``shade3_edges``): the same with crease and occlusion edge lines drawn dark.

Measured on real LM-O crops at the true view, grey multi-light shading with edge lines matched real
photos best; depth and normal colormaps are the paper's encodings.
"""

from __future__ import annotations

import cv2
import numpy as np

from pixie.errors import ConfigError

# Light directions in the camera frame (pointing from the surface towards the light).
_HEADLIGHT = np.array([[-0.3, -0.4, -1.0]])
_THREE_LIGHTS = np.array([[-0.6, -0.6, -1.0], [0.7, -0.2, -0.8], [0.0, 0.8, -0.6]])
_THREE_WEIGHTS = np.array([0.55, 0.3, 0.25])
AMBIENT = 0.12

BASE_ENCODINGS = ("depth", "normal", "shade1", "shade3")
ENCODINGS = BASE_ENCODINGS + tuple(f"{b}_edges" for b in BASE_ENCODINGS)


def check_encodings(names: list[str]) -> list[str]:
    """Validate a list of encoding names."""
    for n in names:
        if n not in ENCODINGS:
            raise ConfigError(f"unknown encoding {n!r}; known: {', '.join(ENCODINGS)}")
    if not names:
        raise ConfigError("at least one encoding is needed")
    return list(names)


def encode_depth(depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Turbo-coloured normalised depth (H, W, 3) uint8; near surfaces are warm."""
    out = np.zeros((*depth.shape, 3), np.uint8)
    if not mask.any():
        return out
    d = depth[mask]
    lo, hi = float(d.min()), float(d.max())
    norm = np.zeros(depth.shape, np.float32)
    norm[mask] = 1.0 - (depth[mask] - lo) / max(hi - lo, 1e-6)
    grey = np.clip(norm * 255.0 + 0.5, 0, 255).astype(np.uint8)
    col = cv2.applyColorMap(grey, cv2.COLORMAP_TURBO)[..., ::-1]
    out[mask] = col[mask]
    return out


def encode_normal(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Normal map RGB (H, W, 3) uint8 in the usual (x right, y up, z to viewer) convention."""
    rgb = np.zeros((*mask.shape, 3), np.uint8)
    n = normals[mask] * np.array([1.0, -1.0, -1.0], np.float32)
    rgb[mask] = np.clip((n + 1.0) * 127.5 + 0.5, 0, 255).astype(np.uint8)
    return rgb


def shade(normals: np.ndarray, mask: np.ndarray, n_lights: int = 3) -> np.ndarray:
    """Grey Lambertian shading (H, W) uint8 of camera-frame normals; background black."""
    if n_lights == 1:
        L, w = _HEADLIGHT, np.array([1.0 - AMBIENT])
    elif n_lights == 3:
        L, w = _THREE_LIGHTS, _THREE_WEIGHTS * (1.0 - AMBIENT) / _THREE_WEIGHTS.sum() * 1.3
    else:
        raise ConfigError(f"shading supports 1 or 3 lights, got {n_lights}")
    L = (L / np.linalg.norm(L, axis=1, keepdims=True)).astype(np.float32)
    sel = normals[mask].astype(np.float32, copy=False)
    lam = np.maximum(sel @ L.T, 0.0) @ w.astype(np.float32)
    out = np.zeros(mask.shape, np.uint8)
    out[mask] = (np.clip(AMBIENT + lam, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return out


def edge_map(depth: np.ndarray, normals: np.ndarray, mask: np.ndarray,
             crease_deg: float = 35.0, depth_jump: float = 0.02) -> np.ndarray:
    """Boolean (H, W) map of silhouette, occlusion (relative depth jump) and crease edges."""
    edges = np.zeros(mask.shape, bool)
    for dy, dx in ((0, 1), (1, 0)):
        a = (slice(0, mask.shape[0] - dy), slice(0, mask.shape[1] - dx))
        b = (slice(dy, None), slice(dx, None))
        ma, mb = mask[a], mask[b]
        sil = ma != mb
        both = ma & mb
        da, db = depth[a], depth[b]
        occ = both & (np.abs(da - db) > depth_jump * np.maximum(np.minimum(da, db), 1e-6))
        cos = np.einsum("ijk,ijk->ij", normals[a], normals[b])
        crease = both & (cos < np.cos(np.radians(crease_deg)))
        e = sil | occ | crease
        edges[a] |= e
        edges[b] |= e
    return edges


def encode(name: str, depth: np.ndarray, normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Encode one view with the named encoding; returns uint8 (H, W) or (H, W, 3)."""
    base, _, suffix = name.partition("_")
    if name not in ENCODINGS:
        raise ConfigError(f"unknown encoding {name!r}; known: {', '.join(ENCODINGS)}")
    if base == "depth":
        img = encode_depth(depth, mask)
    elif base == "normal":
        img = encode_normal(normals, mask)
    else:
        img = shade(normals, mask, n_lights=int(base[-1]))
    if suffix == "edges":
        e = edge_map(depth, normals, mask)
        thick = max(1, int(round(min(mask.shape) / 384)))
        if thick > 1:
            e = cv2.dilate(e.astype(np.uint8), np.ones((thick, thick), np.uint8)).astype(bool)
        img = img.copy()
        img[e] = 0
    return img
