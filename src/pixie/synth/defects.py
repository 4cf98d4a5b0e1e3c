"""Assembly defect operators: each returns a new :class:`Assembly` (its own mesh) in the target's frame.

Operators (``DEFECT_TYPES``):

missing   a part is left out (by default one that nothing rests on, never the base)
shifted   a part is misplaced: LEGO bricks by whole studs (8 mm), mechanical parts by a few mm
rotated   a part is mounted turned: bricks by 90 deg about their vertical axis (footprint swapped,
          kept on the grid), other parts by an angle about their own centre
wrong     a part is swapped for another of the same family (2x4 brick -> 2x2 / 1x4 / ..., a
          thicker / shorter cylinder, a different bracket)
extra     an additional part is mounted (a brick on top of the highest brick / a spare bolt)

The defective assembly records ``defect = {type, part, detail}``. Every operator is
deterministic given its ``rng``.
"""

from __future__ import annotations

import numpy as np

from pixie.geometry.collide import max_overlap_depth, part_solids
from pixie.geometry.rotations import rodrigues
from pixie.synth.assemblies import (
    Assembly,
    bracket_part,
    brick_part,
    cylinder_part,
    Part,
    plate_with_holes_part,
    shaft_part,
    STUD_PITCH,
)

DEFECT_TYPES = ("missing", "shifted", "rotated", "wrong", "extra")

__all__ = [
    "DEFECT_TYPES",
    "missing_part",
    "shifted_part",
    "rotated_part",
    "wrong_part",
    "extra_part",
    "apply_defect",
    "make_defects",
    "passes_through",
]


def _pick(asm: Assembly, rng: np.random.Generator, part: int | None, removable: bool = True) -> int:
    if part is not None:
        if not 0 <= part < len(asm.parts):
            raise IndexError(f"part {part} out of range (assembly has {len(asm.parts)} parts)")
        return int(part)
    cands = asm.removable_parts() if removable else list(range(1, len(asm.parts)))
    if not cands:
        cands = list(range(1, len(asm.parts)))
    if not cands:
        raise ValueError(f"assembly {asm.name!r} has no part besides its base")
    return int(cands[int(rng.integers(len(cands)))])


def missing_part(asm: Assembly, rng: np.random.Generator, part: int | None = None) -> Assembly:
    """Leave one part out."""
    k = _pick(asm, rng, part)
    out = asm.copy(name=f"{asm.name}_missing{k}")
    removed = out.parts.pop(k)
    out.defect = dict(type="missing", part=k, part_name=removed.name)
    return out


def shifted_part(asm: Assembly, rng: np.random.Generator, part: int | None = None, offset=None) -> Assembly:
    """Misplace one part: bricks move by 1-2 studs in x or y, other parts by 3-8 mm in the plane."""
    k = _pick(asm, rng, part)
    p = asm.parts[k]
    if offset is None:
        if p.kind == "brick":
            axis = int(rng.integers(2))
            step = float(rng.choice([-1, 1])) * STUD_PITCH * (1 if rng.random() < 0.75 else 2)
            offset = np.zeros(3)
            offset[axis] = step
        else:
            a = rng.uniform(0, 2 * np.pi)
            offset = np.array([np.cos(a), np.sin(a), 0.0]) * rng.uniform(3.0, 8.0)
    offset = np.asarray(offset, dtype=np.float64).reshape(3)
    out = asm.copy(name=f"{asm.name}_shifted{k}")
    out.parts[k].transform[:3, 3] += offset
    out.defect = dict(type="shifted", part=k, part_name=p.name, offset_mm=offset.round(4).tolist())
    return out


def _rot_about(T: np.ndarray, center: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    R = rodrigues(axis, angle)
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = center - R @ center
    return M @ T


def _turn_visible(p: Part) -> bool:
    if p.kind == "brick":
        return p.params["nx"] != p.params["ny"]
    return p.kind in ("bracket", "plate")


def rotated_part(asm: Assembly, rng: np.random.Generator, part: int | None = None, angle_deg: float | None = None) -> Assembly:
    """Mount one part turned about its vertical axis through its footprint centre.

    Non-square bricks turn by 90 deg (kept on the stud grid: the corner snaps to a whole stud);
    other parts by ``angle_deg`` (default: random 20-90 deg, either sign).
    """
    if part is None:  # parts whose turn changes the geometry (not cylinders, not square bricks)
        cands = [k for k in asm.removable_parts() if _turn_visible(asm.parts[k])]
        cands = cands or [k for k in range(1, len(asm.parts)) if _turn_visible(asm.parts[k])]
        if not cands:
            raise ValueError(f"assembly {asm.name!r} has no part whose rotation is visible")
        part = int(cands[int(rng.integers(len(cands)))])
    k = _pick(asm, rng, part)
    p = asm.parts[k]
    out = asm.copy(name=f"{asm.name}_rotated{k}")
    q = out.parts[k]
    lo, hi = p.bounds()
    c = 0.5 * (lo + hi)
    if p.kind == "brick" and angle_deg is None:
        angle = np.pi / 2
        T = _rot_about(p.transform, c, np.array([0.0, 0.0, 1.0]), angle)
        # Snap to the grid: the new lower corner on a whole stud (relative to the old one).
        v = p.mesh.vertices @ T[:3, :3].T + T[:3, 3]
        new_lo = v.min(0)
        d = (new_lo[:2] - lo[:2]) / STUD_PITCH
        T[:2, 3] += (np.round(d) - d) * STUD_PITCH
        q.transform = T
        angle_deg = 90.0
    else:
        if angle_deg is None:
            angle_deg = float(rng.uniform(20, 90) * rng.choice([-1, 1]))
        q.transform = _rot_about(p.transform, c, np.array([0.0, 0.0, 1.0]), np.radians(angle_deg))
    out.defect = dict(type="rotated", part=k, part_name=p.name, angle_deg=float(angle_deg))
    return out


def _substitute(p: Part, rng: np.random.Generator) -> Part:
    """A different part of the same family at the same place."""
    if p.kind == "brick":
        nx, ny, rot = p.params["nx"], p.params["ny"], p.params["rotated"]
        options = [(2, 4), (2, 2), (1, 4), (2, 3), (1, 2), (2, 6), (1, 6), (1, 3), (1, 1)]
        options = [o for o in options if o != (nx, ny) and o[0] * o[1] >= 2]
        nnx, nny = options[int(rng.integers(len(options)))]
        plates = p.params["plates"]
        if rng.random() < 0.25:  # a plate instead of a brick, or vice versa
            plates = 1 if plates == 3 else 3
        i, j, lvl = p.cell
        q = brick_part(nnx, nny, 0, 0, 0, plates=plates, rotated=rot, name=f"{p.name}_wrong{nnx}x{nny}")
        # Same lower corner as the original.
        q.transform = q.transform.copy()
        q.transform[:3, 3] += p.transform[:3, 3] - np.array([0.0, 0.0, 0.0]) - (
            brick_part(nx, ny, 0, 0, 0, rotated=rot).transform[:3, 3])
        q.cell = p.cell
        return q
    if p.kind == "cylinder":
        r, h = p.params["r"], p.params["h"]
        x, y, z = p.transform[:3, 3]
        if rng.random() < 0.5:
            r2, h2 = r * rng.uniform(1.3, 1.6), h
        else:
            r2, h2 = r, h * rng.uniform(0.55, 0.8)
        return cylinder_part(r2, h2, x, y, z, bore=p.params.get("bore", 0.0) * r2 / r, name=f"{p.name}_wrong")
    if p.kind == "shaft":
        x, y, z = p.transform[:3, 3]
        return shaft_part(p.params["r"], p.params["h"] * rng.uniform(1.4, 2.0), x, y, z, name=f"{p.name}_wrong")
    if p.kind == "bracket":
        pr = dict(p.params)
        pr["lz"] = pr["lz"] * rng.uniform(1.3, 1.6)
        pr["lx"] = pr["lx"] * rng.uniform(0.7, 0.9)
        return bracket_part(pr["lx"], pr["ly"], pr["lz"], pr["t"], pr["hole_r"], p.transform.copy(), name=f"{p.name}_wrong")
    if p.kind == "plate":
        pr = p.params
        q = plate_with_holes_part(pr["lx"] * rng.uniform(0.6, 0.85), pr["ly"], pr["t"] * 1.5,
                                  [h for h in pr["holes"] if h[0] < pr["lx"] * 0.6], T=p.transform.copy(),
                                  name=f"{p.name}_wrong")
        return q
    raise ValueError(f"no substitute for part kind {p.kind!r}")


def wrong_part(asm: Assembly, rng: np.random.Generator, part: int | None = None) -> Assembly:
    """Swap one part for a different one of the same family, mounted at the same place."""
    k = _pick(asm, rng, part)
    p = asm.parts[k]
    out = asm.copy(name=f"{asm.name}_wrong{k}")
    q = _substitute(p, rng)
    q.color_key = p.color_key
    out.parts[k] = q
    out.defect = dict(type="wrong", part=k, part_name=p.name, replacement=q.name, replacement_params=q.params)
    return out


def extra_part(asm: Assembly, rng: np.random.Generator) -> Assembly:
    """Mount one additional part: a small brick on top of a random top-level brick (LEGO), or a
    spare bolt / standoff on the base plate (mechanical)."""
    out = asm.copy(name=f"{asm.name}_extra")
    if asm.family == "lego":
        tops = [k for k in asm.removable_parts() if asm.parts[k].kind == "brick"] or [0]
        k = int(tops[int(rng.integers(len(tops)))])
        p = asm.parts[k]
        lo, hi = p.bounds()
        h_body = (p.params["plates"] * 3.2)
        fx, fy = p.params["fx"], p.params["fy"]
        nx, ny = (1, 2) if rng.random() < 0.5 else (2, 2)
        nx, ny = min(nx, fx), min(ny, fy)
        rot = bool(rng.random() < 0.5) and nx != ny and ny <= fx and nx <= fy
        ex, ey = (ny, nx) if rot else (nx, ny)
        di, dj = int(rng.integers(0, fx - ex + 1)), int(rng.integers(0, fy - ey + 1))
        q = brick_part(nx, ny, 0, 0, 0, rotated=rot, name=f"extra{nx}x{ny}")
        corner = p.transform[:3, 3] - brick_part(p.params["nx"], p.params["ny"], 0, 0, 0, rotated=p.params["rotated"]).transform[:3, 3]
        q.transform[:3, 3] += corner + np.array([di * STUD_PITCH, dj * STUD_PITCH, h_body])
        detail = dict(on_part=k)
    else:
        base = asm.parts[0]
        lo, hi = base.bounds()
        x = float(rng.uniform(lo[0] + 0.3 * (hi[0] - lo[0]), lo[0] + 0.7 * (hi[0] - lo[0])))
        y = float(rng.uniform(lo[1] + 0.15 * (hi[1] - lo[1]), lo[1] + 0.4 * (hi[1] - lo[1])))
        q = cylinder_part(float(rng.uniform(3, 5)), float(rng.uniform(10, 18)), x, y, float(hi[2]), name="extra_standoff")
        detail = dict(on_part=0)
    q.color_key = f"extra{len(out.parts)}"
    out.parts.append(q)
    out.defect = dict(type="extra", part=len(out.parts) - 1, part_name=q.name, **detail)
    return out


_OPS = {
    "missing": missing_part,
    "shifted": shifted_part,
    "rotated": rotated_part,
    "wrong": wrong_part,
    "extra": lambda asm, rng, part=None: extra_part(asm, rng),
}


def apply_defect(asm: Assembly, kind: str, rng: np.random.Generator, part: int | None = None) -> Assembly:
    if kind not in _OPS:
        raise ValueError(f"unknown defect {kind!r}; use one of {DEFECT_TYPES}")
    return _OPS[kind](asm, rng, part)


def passes_through(asm: Assembly, tolerance: float) -> bool:
    """Whether two parts of ``asm`` overlap deeper than ``tolerance`` mm (:mod:`pixie.geometry.collide`): a part
    moved into its neighbour, which no physical assembly can show."""
    return len(asm.parts) > 1 and max_overlap_depth(part_solids(asm.to_parts_mesh())) > tolerance


def make_defects(asm: Assembly, n: int, seed: int, types=DEFECT_TYPES, compound: float = 0.0,
                 physical: bool = True) -> list[Assembly]:
    """``n`` defective variants of ``asm``, cycling through ``types`` (shuffled by ``seed``).

    With probability ``compound`` a variant gets a second defect of another type (stronger
    deviations; its ``defect`` is ``{type: 'a+b', steps: [first, second]}``). Variants whose mesh
    equals an earlier one (e.g. a symmetric part rotated) are redrawn, and with ``physical`` those in which a
    part passes into another deeper than the target's own overlaps allow (a brick shifted into its neighbour:
    :attr:`pixie.geometry.collide.PartSolids.tolerance`).
    """
    tolerance = part_solids(asm.to_parts_mesh()).tolerance if physical and len(asm.parts) > 1 else np.inf
    rng = np.random.default_rng(seed)
    order = list(types)
    rng.shuffle(order)
    out: list[Assembly] = []
    seen = {_signature(asm)}
    attempts = 0
    while len(out) < n and attempts < 20 * max(n, 1):
        kind = order[attempts % len(order)]
        attempts += 1
        try:
            d = apply_defect(asm, kind, rng)
            if compound > 0 and rng.random() < compound:
                kind2 = [t for t in order if t != kind][int(rng.integers(len(order) - 1))]
                first = d.defect
                d = apply_defect(d, kind2, rng)
                d.defect = dict(type=f"{kind}+{kind2}", part=first.get("part"), steps=[first, d.defect])
                kind = f"{kind}+{kind2}"
        except ValueError:
            continue
        sig = _signature(d)
        if sig in seen:
            continue
        if kind != "missing" and passes_through(d, tolerance):
            continue
        seen.add(sig)
        d.name = f"{asm.name}_d{len(out) + 1}_{kind}"
        out.append(d)
    return out


def _signature(asm: Assembly) -> tuple:
    """Order-free fingerprint of the placed geometry (bounding boxes of the parts, rounded)."""
    sig = []
    for p in asm.parts:
        lo, hi = p.bounds()
        sig.append(tuple(np.round(np.concatenate([lo, hi]), 2)) + (p.mesh.name, round(float(p.mesh.vertices.sum()), 2)))
    return tuple(sorted(sig))
