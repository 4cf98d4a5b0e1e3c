"""Whether the parts of an assembly pass through each other: the solids of a mesh's parts on a voxel grid, and how
deep two of them overlap (after a rigid move of one).

A physical part cannot move into another, so a misplaced part seen in a photo is one of the moves that keep it out
of its neighbours. CAD assemblies are often simplified, though: solid bricks whose studs sit inside the brick above,
press fits, threads modelled as cylinders. Overlaps are therefore measured by their *depth* (the largest distance,
inside the overlap, to the nearer of the two parts' surfaces: half a stud's height for a stud in a solid brick,
half the shared thickness for a brick pushed into its neighbour), and the depth the CAD assembly itself already
has between its parts sets what counts as touching (:attr:`PartSolids.tolerance`).

>>> solids = part_solids(mesh)                       # once per mesh (about 0.1-1 s)
>>> collides(solids, k, M)                           # part k moved by M (object frame, X' = M X): bool
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pixie.geometry.mesh import Mesh

__all__ = ["PartSolids", "part_solids", "overlap_depth", "collides", "max_overlap_depth"]

GRID_CELLS = 120  # voxels along the mesh's diameter
MAX_PART_POINTS = 4000  # interior points per part kept for the overlap tests (evenly strided)


@dataclass(kw_only=True)
class PartSolids:
    """The interior of every part of a mesh on one voxel grid (object frame, mm).

    Attributes
    ----------
    pitch : voxel side, mm
    origin : (3,) the grid's corner
    points : per part, (N_k, 3) voxel centres inside the part (at most ``MAX_PART_POINTS``)
    depth : per part, (N_k,) their distance to the part's surface
    occupancy : per part, (lo (3,) int, (nx, ny, nz) bool): the voxels inside it, over its own index range
    surface : per part, a KD-tree of points on its surface (distances to it); None for a part not closed
    closed : per part, whether its surface is closed (a part that is not is never said to collide)
    tolerance : overlaps up to this depth are contacts (the CAD assembly's own deepest overlap x 1.5, at least
        1.5 voxels)
    """

    pitch: float
    origin: np.ndarray
    points: list[np.ndarray]
    depth: list[np.ndarray]
    occupancy: list[tuple[np.ndarray, np.ndarray]]
    surface: list
    closed: list[bool]
    tolerance: float = 0.0


def _part_trimesh(mesh: Mesh, k: int):
    import trimesh

    faces = mesh.faces[np.asarray(mesh.face_parts) == k]
    return trimesh.Trimesh(mesh.vertices, faces, process=True)  # merges the vertices a crease split


def part_solids(mesh: Mesh, cells: int = GRID_CELLS, max_points: int = MAX_PART_POINTS,
                tolerance_factor: float = 1.5) -> PartSolids:
    """The voxelised parts of ``mesh`` (``mesh.face_parts``) and the depth tolerance its own overlaps set.

    Parameters
    ----------
    mesh : a mesh with parts
    cells : voxels along the mesh's diameter
    max_points : interior points kept per part for :func:`overlap_depth` (evenly strided)
    tolerance_factor : the tolerance is this x the deepest overlap between two parts of the CAD assembly (and at
        least this x the pitch)
    """
    from scipy.spatial import cKDTree

    if mesh.face_parts is None or mesh.n_parts < 2:
        raise ValueError(f"mesh {mesh.name!r} has no parts")
    pitch = float(mesh.diameter) / float(cells)
    origin = mesh.vertices.min(axis=0) - pitch
    pts_l, dep_l, occ_l, surf_l, closed_l = [], [], [], [], []
    for k in range(mesh.n_parts):
        tm = _part_trimesh(mesh, k)
        closed = bool(len(tm.faces)) and bool(tm.is_watertight)
        closed_l.append(closed)
        if not closed:  # never tested (overlap_depth): no solid, no surface
            pts_l.append(np.zeros((0, 3)))
            dep_l.append(np.zeros(0))
            occ_l.append((np.zeros(3, int), np.zeros((0, 0, 0), bool)))
            surf_l.append(None)
            continue
        n_s = int(np.clip(tm.area / (0.5 * pitch) ** 2, 2000, 60000))
        surf_l.append(cKDTree(np.vstack([tm.vertices, tm.sample(n_s, seed=k)])))
        lo = np.floor((tm.bounds[0] - origin) / pitch).astype(int)
        hi = np.ceil((tm.bounds[1] - origin) / pitch).astype(int) + 1
        axes = [origin[a] + pitch * np.arange(lo[a], hi[a]) for a in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        inside = tm.contains(grid)
        occ_l.append((lo, inside.reshape(tuple(hi - lo))))
        p = grid[inside]
        if len(p) > max_points:
            p = p[np.linspace(0, len(p) - 1, max_points).astype(int)]
        pts_l.append(p)
        dep_l.append(surf_l[-1].query(p)[0] if len(p) else np.zeros(0))
    solids = PartSolids(pitch=pitch, origin=origin, points=pts_l, depth=dep_l, occupancy=occ_l, surface=surf_l,
                        closed=closed_l)
    solids.tolerance = tolerance_factor * max(max_overlap_depth(solids), pitch)
    return solids


def _inside(solids: PartSolids, j: int, X: np.ndarray) -> np.ndarray:
    """Which points ``X`` (N, 3) lie in a voxel inside part ``j``."""
    lo, occ = solids.occupancy[j]
    if not occ.size:
        return np.zeros(len(X), bool)
    idx = np.round((X - solids.origin) / solids.pitch).astype(int) - lo
    ok = np.all((idx >= 0) & (idx < np.array(occ.shape)), axis=1)
    out = np.zeros(len(X), bool)
    out[ok] = occ[idx[ok, 0], idx[ok, 1], idx[ok, 2]]
    return out


def overlap_depth(solids: PartSolids, k: int, j: int, M: np.ndarray | None = None) -> float:
    """How deep part ``k`` (moved by ``M``, (4, 4) in the object frame; None: where the model has it) and part
    ``j`` overlap: the largest distance, over ``k``'s interior points inside ``j``, to the nearer of the two
    surfaces (mm; 0 when they do not overlap or either is not closed)."""
    if k == j or not (solids.closed[k] and solids.closed[j]) or not len(solids.points[k]):
        return 0.0
    X = solids.points[k]
    if M is not None:
        X = X @ np.asarray(M)[:3, :3].T + np.asarray(M)[:3, 3]
    inside = _inside(solids, j, X)
    if not inside.any():
        return 0.0
    dj = solids.surface[j].query(X[inside])[0]
    return float(np.max(np.minimum(solids.depth[k][inside], dj)))


def max_overlap_depth(solids: PartSolids) -> float:
    """The deepest overlap between two parts where the model has them (:func:`overlap_depth`), mm."""
    n = len(solids.points)
    return max((overlap_depth(solids, k, j) for k in range(n) for j in range(n) if j != k), default=0.0)


def collides(solids: PartSolids, k: int, M: np.ndarray) -> bool:
    """Whether part ``k`` moved by ``M`` ((4, 4), object frame) passes into another part deeper than the
    assembly's :attr:`~PartSolids.tolerance`."""
    return any(overlap_depth(solids, k, j, M) > solids.tolerance for j in range(len(solids.points)) if j != k)
