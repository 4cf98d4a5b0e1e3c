"""Loading CAD meshes (PLY / OBJ / STL / GLB) in millimetres, with validation, and their parts.

pixie works in millimetres throughout. Meshes in metres (a classic 1000x mistake) are
detected from their size and either converted (``units='auto'``) or warned about.

Parts (``Mesh.face_parts``, ``Mesh.part_names``): the named sub-meshes of a multi-mesh file (GLB / glTF
scene nodes; trimesh merges an OBJ's objects, which then count as components), else the connected components
of a single mesh when there are 2 to
``MAX_COMPONENT_PARTS`` of them; components under ``MIN_PART_AREA`` of the surface join the part they are
nearest to. A mesh without parts has ``face_parts is None``.
"""

from __future__ import annotations

import hashlib
import logging
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pixie.errors import MeshError

log = logging.getLogger(__name__)

UNIT_SCALE = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
# Plausible diameters of a part seen by a camera, in mm: a screw head to a car door.
PLAUSIBLE_DIAMETER_MM = (2.0, 5000.0)
MAX_COMPONENT_PARTS = 64  # more connected components than this are a scan's fragments, not an assembly's parts
MIN_PART_AREA = 0.01  # share of the surface below which a connected component is a speck, not a part


@dataclass
class Mesh:
    """A triangle mesh in millimetres.

    Attributes
    ----------
    vertices : (V, 3) float64, mm
    faces : (F, 3) int64
    vertex_normals : (V, 3) float64, unit length
    name : str
    source_hash : str
        SHA-256 of the file bytes (or of the arrays for in-memory meshes); reference sets record it.
    file_units : str
        Units the file was read in ('mm', 'cm', 'm'); ``units_auto`` says whether ``units='auto'`` chose them.
    face_parts : (F,) int32 or None
        Part index of every triangle (see the module docstring), None for a mesh without parts.
    part_names : tuple of str
        One name per part (empty without parts).
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray
    name: str = "mesh"
    source_hash: str = ""
    file_units: str = "mm"
    units_auto: bool = False
    face_parts: np.ndarray | None = None
    part_names: tuple[str, ...] = ()
    _diameter: float | None = field(default=None, repr=False)
    _corner_normals: np.ndarray | None = field(default=None, repr=False)
    _hull_vertices: np.ndarray | None = field(default=None, repr=False)
    _center: np.ndarray | None = field(default=None, repr=False)
    _radius: float | None = field(default=None, repr=False)

    @property
    def n_parts(self) -> int:
        """Number of parts (0 for a mesh without parts)."""
        return len(self.part_names) if self.face_parts is not None else 0

    def with_parts(self, face_parts: np.ndarray | None, part_names=()) -> "Mesh":
        """This mesh with the given part labels (checked: one per face, names for every index, >= 2 parts)."""
        if face_parts is None:
            self.face_parts, self.part_names = None, ()
            return self
        fp = np.asarray(face_parts)
        names = tuple(str(n) for n in part_names)
        if fp.shape != (len(self.faces),) or not np.issubdtype(fp.dtype, np.integer):
            raise MeshError(f"mesh {self.name!r}: face_parts must be one integer per face ({len(self.faces)}), "
                            f"got shape {fp.shape} of {fp.dtype}")
        if len(names) < 2 or fp.min() < 0 or fp.max() >= len(names):
            raise MeshError(f"mesh {self.name!r}: face_parts index {len(names)} part name(s); need >= 2 parts "
                            f"and indices 0..{len(names) - 1}, got {int(fp.min())}..{int(fp.max())}")
        self.face_parts, self.part_names = fp.astype(np.int32), names
        return self

    @property
    def bbox_min(self) -> np.ndarray:
        return self.vertices.min(axis=0)

    @property
    def bbox_max(self) -> np.ndarray:
        return self.vertices.max(axis=0)

    @property
    def extent(self) -> np.ndarray:
        """Size of the axis-aligned bounding box (3,), mm."""
        return self.bbox_max - self.bbox_min

    @property
    def center(self) -> np.ndarray:
        """Centre of the axis-aligned bounding box (3,), mm (computed once: a mesh's vertices do not change)."""
        if self._center is None:
            self._center = 0.5 * (self.bbox_min + self.bbox_max)
        return self._center.copy()

    @property
    def hull_vertices(self) -> np.ndarray:
        """Vertices of the convex hull (H, 3), mm: every projected extreme point (box, silhouette extent) of
        the mesh is one of them, at a fraction of the vertex count (all vertices for flat meshes)."""
        if self._hull_vertices is None:
            self._hull_vertices = _hull_points(self.vertices)
        return self._hull_vertices

    @property
    def diameter(self) -> float:
        """Largest distance between two vertices (exact on the convex hull), mm."""
        if self._diameter is None:
            self._diameter = _diameter(self.hull_vertices)  # the hull's (stored in reference sets): no second qhull
        return self._diameter

    @property
    def bounding_radius(self) -> float:
        """Radius of the sphere about ``center`` that contains every vertex, mm (computed once)."""
        if self._radius is None:
            self._radius = float(np.linalg.norm(self.vertices - self.center, axis=1).max())
        return self._radius

    def corner_normals(self, crease_deg: float = 30.0) -> np.ndarray:
        """Per-corner normals (F, 3, 3) that are smooth across gentle edges and sharp across creases.

        Each face corner averages (area-weighted) the normals of the faces around its vertex that are
        within ``crease_deg`` of its own face, so planar CAD faces stay flat while scanned, finely
        tessellated surfaces stay smooth.
        """
        if self._corner_normals is None or crease_deg != 30.0:
            cn = _corner_normals(self.vertices, self.faces, crease_deg)
            if crease_deg != 30.0:
                return cn
            self._corner_normals = cn
        return self._corner_normals

    def to_trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, vertex_normals=self.vertex_normals, process=False)

    def sample_points(self, n: int, seed: int = 0) -> np.ndarray:
        """``n`` points sampled uniformly on the surface (area-weighted), mm."""
        rng = np.random.default_rng(seed)
        tri = self.vertices[self.faces]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        idx = rng.choice(len(tri), size=n, p=area / area.sum())
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
        return np.einsum("nk,nkd->nd", w, tri[idx])


def _hull_points(vertices: np.ndarray) -> np.ndarray:
    """Convex-hull vertices of ``vertices`` (N, 3); all of them when few, or when the hull is degenerate (flat)."""
    if len(vertices) <= 64:
        return vertices
    from scipy.spatial import ConvexHull

    try:
        return vertices[ConvexHull(vertices).vertices]
    except (RuntimeError, ValueError):  # QhullError (a RuntimeError) on flat or degenerate point sets
        return vertices


def _diameter(pts: np.ndarray) -> float:
    """Largest pairwise distance of ``pts`` (N, 3): pass the convex-hull vertices, the only candidates.

    Squared distances come from the Gram matrix (one BLAS product per block, no (N, N, 3) temporary); the
    rows whose maximum is within round-off of the largest are then measured exactly.
    """
    p = np.asarray(pts, dtype=np.float64)
    p = p - p.mean(axis=0)
    sq = (p * p).sum(axis=1)
    row_max = np.concatenate([(sq[i : i + 2048, None] + sq[None, :] - 2.0 * p[i : i + 2048] @ p.T).max(axis=1)
                              for i in range(0, len(p), 2048)])
    rows = np.flatnonzero(row_max >= row_max.max() - 1e-6 * max(float(row_max.max()), 1.0))
    return float(np.linalg.norm(p[rows, None, :] - p[None, :, :], axis=-1).max())


def from_arrays(vertices: np.ndarray, faces: np.ndarray, name: str = "mesh", units: str = "mm") -> Mesh:
    """Build a validated :class:`Mesh` from arrays (units as for :func:`load_mesh`)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    digest = hashlib.sha256(v.tobytes() + np.asarray(f, dtype=np.int64).tobytes()).hexdigest()
    return _finish(v, f, name, digest, units)


def load_mesh(path: str | Path, units: str = "auto", implausible: str = "warn") -> Mesh:
    """Load a triangle mesh and return it in millimetres.

    Parameters
    ----------
    path : str or Path
        PLY, OBJ, STL, GLB/GLTF or OFF file. Multi-part scenes are merged.
    units : {'mm', 'cm', 'm', 'auto'}
        Units the file is written in. ``'auto'`` (default) takes metres when the bounding-box diagonal
        is below 2 (a part under 2 mm is unlikely), else millimetres; :func:`units_note` says what it chose.
    implausible : {'warn', 'error'}
        What a size outside 2 mm .. 5 m in the (declared or chosen) units does: a ``UserWarning`` or a
        :class:`MeshError` (the CLI's choice when the user did not name the units).

    Raises
    ------
    MeshError
        Missing or unreadable file, no triangles, NaN/inf vertices, zero surface area,
        or unknown units.
    """
    import trimesh

    if not isinstance(path, (str, os.PathLike)):
        raise MeshError(f"mesh path must be a str or Path, got {type(path).__name__}")
    if implausible not in ("warn", "error"):
        raise MeshError(f"implausible must be 'warn' or 'error', got {implausible!r}")
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"mesh file not found: {path}")
    data = path.read_bytes()
    if not data:
        raise MeshError(f"mesh file is empty: {path}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            raw = trimesh.load(path, process=False)
            loaded, face_parts, part_names = _scene_parts(raw)
            if loaded is None:  # one mesh as read; a scene (or point cloud) merged as trimesh merges it
                loaded = raw if isinstance(raw, trimesh.Trimesh) else trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types on corrupt files
        raise MeshError(f"cannot read mesh {path}: {type(exc).__name__}: {exc}") from exc
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f"{path} holds no triangle mesh (got {type(loaded).__name__})")
    if len(loaded.faces) == 0:
        raise MeshError(_no_triangles_message(path, len(loaded.vertices)))
    faces = np.asarray(loaded.faces)
    if faces.min() < 0 or faces.max() >= len(loaded.vertices):  # checked before trimesh indexes with them
        bad = int(((faces < 0) | (faces >= len(loaded.vertices))).any(axis=1).sum())
        raise MeshError(f"mesh {path}: {bad} face(s) use vertex indices outside its {len(loaded.vertices)} vertices "
                        f"(indices {int(faces.min())}..{int(faces.max())}); the file is corrupt")
    # STL (and some OBJ/GLB exports) repeat every vertex per face: weld equal positions so that
    # smooth normals and adjacency do not depend on the file format.
    if len(loaded.vertices) and np.all(np.isfinite(loaded.vertices)):  # NaNs are reported below
        loaded.merge_vertices(merge_tex=True, merge_norm=True)  # keeps the faces and their order
    mesh = _finish(
        np.asarray(loaded.vertices, dtype=np.float64),
        np.asarray(loaded.faces),
        path.stem,
        hashlib.sha256(data).hexdigest(),
        units,
        implausible,
    )
    if face_parts is None:
        face_parts, part_names = component_parts(mesh.vertices, mesh.faces)
    return mesh.with_parts(face_parts, part_names)


def _scene_parts(raw) -> tuple[object | None, np.ndarray | None, tuple[str, ...]]:
    """(one Trimesh, part index per face, part names) of a file holding >= 2 triangle meshes; (None, None, ())
    otherwise (the caller loads it as one mesh). Node transforms are applied; nodes are taken in name order."""
    import trimesh

    if not isinstance(raw, trimesh.Scene):
        return None, None, ()
    items = []
    for node in sorted(raw.graph.nodes_geometry):
        T, geom = raw.graph[node]
        g = raw.geometry.get(geom)
        if isinstance(g, trimesh.Trimesh) and len(g.faces):
            items.append((str(node), g, np.asarray(T, np.float64)))
    if len(items) < 2:
        return None, None, ()
    verts, faces, parts, off = [], [], [], 0
    for k, (_name, g, T) in enumerate(items):
        v = np.asarray(g.vertices, np.float64) @ T[:3, :3].T + T[:3, 3]
        verts.append(v)
        faces.append(np.asarray(g.faces, np.int64) + off)
        parts.append(np.full(len(g.faces), k, np.int32))
        off += len(v)
    mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
    return mesh, np.concatenate(parts), tuple(name for name, _g, _T in items)


def component_parts(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray | None, tuple[str, ...]]:
    """Connected components (faces sharing a vertex) as parts: (part index per face, names), or (None, ())
    when there is one component, more than ``MAX_COMPONENT_PARTS``, or fewer than 2 above ``MIN_PART_AREA``.
    Specks (below ``MIN_PART_AREA`` of the surface) join the part whose centroid is nearest to theirs."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, np.int64)
    nv = len(vertices)
    rows = np.repeat(np.arange(len(f)), 3)
    g = coo_matrix((np.ones(len(rows), np.int8), (rows, f.ravel())), shape=(len(f), nv)).tocsr()
    # faces and vertices as one bipartite graph: components of faces through shared vertices
    _, lab = connected_components(_bipartite(g), directed=False)
    face_lab = lab[: len(f)]
    uniq, face_lab = np.unique(face_lab, return_inverse=True)
    if len(uniq) < 2 or len(uniq) > MAX_COMPONENT_PARTS:
        return None, ()
    tri = np.asarray(vertices, np.float64)[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    comp_area = np.bincount(face_lab, weights=area, minlength=len(uniq))
    cent = np.stack([np.bincount(face_lab, weights=area * tri[:, :, d].mean(1), minlength=len(uniq))
                     for d in range(3)], 1) / np.maximum(comp_area, 1e-12)[:, None]
    big = np.flatnonzero(comp_area >= MIN_PART_AREA * comp_area.sum())
    if len(big) < 2:
        return None, ()
    # order parts by area (largest first) so that indices are stable under vertex renumbering
    big = big[np.argsort(-comp_area[big], kind="stable")]
    to_part = np.empty(len(uniq), np.int32)
    to_part[big] = np.arange(len(big))
    small = np.setdiff1d(np.arange(len(uniq)), big)
    if len(small):
        d = np.linalg.norm(cent[small, None] - cent[None, big], axis=2)
        to_part[small] = np.argmin(d, axis=1)
    return to_part[face_lab].astype(np.int32), tuple(f"component_{k:02d}" for k in range(len(big)))


def _bipartite(face_vertex):
    """Symmetric adjacency of the (faces + vertices) graph from a (F, V) incidence matrix."""
    from scipy.sparse import bmat

    return bmat([[None, face_vertex], [face_vertex.T, None]]).tocsr()


def _no_triangles_message(path: Path, n_loaded: int) -> str:
    """Why a file without triangles is refused: a point cloud (vertices only) or nothing at all.

    Parameters
    ----------
    path : Path
        The mesh file.
    n_loaded : int
        Vertices of the triangle mesh read from it (trimesh drops the points of a file without faces).
    """
    n = n_loaded or _count_points(path)
    if n == 0:
        return f"mesh file {path} has no vertices and no triangles"
    return (f"mesh file {path} has no triangles: it is a point cloud ({n} vertices, no faces); "
            "only triangle meshes are supported")


def _count_points(path: Path) -> int:
    """Vertices in a file read as it is (a point cloud or lines), 0 when it cannot be read."""
    import trimesh

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            raw = trimesh.load(path, process=False)
    except Exception:  # the caller reports the missing triangles either way
        return 0
    parts = raw.geometry.values() if isinstance(raw, trimesh.Scene) else [raw]
    return int(sum(len(getattr(g, "vertices", ())) for g in parts))


def _finish(v: np.ndarray, f: np.ndarray, name: str, digest: str, units: str, implausible: str = "warn") -> Mesh:
    if units not in (*UNIT_SCALE, "auto"):
        raise MeshError(f"unknown units {units!r}; use one of mm, cm, m, auto")
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise MeshError(f"mesh {name!r} has no vertices (shape {v.shape})")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise MeshError(f"mesh {name!r} has no triangles (faces shape {f.shape}); only triangle meshes are supported")
    if not np.all(np.isfinite(v)):
        raise MeshError(f"mesh {name!r} has {int((~np.isfinite(v)).any(axis=1).sum())} NaN/inf vertices")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"mesh {name!r} has face indices outside its {len(v)} vertices")
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    auto = units == "auto"
    if auto:
        units = "m" if diag < 2.0 else "mm"
        log.info("mesh %s: units=auto chose %s (bbox diagonal %.4g in file units)", name, units, diag)
    v = v * UNIT_SCALE[units]
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if area.sum() <= 1e-12:
        raise MeshError(f"mesh {name!r} has zero surface area (all triangles degenerate)")
    lo, hi = PLAUSIBLE_DIAMETER_MM
    diag_mm = diag * UNIT_SCALE[units]
    if not lo <= diag_mm <= hi:
        fits = [u for u in UNIT_SCALE if u != units and lo <= diag * UNIT_SCALE[u] <= hi]  # only the other units
        hint = (f"in {' or '.join(fits)}? try " + " or ".join(f"--units {u}" for u in fits) if fits
                else "no other unit (mm, cm, m) makes it plausible: check the file")
        msg = (f"mesh {name!r} is {diag_mm:.4g} mm across in the declared units ({units}); "
               f"this is implausible for a part ({hint})")
        if implausible == "error":
            raise MeshError(msg + "; name the file's units with --units to go on")
        warnings.warn(msg, UserWarning, stacklevel=3)
    normals = _vertex_normals(v, f, area)
    return Mesh(vertices=v, faces=f, vertex_normals=normals, name=name, source_hash=digest, file_units=units,
                units_auto=auto)


def units_note(mesh: Mesh) -> str:
    """One line for people: the units the mesh was read in, how they were chosen, and its diameter in mm."""
    name = {"mm": "millimetres", "cm": "centimetres", "m": "metres"}.get(mesh.file_units, mesh.file_units)
    how = "auto-detected from its size" if mesh.units_auto else "as given"
    return (f"mesh {mesh.name}: read in {name} ({how}), diameter {mesh.diameter:.1f} mm"
            + ("; if that is wrong pass --units mm|cm|m" if mesh.units_auto else ""))


def _vertex_normals(v: np.ndarray, f: np.ndarray, area: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, recomputed from geometry (files' normals are often stale)."""
    tri = v[f]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.where(norm > 0, vn / np.maximum(norm, 1e-30), 0.0)


def _corner_normals(v: np.ndarray, f: np.ndarray, crease_deg: float) -> np.ndarray:
    tri = v[f]
    fn_w = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    fn = fn_w / np.maximum(np.linalg.norm(fn_w, axis=1, keepdims=True), 1e-30)
    corner_v = f.ravel()
    corner_f = np.repeat(np.arange(len(f)), 3)
    order = np.argsort(corner_v, kind="stable")
    sv = corner_v[order]
    starts = np.flatnonzero(np.r_[True, sv[1:] != sv[:-1]])
    counts = np.diff(np.r_[starts, len(sv)])
    start_of = np.repeat(starts, counts)  # group start of each sorted corner
    size_of = np.repeat(counts, counts)
    a = np.repeat(np.arange(len(sv)), size_of)  # every ordered pair of corners sharing a vertex
    b = np.repeat(start_of, size_of) + (np.arange(len(a)) - np.repeat(np.cumsum(size_of) - size_of, size_of))
    fa, fb = corner_f[order[a]], corner_f[order[b]]
    ga, gb = fn[fa], fn[fb]
    keep = ga[:, 0] * gb[:, 0] + ga[:, 1] * gb[:, 1] + ga[:, 2] * gb[:, 2] >= np.cos(np.radians(crease_deg))
    dst, src = order[a[keep]], fn_w[fb[keep]]
    # np.bincount sums in input order, as np.add.at does (bit-identical)
    out = np.stack([np.bincount(dst, weights=src[:, k], minlength=len(corner_v)) for k in range(3)], axis=1)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    out = np.where(norm > 0, out / np.maximum(norm, 1e-30), fn[corner_f])
    return out.reshape(len(f), 3, 3)


def face_normals(mesh: Mesh) -> np.ndarray:
    """Unit face normals (F, 3) following the winding order."""
    tri = mesh.vertices[mesh.faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
