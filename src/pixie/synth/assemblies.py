"""Procedural target assemblies: LEGO-like bricks on a stud grid and simple mechanical parts.

Units are millimetres. LEGO-like parts follow the real grid: 8 mm stud pitch, 9.6 mm brick
height (3.2 mm plates), studs 4.8 mm across and 1.7 mm tall; each brick is 0.1 mm smaller than
its grid cell on every side (as real bricks, which also keeps neighbours from sharing faces).
Mechanical parts (plates with holes, cylinders / standoffs, L-brackets, shafts) are built with
manifold3d booleans.

An :class:`Assembly` is a list of :class:`Part` (local mesh + placement + name); its
:meth:`Assembly.to_mesh` is the boolean union of the placed parts (a closed solid, so voxel
IoU3D works) together with the part index of every output triangle (for per-part colours).
Everything is deterministic given a seed.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace

import numpy as np

from pixie.geometry.mesh import Mesh, from_arrays

STUD_PITCH = 8.0
BRICK_H = 9.6
PLATE_H = 3.2
STUD_D = 4.8
STUD_H = 1.7
GAP = 0.1  # per side
STUD_SEGMENTS = 20

__all__ = [
    "STUD_PITCH",
    "BRICK_H",
    "PLATE_H",
    "Part",
    "Assembly",
    "brick_part",
    "plate_with_holes_part",
    "cylinder_part",
    "bracket_part",
    "shaft_part",
    "lego_assembly",
    "mechanical_assembly",
    "make_target_assembly",
    "make_target_assemblies",
    "LEGO_COLORS",
    "part_palette",
]


# --------------------------------------------------------------------------- manifold helpers


def _mf():
    import manifold3d

    return manifold3d


def manifold_to_mesh(solid, name: str) -> Mesh:
    out = solid.to_mesh()
    v = np.asarray(out.vert_properties, dtype=np.float64)[:, :3]
    return from_arrays(v, np.asarray(out.tri_verts, dtype=np.int64), name=name)


def mesh_to_manifold(mesh: Mesh, T: np.ndarray | None = None):
    mf = _mf()
    v = mesh.vertices if T is None else mesh.vertices @ T[:3, :3].T + T[:3, 3]
    m = mf.Mesh(
        vert_properties=np.ascontiguousarray(v, dtype=np.float32),
        tri_verts=np.ascontiguousarray(mesh.faces, dtype=np.uint32),
    )
    solid = mf.Manifold(m)
    if solid.is_empty():
        raise ValueError(f"mesh {mesh.name!r} is not a closed manifold solid")
    return solid


def _box(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return _mf().Manifold.cube(list(hi - lo)).translate(list(lo))


def _cyl(r: float, h: float, x: float = 0.0, y: float = 0.0, z: float = 0.0, seg: int = 24, axis: str = "z"):
    c = _mf().Manifold.cylinder(h, r, r, seg)
    if axis == "x":
        c = c.rotate([0.0, 90.0, 0.0])
    elif axis == "y":
        c = c.rotate([-90.0, 0.0, 0.0])
    return c.translate([x, y, z])


# --------------------------------------------------------------------------- parts


@dataclass
class Part:
    """One rigid part: a mesh in its own frame, placed by ``transform`` (assembly from part), mm.

    ``kind`` and ``params`` describe the part family (used by the wrong-part defect);
    ``cell`` is the LEGO grid position (i, j, level) of its lower corner, when on the grid.
    """

    mesh: Mesh
    transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    name: str = "part"
    kind: str = "generic"
    params: dict = field(default_factory=dict)
    cell: tuple[int, int, int] | None = None
    color_key: str = ""

    def placed_vertices(self) -> np.ndarray:
        T = self.transform
        return self.mesh.vertices @ T[:3, :3].T + T[:3, 3]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        v = self.placed_vertices()
        return v.min(0), v.max(0)

    def volume(self) -> float:
        return float(mesh_to_manifold(self.mesh).volume())


@functools.lru_cache(maxsize=256)
def _brick_mesh(nx: int, ny: int, plates: int, studs: bool) -> Mesh:
    h = PLATE_H * plates
    body = _box([GAP, GAP, 0.0], [nx * STUD_PITCH - GAP, ny * STUD_PITCH - GAP, h])
    parts = [body]
    if studs:
        for i in range(nx):
            for j in range(ny):
                parts.append(_cyl(STUD_D / 2, STUD_H + 0.05, (i + 0.5) * STUD_PITCH, (j + 0.5) * STUD_PITCH,
                                  h - 0.05, seg=STUD_SEGMENTS))
    solid = _mf().Manifold.batch_boolean(parts, _mf().OpType.Add) if len(parts) > 1 else body
    return manifold_to_mesh(solid, f"brick{nx}x{ny}" + ("" if plates == 3 else f"_p{plates}"))


def brick_part(nx: int, ny: int, i: int, j: int, level: float, plates: int = 3, studs: bool = True,
               rotated: bool = False, name: str = "") -> Part:
    """A LEGO-like brick of nx x ny studs with its lower corner on grid cell (i, j) and its base at
    height ``level`` plates (``level * 3.2`` mm). ``rotated`` swaps the footprint (90 deg)."""
    mesh = _brick_mesh(int(nx), int(ny), int(plates), bool(studs))
    T = np.eye(4)
    if rotated:  # rotate 90 deg about z, keeping the lower corner on the grid
        T[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        T[0, 3] = ny * STUD_PITCH
    T[:3, 3] += [i * STUD_PITCH, j * STUD_PITCH, level * PLATE_H]
    fx, fy = (ny, nx) if rotated else (nx, ny)
    return Part(mesh, T, name or f"brick{nx}x{ny}", kind="brick",
                params=dict(nx=int(nx), ny=int(ny), plates=int(plates), studs=bool(studs), rotated=bool(rotated),
                            fx=int(fx), fy=int(fy)),
                cell=(int(i), int(j), int(level)))


@functools.lru_cache(maxsize=64)
def _plate_holes_mesh(lx: float, ly: float, t: float, holes: tuple) -> Mesh:
    solid = _box([0, 0, 0], [lx, ly, t])
    for x, y, r in holes:
        solid = solid - _cyl(r, t + 2.0, x, y, -1.0, seg=24)
    return manifold_to_mesh(solid, f"plate{lx:g}x{ly:g}")


def plate_with_holes_part(lx: float, ly: float, t: float, holes, T: np.ndarray | None = None, name: str = "plate") -> Part:
    holes = tuple((float(x), float(y), float(r)) for x, y, r in holes)
    return Part(_plate_holes_mesh(float(lx), float(ly), float(t), holes), np.eye(4) if T is None else T, name,
                kind="plate", params=dict(lx=lx, ly=ly, t=t, holes=[list(h) for h in holes]))


@functools.lru_cache(maxsize=64)
def _cylinder_mesh(r: float, h: float, bore: float, seg: int) -> Mesh:
    solid = _cyl(r, h, seg=seg)
    if bore > 0:
        solid = solid - _cyl(bore, h + 2.0, z=-1.0, seg=seg)
    return manifold_to_mesh(solid, f"cyl{r:g}x{h:g}")


def cylinder_part(r: float, h: float, x: float, y: float, z: float, bore: float = 0.0, name: str = "cylinder",
                  seg: int = 28) -> Part:
    """A vertical cylinder (optionally a tube with a bore) standing at (x, y, z)."""
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return Part(_cylinder_mesh(float(r), float(h), float(bore), int(seg)), T, name, kind="cylinder",
                params=dict(r=float(r), h=float(h), bore=float(bore)))


@functools.lru_cache(maxsize=64)
def _bracket_mesh(lx: float, ly: float, lz: float, t: float, hole_r: float) -> Mesh:
    base = _box([0, 0, 0], [lx, ly, t])
    wall = _box([0, 0, 0], [t, ly, lz])
    solid = base + wall
    if hole_r > 0:
        solid = solid - _cyl(hole_r, t + 2, lx * 0.62, ly / 2, -1.0)
        solid = solid - _cyl(hole_r, t + 2, -1.0, ly / 2, lz * 0.62, axis="x")
    # A gusset makes the bracket asymmetric and recognisable.
    g = _mf().Manifold.hull_points([[t, ly / 2 - t / 2, t], [t + lx * 0.35, ly / 2 - t / 2, t], [t, ly / 2 - t / 2, t + lz * 0.35],
                                    [t, ly / 2 + t / 2, t], [t + lx * 0.35, ly / 2 + t / 2, t], [t, ly / 2 + t / 2, t + lz * 0.35]])
    solid = solid + g
    return manifold_to_mesh(solid, f"bracket{lx:g}")


def bracket_part(lx: float, ly: float, lz: float, t: float, hole_r: float, T: np.ndarray, name: str = "bracket") -> Part:
    """An L-bracket with a gusset and one hole per leg; its corner at the origin of ``T``."""
    return Part(_bracket_mesh(float(lx), float(ly), float(lz), float(t), float(hole_r)), T, name, kind="bracket",
                params=dict(lx=lx, ly=ly, lz=lz, t=t, hole_r=hole_r))


@functools.lru_cache(maxsize=64)
def _shaft_mesh(r: float, h: float, head_r: float, head_h: float) -> Mesh:
    solid = _cyl(r, h, seg=24) + _cyl(head_r, head_h, z=h - head_h, seg=6)  # hex-ish head
    return manifold_to_mesh(solid, f"shaft{r:g}x{h:g}")


def shaft_part(r: float, h: float, x: float, y: float, z: float, head_r: float = 0.0, head_h: float = 0.0,
               name: str = "shaft") -> Part:
    """A bolt-like shaft (cylinder with a hexagonal head on top) standing at (x, y, z)."""
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    head_r = head_r or 1.8 * r
    head_h = head_h or 0.7 * r
    return Part(_shaft_mesh(float(r), float(h), float(head_r), float(head_h)), T, name, kind="shaft",
                params=dict(r=float(r), h=float(h), head_r=float(head_r), head_h=float(head_h)))


# --------------------------------------------------------------------------- assembly


@dataclass
class Assembly:
    """A rigid assembly of parts, in mm, in the object frame of its target model.

    ``defect`` describes how a defective variant differs from its target (None for a target).
    """

    parts: list[Part]
    name: str = "assembly"
    family: str = "lego"
    defect: dict | None = None
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def copy(self, **kw) -> "Assembly":
        parts = [replace(p, transform=p.transform.copy(), params=dict(p.params)) for p in self.parts]
        args = dict(parts=parts, name=self.name, family=self.family, defect=None if self.defect is None else dict(self.defect))
        args.update(kw)
        return Assembly(**args)

    def to_mesh(self) -> Mesh:
        """Boolean union of the placed parts (a closed solid)."""
        return self.to_mesh_with_part_ids()[0]

    def to_mesh_with_part_ids(self) -> tuple[Mesh, np.ndarray]:
        """(union mesh, part index of every triangle)."""
        if "mesh" not in self._cache:
            mf = _mf()
            solids, ids = [], {}
            for k, p in enumerate(self.parts):
                s = mesh_to_manifold(p.mesh, p.transform).as_original()
                ids[int(s.original_id())] = k
                solids.append(s)
            union = mf.Manifold.batch_boolean(solids, mf.OpType.Add) if len(solids) > 1 else solids[0]
            out = union.to_mesh()
            v = np.asarray(out.vert_properties, dtype=np.float64)[:, :3]
            f = np.asarray(out.tri_verts, dtype=np.int64)
            part_of = np.zeros(len(f), np.int64)
            run_idx = np.asarray(out.run_index, dtype=np.int64) // 3
            for r, oid in enumerate(np.asarray(out.run_original_id)):
                part_of[run_idx[r] : run_idx[r + 1]] = ids.get(int(oid), 0)
            self._cache["mesh"] = (from_arrays(v, f, name=self.name), part_of)
            self._cache["volume"] = float(union.volume())
        return self._cache["mesh"]

    def to_parts_mesh(self) -> Mesh:
        """The placed parts as they are, each its own closed solid (not united: a stud stays inside the brick
        above), one part per solid (``face_parts``, ``part_names`` ``part_KK_<name>``): what a multi-body CAD
        export holds."""
        if "parts_mesh" not in self._cache:
            V, F, P, off = [], [], [], 0
            for k, p in enumerate(self.parts):
                V.append(p.placed_vertices())
                F.append(np.asarray(p.mesh.faces, np.int64) + off)
                P.append(np.full(len(p.mesh.faces), k, np.int32))
                off += len(p.mesh.vertices)
            m = from_arrays(np.vstack(V), np.vstack(F), name=self.name)
            self._cache["parts_mesh"] = m.with_parts(np.concatenate(P),
                                                     [f"part_{k:02d}_{p.name}" for k, p in enumerate(self.parts)])
        return self._cache["parts_mesh"]

    def volume(self) -> float:
        self.to_mesh_with_part_ids()
        return self._cache["volume"]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        b = [p.bounds() for p in self.parts]
        return np.min([x[0] for x in b], axis=0), np.max([x[1] for x in b], axis=0)

    def centered(self) -> "Assembly":
        """Copy translated so that its bounding-box centre is the origin (BOP-style models)."""
        lo, hi = self.bounds()
        c = 0.5 * (lo + hi)
        out = self.copy()
        for p in out.parts:
            p.transform[:3, 3] -= c
        out._cache.clear()
        return out

    def translated(self, offset) -> "Assembly":
        out = self.copy()
        for p in out.parts:
            p.transform[:3, 3] += np.asarray(offset, float)
        return out

    def supported_by(self) -> dict[int, set[int]]:
        """For each part, the parts lying directly on it (touching its top from above, overlapping in xy)."""
        b = [p.bounds() for p in self.parts]
        out: dict[int, set[int]] = {k: set() for k in range(len(self.parts))}
        for a, (alo, ahi) in enumerate(b):
            for c, (clo, chi) in enumerate(b):
                if a == c:
                    continue
                overlap_xy = np.all(np.minimum(ahi[:2], chi[:2]) - np.maximum(alo[:2], clo[:2]) > 0.5)
                # c rests on a: c's base is at a's body top (studs excluded, within 2 mm).
                if overlap_xy and abs(clo[2] - (ahi[2] - (STUD_H if self.parts[a].kind == "brick" and self.parts[a].params.get("studs") else 0))) < 0.3:
                    out[a].add(c)
        return out

    def removable_parts(self) -> list[int]:
        """Parts other than the base (index 0) that nothing rests on."""
        sup = self.supported_by()
        return [k for k in range(1, len(self.parts)) if not sup[k]]

    def info(self) -> dict:
        return dict(name=self.name, family=self.family, n_parts=len(self.parts), defect=self.defect,
                    parts=[dict(name=p.name, kind=p.kind, params=p.params, cell=p.cell,
                                transform=np.round(p.transform, 6).tolist()) for p in self.parts])


# --------------------------------------------------------------------------- target generators

LEGO_COLORS = {  # name -> sRGB
    "red": (201, 26, 9), "blue": (0, 85, 191), "yellow": (242, 205, 55),
    "green": (35, 120, 65), "white": (244, 244, 244), "black": (27, 42, 52),
    "light_grey": (160, 165, 169), "dark_grey": (99, 95, 98), "orange": (254, 138, 24),
    "tan": (228, 205, 158), "lime": (187, 233, 11), "azure": (54, 174, 191),
}


def part_palette(n_parts: int, rng: np.random.Generator, family: str = "lego") -> list[np.ndarray]:
    """Linear-RGB colours (0-1) for ``n_parts`` parts: LEGO colours, or metal/anodised/painted tones."""
    if family == "lego":
        names = list(LEGO_COLORS)
        base = rng.choice(len(names), size=min(4, len(names)), replace=False)  # an assembly uses few colours
        cols = [np.asarray(LEGO_COLORS[names[int(rng.choice(base))]], float) / 255.0 for _ in range(n_parts)]
    else:
        tones = [(0.55, 0.56, 0.58), (0.25, 0.26, 0.28), (0.75, 0.72, 0.65), (0.1, 0.2, 0.5), (0.6, 0.1, 0.1),
                 (0.85, 0.6, 0.2), (0.2, 0.45, 0.25), (0.9, 0.9, 0.88)]
        base = rng.choice(len(tones), size=3, replace=False)
        cols = [np.asarray(tones[int(rng.choice(base))], float) for _ in range(n_parts)]
    return [np.clip(c * rng.uniform(0.92, 1.08), 0, 1) ** 2.2 for c in cols]


def _lego_footprints():
    return [(2, 4), (2, 2), (1, 4), (2, 3), (1, 2), (2, 6), (1, 6), (1, 3)]


def lego_assembly(seed: int, n_bricks: int = 8, base: tuple[int, int] = (6, 8), name: str = "") -> Assembly:
    """A LEGO-like assembly: a base plate of ``base`` studs and ``n_bricks`` bricks stacked on it.

    Each new brick rests on the current height map where it has full support under at least two
    of its cells (so it is physically plausible) and stays within the base footprint.
    """
    rng = np.random.default_rng(seed)
    bx, by = base
    parts = [brick_part(bx, by, 0, 0, 0, plates=1, name="base_plate")]
    height = np.ones((bx, by), np.int64)  # in plates
    fps = _lego_footprints()
    tries = 0
    while len(parts) < n_bricks + 1 and tries < 2000:
        tries += 1
        nx, ny = fps[int(rng.integers(len(fps)))]
        rot = bool(rng.random() < 0.5)
        fx, fy = (ny, nx) if rot else (nx, ny)
        if fx > bx or fy > by:
            continue
        i, j = int(rng.integers(0, bx - fx + 1)), int(rng.integers(0, by - fy + 1))
        region = height[i : i + fx, j : j + fy]
        top = int(region.max())
        if int((region == top).sum()) < min(2, region.size):
            continue
        # Keep towers modest and prefer lower positions early (a compact, irregular assembly).
        if top > 1 + 3 * 3 or (top >= 7 and rng.random() < 0.6):
            continue
        plates = 3 if rng.random() < 0.8 else 1
        k = len(parts)
        parts.append(brick_part(nx, ny, i, j, top, plates=plates, rotated=rot, name=f"b{k}_{nx}x{ny}"))
        height[i : i + fx, j : j + fy] = top + plates
    for k, p in enumerate(parts):
        p.color_key = f"p{k}"
    return Assembly(parts, name or f"lego_{seed}", family="lego").centered()


def mechanical_assembly(seed: int, name: str = "") -> Assembly:
    """A mechanical assembly: a base plate with holes, two or three standoffs / tubes, an
    L-bracket, bolts and a cross plate on the standoffs."""
    rng = np.random.default_rng(seed)
    lx, ly, t = float(rng.uniform(60, 80)), float(rng.uniform(40, 55)), float(rng.uniform(4, 6))
    holes = [(8.0, 8.0, 2.5), (lx - 8.0, 8.0, 2.5), (8.0, ly - 8.0, 2.5), (lx - 8.0, ly - 8.0, 2.5)]
    holes.append((lx * 0.5, ly * 0.5, float(rng.uniform(4, 7))))
    parts = [plate_with_holes_part(lx, ly, t, holes, name="base_plate")]
    n_cyl = int(rng.integers(2, 4))
    h_cyl = float(rng.uniform(14, 24))
    xs = np.linspace(lx * 0.25, lx * 0.75, n_cyl)
    for k, x in enumerate(xs):
        r = float(rng.uniform(3.5, 5.5))
        parts.append(cylinder_part(r, h_cyl, float(x), ly * 0.72, t, bore=r * 0.45 if rng.random() < 0.5 else 0.0,
                                   name=f"standoff{k}"))
    # Cross plate on top of the standoffs.
    cw = float(rng.uniform(10, 14))
    cp = plate_with_holes_part(xs[-1] - xs[0] + 16.0, cw, 3.0, [(4.0, cw / 2, 1.6)], name="cross_plate")
    cp.transform[:3, 3] = [xs[0] - 8.0, ly * 0.72 - cw / 2, t + h_cyl]
    parts.append(cp)
    # Bracket standing on the front-left of the plate.
    T = np.eye(4)
    T[:3, 3] = [4.0, 3.0, t]
    parts.append(bracket_part(float(rng.uniform(16, 22)), float(rng.uniform(10, 14)), float(rng.uniform(16, 24)), 3.0,
                              1.8, T, name="bracket"))
    # Bolts in two of the corner holes (heads above the plate).
    for k, (x, y, _) in enumerate(holes[1:3]):
        parts.append(shaft_part(2.4, t + 6.0, x, y, 0.0, name=f"bolt{k}"))
    # A tall post near the back right.
    parts.append(cylinder_part(float(rng.uniform(3, 4)), float(rng.uniform(25, 35)), lx - 14.0, ly * 0.35, t, name="post"))
    for k, p in enumerate(parts):
        p.color_key = f"p{k}"
    return Assembly(parts, name or f"mech_{seed}", family="mechanical").centered()


def make_target_assembly(index: int, seed: int) -> Assembly:
    """Target assembly ``index`` (0-based): LEGO-like for even indices, mechanical for odd ones
    when ``index >= 2`` (the first two are LEGO, like the paper's dataset)."""
    s = int(seed) * 1000 + index
    if index % 3 == 2:
        return mechanical_assembly(s, name=f"asm{index + 1}_mech")
    n_bricks = 6 + (index * 3) % 5
    base = [(6, 8), (8, 8), (6, 6)][index % 3]
    return lego_assembly(s, n_bricks=n_bricks, base=base, name=f"asm{index + 1}_lego")


def make_target_assemblies(n: int, seed: int) -> list[Assembly]:
    return [make_target_assembly(k, seed) for k in range(n)]
