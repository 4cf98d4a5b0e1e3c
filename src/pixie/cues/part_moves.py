"""What a part of an assembly shows in a render, and what a change to it would show: the contour pixels of every
part (silhouette, depth steps, seams, creases) and the 3D move search of the part report (:mod:`pixie.cues.parts`).

A misplaced part is usually moved along the model's axes or turned about one of them (:func:`part_moves`). Each
move is rendered by compositing the part, moved, with the model without it; where the moved assembly's contour
differs from the CAD one's and from the part's absence, the photo's edges say which hypothesis they support
(:func:`move_evidence`). Two parts whose moves change the same pixels are compared with each other
(:func:`explain_away`), so a neighbour uncovered by a moved brick is not blamed for it.

>>> fit = move_evidence(pe, T, k, complements[k], part_renderers[k], part_moves(mesh, k))
>>> fit.name, fit.gain                               # e.g. '+y 7.9 mm', 0.62
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from pixie.cues.edge_align import edge_distances
from pixie.cues.edge_photo import PhotoEdges
from pixie.geometry.camera import project, transform_points
from pixie.geometry.mesh import Mesh, from_arrays
from pixie.geometry.render import RenderResult, Renderer
from pixie.geometry.rotations import rodrigues
from pixie.references.templates import edge_map

__all__ = ["Contour", "MoveFit", "part_contours", "contours_of_maps", "near_maps", "explained", "coarse_pixels",
           "part_moves", "part_resizes", "resize_factor", "of_factors", "is_rigid", "move_evidence", "explain_away"]


def _bin_pixel(xy: np.ndarray, ori: np.ndarray, shape: tuple[int, int], n_bins: int) -> tuple[np.ndarray, ...]:
    """Orientation bin (of ``n_bins`` over [0, pi)), row and column of each contour pixel, clipped to ``shape``."""
    b = np.floor(np.mod(ori, np.pi) / np.pi * n_bins).astype(int) % n_bins
    x = np.clip(np.rint(xy[:, 0]).astype(int), 0, shape[1] - 1)
    y = np.clip(np.rint(xy[:, 1]).astype(int), 0, shape[0] - 1)
    return b, y, x


def near_maps(xy: np.ndarray, ori: np.ndarray, shape: tuple[int, int], n_bins: int = 8,
              radius: int = 1) -> np.ndarray:
    """(n_bins, H, W) bool: a contour pixel of orientation bin b (or b ± 1) lies within ``radius`` px (a square of
    side 2 radius + 1)."""
    maps = np.zeros((n_bins,) + tuple(shape), np.uint8)
    if len(xy):
        maps[_bin_pixel(xy, ori, shape, n_bins)] = 1
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    dil = np.stack([cv2.dilate(m, k) for m in maps]).astype(bool)
    return dil | np.roll(dil, 1, axis=0) | np.roll(dil, -1, axis=0)


def explained(xy: np.ndarray, ori: np.ndarray, near: np.ndarray) -> np.ndarray:
    """Which contour pixels (xy, ori) another contour (its :func:`near_maps`) also has."""
    if not len(xy):
        return np.zeros(0, bool)
    return near[_bin_pixel(xy, ori, near.shape[1:], near.shape[0])]


def part_contours(r: RenderResult, face_parts: np.ndarray, crease_deg: float = 35.0, depth_jump: float = 0.01,
                  step_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Contour pixels of every part in one render.

    A depth step (one surface in front of another) counts when the far side is more than ``depth_jump`` of the
    depth and more than ``step_mm`` farther: a LEGO stud's rim (1.7 mm) is not a step at ``step_mm`` 5, a brick on
    a brick is.

    Returns
    -------
    xy : (N, 2) float pixel centres; ori : (N,) unsigned edge orientation (radians, [0, pi));
    part : (N,) part index of each pixel; part_map : (H, W) int part index per pixel (-1 background);
    kind : (N,) 0 silhouette, 1 depth step where the part is in front, 2 seam with another part, 3 crease
    """
    part_map = np.where(r.tri_ids >= 0, face_parts[np.maximum(r.tri_ids, 0)], -1).astype(np.int32)
    return contours_of_maps(r.depth, r.normals, part_map, crease_deg, depth_jump, step_mm)


def contours_of_maps(depth: np.ndarray, normals: np.ndarray, part_map: np.ndarray, crease_deg: float = 35.0,
                     depth_jump: float = 0.01, step_mm: float = 0.0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`part_contours` of a render given as its depth, normals and part index per pixel (-1 background):
    also of a composite render, e.g. the model with one part moved (:func:`move_evidence`)."""
    part_map = np.asarray(part_map, np.int32)
    obj = part_map >= 0
    depth = np.asarray(depth, np.float32)
    sil, crease, ori, _ = edge_map(depth, normals, crease_deg, depth_jump)
    # the far side of a depth step is the occluded part: the edge is the near part's
    big = np.float32(1e9)
    dmin = cv2.erode(np.where(obj, depth, big), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                     borderValue=float(big))
    jump = np.maximum(depth_jump * depth, np.float32(step_mm))
    far = obj & (depth - dmin > jump)
    # seams: a 4-neighbour of another part at about the same depth
    seam = np.zeros_like(obj)
    H, W = obj.shape
    for dy, dx in ((0, 1), (1, 0)):
        a = (slice(0, H - dy), slice(0, W - dx))
        b = (slice(dy, H), slice(dx, W))
        s = obj[a] & obj[b] & (part_map[a] != part_map[b])
        seam[a] |= s
        seam[b] |= s
    # kinds: 0 silhouette, 1 depth step (the near side), 2 seam, 3 crease inside the part
    step = crease & (depth - dmin <= jump) & _near_step(depth, obj, jump)
    kind_map = np.full(obj.shape, -1, np.int8)
    kind_map[crease] = 3
    kind_map[seam] = 2
    kind_map[step] = 1
    kind_map[sil] = 0
    edges = (sil | crease | seam) & ~far & obj
    # orientation: the part indicator's gradient on the part's outline (silhouette, steps, seams), the render's
    # own edge orientation on creases inside a part
    ori_out = ori.astype(np.float64).copy()
    for k in np.unique(part_map[edges]):
        ind = cv2.GaussianBlur((part_map == k).astype(np.float32), (0, 0), 1.0)
        gx = cv2.Sobel(ind, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(ind, cv2.CV_32F, 0, 1, ksize=3)
        on = edges & (part_map == k) & (np.hypot(gx, gy) > 0.1)
        ori_out[on] = np.mod(np.arctan2(gy[on], gx[on]), np.pi)
    ys, xs = np.nonzero(edges)
    return (np.stack([xs, ys], 1).astype(np.float64), ori_out[ys, xs], part_map[ys, xs].astype(np.int64), part_map,
            kind_map[ys, xs])


def _near_step(depth: np.ndarray, obj: np.ndarray, jump: np.ndarray) -> np.ndarray:
    """Pixels with a neighbour (3 x 3) farther by more than ``jump`` (per pixel, mm), or background."""
    dmax = cv2.dilate(np.where(obj, depth, np.float32(1e9)), np.ones((3, 3), np.uint8),
                      borderType=cv2.BORDER_CONSTANT, borderValue=1e9)
    return obj & (dmax - depth > jump)


def coarse_pixels(xy: np.ndarray, sel: np.ndarray, shape: tuple[int, int], detail_px: float) -> np.ndarray:
    """``sel`` without the contour pixels of small pieces: of the pixels ``xy[sel]``, the 8-connected components
    whose bounding box is under ``detail_px`` on its longer side are dropped (a LEGO stud's rim, a screw head: detail
    the photo does not resolve at this scale). ``detail_px`` <= 0 keeps every pixel.

    Parameters
    ----------
    xy : (N, 2) pixel centres (x, y) of a contour; sel : (N,) bool, the pixels considered
    shape : (H, W) of the image the pixels lie in; detail_px : the smallest piece kept, px

    Returns
    -------
    (N,) bool: ``sel`` and in a component at least ``detail_px`` across
    """
    sel = np.asarray(sel, bool)
    if detail_px <= 0 or not sel.any():
        return sel
    H, W = shape
    x = np.clip(np.rint(xy[:, 0]).astype(int), 0, W - 1)
    y = np.clip(np.rint(xy[:, 1]).astype(int), 0, H - 1)
    m = np.zeros((H, W), np.uint8)
    m[y[sel], x[sel]] = 1
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    big = np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]) >= detail_px
    big[0] = False  # the background label
    return sel & big[lab[y, x]]


def part_moves(mesh: Mesh, k: int, fractions=(1 / 6, 1 / 4, 1 / 3, 1 / 2, 1.0), angles_deg=(90.0, 180.0, 270.0),
               min_mm: float = 1.0, same_mm: float = 0.5) -> list[tuple[str, np.ndarray]]:
    """Rigid 3D moves of part ``k`` that a wrong assembly could have made, in the object frame (``X' = M X``).

    Translations along the model's axes by ``fractions`` of the part's own extent along that axis (both signs;
    none shorter than ``min_mm``; the fractions hold a whole pitch of a part made of 1-6 equal cells, e.g. studs
    or holes), and turns by ``angles_deg`` about the model's axes through the centre of the
    part's bounding box. CAD assemblies are modelled on their axes, so a misplaced part is usually moved along
    them (a brick by a stud, a plate along its slot) or turned about one of them. A move that maps the part onto
    itself (every moved vertex within ``same_mm`` of a vertex: a square brick turned by 90°, a bolt about its axis)
    cannot be seen and is left out.

    Returns
    -------
    list of (description, (4, 4) M)
    """
    faces = mesh.faces[np.asarray(mesh.face_parts) == k]
    if not len(faces):
        return []
    V = mesh.vertices[np.unique(faces)]
    lo, hi = V.min(axis=0), V.max(axis=0)
    c, ext = 0.5 * (lo + hi), hi - lo
    from scipy.spatial import cKDTree

    tree = cKDTree(V)

    def visible_change(M: np.ndarray) -> bool:
        d, _ = tree.query(V @ M[:3, :3].T + M[:3, 3], distance_upper_bound=same_mm)
        return bool(np.isinf(d).any())

    out: list[tuple[str, np.ndarray]] = []
    for a, name in enumerate("xyz"):
        for d in sorted({round(float(f * ext[a]), 3) for f in fractions}):
            if d < min_mm:
                continue
            for sign in (1.0, -1.0):
                M = np.eye(4)
                M[a, 3] = sign * d
                out.append((f"{'+' if sign > 0 else '-'}{name} {d:.1f} mm", M))
        axis = np.eye(3)[a]
        for ang in angles_deg:
            R = rodrigues(axis, np.radians(ang))
            M = np.eye(4)
            M[:3, :3] = R
            M[:3, 3] = c - R @ c
            if visible_change(M):
                out.append((f"turned {ang:.0f} deg about {name}", M))
    return out


# only longer: a part shortened at one end looks like one whose end is hidden (an occluder, a neighbour), and on the
# defects benchmark shrinks flagged correct assemblies as often as wrong parts (bench/RESULTS.md, session 34)
RESIZE_FACTORS = (1.5, 2.0, 3.0)  # a stud row more, a longer bolt, a brick for a plate


def part_resizes(mesh: Mesh, k: int, factors=RESIZE_FACTORS, min_mm: float = 1.0) -> list[tuple[str, np.ndarray]]:
    """Part ``k`` made longer or shorter along one of the model's axes, one end kept: the wrong part of a family
    mounted where the CAD one goes (a longer bolt in the same hole, a 2x6 brick for a 2x4, a plate for a brick).

    Each is an affine map of the object frame (``X' = A X``): the part scaled by a factor of ``factors`` along axis
    x, y or z, its bounding box's low or high end along that axis fixed. A resize that moves the free end by less
    than ``min_mm`` is left out.

    Returns
    -------
    list of (description, (4, 4) A), e.g. ('1.5x as long along z, low end kept', A)
    """
    faces = mesh.faces[np.asarray(mesh.face_parts) == k]
    if not len(faces):
        return []
    V = mesh.vertices[np.unique(faces)]
    lo, hi = V.min(axis=0), V.max(axis=0)
    out: list[tuple[str, np.ndarray]] = []
    for a, name in enumerate("xyz"):
        ext = hi[a] - lo[a]
        for s in factors:
            if abs(s - 1.0) * ext < min_mm:
                continue
            for end, fixed in (("low", lo[a]), ("high", hi[a])):
                A = np.eye(4)
                A[a, a] = s
                A[a, 3] = fixed * (1.0 - s)
                out.append((f"{s:.2g}x as long along {name}, {end} end kept", A))
    return out


def resize_factor(name: str) -> float:
    """The length factor of a resize :func:`part_resizes` named ('1.5x as long along z, low end kept' -> 1.5)."""
    return float(name.split("x as long")[0])


def of_factors(gains: dict[str, float], factors) -> dict[str, float]:
    """The resizes of ``gains`` (name -> gain, as :func:`part_resizes` names them) whose length factor is one of
    ``factors`` (compared to 2 digits, as the names give them)."""
    fs = [float(f"{f:.2g}") for f in factors]
    return {n: g for n, g in gains.items() if any(np.isclose(resize_factor(n), f) for f in fs)}


def is_rigid(M: np.ndarray, tol: float = 1e-6) -> bool:
    """Whether the (4, 4) map ``M`` is a rigid motion (its 3 x 3 block a rotation), not a resize."""
    R = np.asarray(M, np.float64)[:3, :3]
    return bool(np.allclose(R.T @ R, np.eye(3), atol=tol) and np.linalg.det(R) > 0)


def _render_moved(part: Renderer, T: np.ndarray, M: np.ndarray, K: np.ndarray, size: int) -> RenderResult:
    """The part alone at ``T M``: a rigid ``M`` moves the pose, a resize (:func:`part_resizes`) the vertices (a
    renderer of the resized part, so that its normals are the resized surface's)."""
    if is_rigid(M):
        return part.render(T @ M, K, size, size)
    V = part.mesh.vertices @ M[:3, :3].T + M[:3, 3]
    return Renderer(from_arrays(V, part.mesh.faces, name=f"{part.mesh.name}:resized"),
                    smooth_normals=part.smooth_normals).render(T, K, size, size)


def _composite(rc: RenderResult, pc: np.ndarray, rp: RenderResult, k: int) -> tuple[np.ndarray, ...]:
    """Depth, normals and part map of the model without part ``k`` (``rc``, its part map ``pc``) with the part
    rendered on its own (``rp``, possibly moved) put back in front where it is nearer."""
    front = rp.mask & (~rc.mask | (rp.depth < rc.depth))
    return (np.where(front, rp.depth, rc.depth), np.where(front[..., None], rp.normals, rc.normals),
            np.where(front, k, pc))


@dataclass(kw_only=True)
class Contour:
    """The visible contour pixels of one hypothesis of the assembly (crop px), their orientations, whether a photo
    edge supports each, and their :func:`near_maps` (for comparing hypotheses)."""

    xy: np.ndarray
    ori: np.ndarray
    hit: np.ndarray
    near: np.ndarray
    roi: tuple[int, int, int, int]  # (x0, y0, x1, y1): the pixels it was taken from; outside them it says nothing


@dataclass(kw_only=True)
class MoveFit:
    """The best 3D move of one part (:func:`move_evidence`)."""

    gain: float  # the evidence for the moved assembly over the CAD one and over the part's absence (the smaller)
    name: str  # the move in words
    M: np.ndarray  # (4, 4) the move in the object frame
    support: float  # the support of the moved assembly's own contour pixels (where it differs from the CAD one)
    contour: Contour  # the moved assembly's contour
    changed: np.ndarray  # (H, W) bool: where the moved and the CAD assembly's contours differ
    gains: dict[str, float] = field(default_factory=dict)  # every judged move's gain by name (the best one's included)


ROI_MARGIN = 12  # px around a part's reach: more than the edge filters' (8) and the near maps' (1) reach


def _move_roi(V: np.ndarray, pe: PhotoEdges, poses: list[np.ndarray], margin: int) -> tuple[int, int, int, int]:
    """The crop pixels the part (its vertices ``V``) can cover at any of ``poses`` (projected box) + ``margin``."""
    lo, hi = np.array([np.inf, np.inf]), np.array([-np.inf, -np.inf])
    for P in poses:
        uv = project(pe.K, transform_points(P, V))
        lo, hi = np.minimum(lo, uv.min(axis=0)), np.maximum(hi, uv.max(axis=0))
    x0, y0 = (int(np.clip(np.floor(v) - margin, 0, pe.size)) for v in lo)
    x1, y1 = (int(np.clip(np.ceil(v) + margin + 1, 0, pe.size)) for v in hi)
    return x0, y0, max(x1, x0), max(y1, y0)


def _within(c: Contour, roi: tuple[int, int, int, int], shape: tuple[int, int]) -> Contour:
    """``c`` restricted to the pixels of ``roi``."""
    x0, y0, x1, y1 = roi
    m = (c.xy[:, 0] >= x0) & (c.xy[:, 0] < x1) & (c.xy[:, 1] >= y0) & (c.xy[:, 1] < y1)
    return Contour(xy=c.xy[m], ori=c.ori[m], hit=c.hit[m], near=near_maps(c.xy[m], c.ori[m], shape), roi=roi)


def _versus(a: Contour, b: Contour, min_points: int) -> float | None:
    """The evidence for hypothesis ``a`` over ``b`` on the pixels where their contours differ: each own pixel of
    ``a`` counts +1 when a photo edge supports it and -1 when none does, each own pixel of ``b`` the opposite, over
    the number of those pixels (the difference of the two supports when both have as many). None when fewer than
    ``min_points`` pixels differ."""
    own_a, own_b = ~explained(a.xy, a.ori, b.near), ~explained(b.xy, b.ori, a.near)
    n = int(own_a.sum() + own_b.sum())
    if n < min_points:
        return None
    return float((np.sum(2.0 * a.hit[own_a] - 1.0) - np.sum(2.0 * b.hit[own_b] - 1.0)) / n)


def move_evidence(pe: PhotoEdges, T: np.ndarray, k: int, complement: tuple[Renderer, np.ndarray], part: Renderer,
                  moves: list[tuple[str, np.ndarray]], *, fit_px: float = 1.5, max_bin_gap: int = 1, kinds=(0, 1, 2),
                  step_mm: float = 0.0, min_points: int = 12, min_changed: int = 12,
                  min_px: float = 4.0) -> MoveFit | None:
    """How much better the photo's edges support part ``k`` moved by one of ``moves`` than where the model has it.

    The model without the part (``complement``) is rendered at ``T`` once; the part alone (``part``) at ``T M``
    for each move and at ``T``, each composited with it. Where two hypotheses' contours differ (pixels of one
    that the other lacks, within 1 px and ±1 of 8 orientation bins; visible in the allowed region), the share of
    pixels supported by a same-orientation photo edge is compared (:func:`_versus`): the moved assembly against
    the CAD one, and against the model without the part (the part absent). The gain is the smaller of the two:
    a present part loses by moving (its edges are where the model has it), a missing one gains against the CAD
    position but not against its absence (what a move would hide is there to see), a moved part gains against
    both; the other parts' contours cancel out. A move is not judged when it shifts no vertex of the part by
    ``min_px`` crop px (too small to tell from the pose's own error) or changes fewer than ``min_changed``
    contour pixels either way. ``moves`` may also be resizes (:func:`part_resizes`): the part is then rendered
    resized, at ``T``.

    Returns
    -------
    :class:`MoveFit` of the best move; None when no move changes ``min_points`` pixels in view.
    """
    cren, cparts = complement
    rc = cren.render(T, pe.K, pe.size, pe.size)
    pc = np.where(rc.tri_ids >= 0, np.asarray(cparts)[np.maximum(rc.tri_ids, 0)], -1)  # its part map, once
    shape = (pe.size, pe.size)
    T = np.asarray(T, np.float64)
    V = part.mesh.vertices[np.unique(part.mesh.faces)]
    x0, y0, x1, y1 = _move_roi(V, pe, [T] + [T @ M for _, M in moves], ROI_MARGIN)
    uv0 = project(pe.K, transform_points(T, V))

    def contour(Mp: np.ndarray | None) -> Contour:
        if Mp is None:  # the part absent: the model without it alone
            d, n, pm = rc.depth, rc.normals, pc
        else:
            d, n, pm = _composite(rc, pc, _render_moved(part, T, Mp, pe.K, pe.size), k)
        # only where the hypotheses can differ (the part's reach): elsewhere all contours are the same and cancel
        xy, ori, _, _, kind = contours_of_maps(d[y0:y1, x0:x1], n[y0:y1, x0:x1], pm[y0:y1, x0:x1], step_mm=step_mm)
        keep = np.isin(kind, np.asarray(kinds))
        xy, ori = xy[keep] + np.array([x0, y0], np.float64), ori[keep]
        dist, inside = edge_distances(pe, xy, ori, max_bin_gap, fit_px) if len(xy) else (np.zeros(0), np.zeros(0, bool))
        xy, ori = xy[inside], ori[inside]
        return Contour(xy=xy, ori=ori, hit=dist[inside] <= fit_px, near=near_maps(xy, ori, shape),
                       roi=(x0, y0, x1, y1))

    cad, absent = contour(np.eye(4)), contour(None)
    if len(cad.xy) < min_points:
        return None
    best: MoveFit | None = None
    gains: dict[str, float] = {}
    for name, M in moves:
        if np.max(np.linalg.norm(project(pe.K, transform_points(T @ M, V)) - uv0, axis=1)) < min_px:
            continue
        c = contour(M)
        g0, ga = _versus(c, cad, min_changed), _versus(c, absent, min_changed)
        if g0 is None or ga is None:  # the move changes (next to) nothing in view
            continue
        gain = min(g0, ga)
        gains[name] = gain
        if best is None or gain > best.gain:
            own = ~explained(c.xy, c.ori, cad.near)
            changed = np.zeros(shape, bool)
            for xy in (c.xy[own], cad.xy[~explained(cad.xy, cad.ori, c.near)]):
                changed[_bin_pixel(xy, np.zeros(len(xy)), shape, 1)[1:]] = True
            best = MoveFit(gain=gain, name=name, M=M, support=float(c.hit[own].mean()) if own.any() else 0.0,
                           contour=c, changed=changed)
    if best is not None:
        best.gains = gains
    return best


def explain_away(fits: dict[int, MoveFit], min_points: int = 12, reach_px: int = 4) -> dict[int, int]:
    """For parts whose best moves change overlapping parts of the image (within ``reach_px``), which one the photo
    supports better: the moved assemblies are compared with each other (:func:`_versus`, where both were taken).
    Returns {part: the part whose move explains its evidence better}, for the losers only; parts whose changes do
    not touch stay independent (two defects)."""
    k3 = np.ones((2 * reach_px + 1, 2 * reach_px + 1), np.uint8)
    grown = {k: cv2.dilate(f.changed.astype(np.uint8), k3) > 0 for k, f in fits.items()}
    out: dict[int, int] = {}
    keys = sorted(fits, key=lambda k: -fits[k].gain)
    for i, a in enumerate(keys):
        for b in keys[i + 1:]:
            if not (grown[a] & fits[b].changed).any():
                continue
            ra, rb = fits[a].contour.roi, fits[b].contour.roi
            roi = (max(ra[0], rb[0]), max(ra[1], rb[1]), min(ra[2], rb[2]), min(ra[3], rb[3]))
            if roi[2] <= roi[0] or roi[3] <= roi[1]:
                continue
            shape = fits[a].changed.shape
            v = _versus(_within(fits[a].contour, roi, shape), _within(fits[b].contour, roi, shape), min_points)
            if v is None:
                continue
            loser, winner = (b, a) if v >= 0 else (a, b)
            out.setdefault(loser, winner)
    return out
