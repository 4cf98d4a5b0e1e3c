"""Per-object evaluation data (evaluation model points, symmetries, KD-tree, renderer), built once per object,
and :func:`pose_errors`: the ADD(-S) / rotation / translation errors of one estimate, as benchmarks report them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pixie.eval import pose_error as M
from pixie.eval.datasets import BopDataset, is_symmetric, symmetry_transforms
from pixie.geometry.mesh import load_mesh
from pixie.geometry.render import Renderer


@dataclass
class ObjectData:
    """Everything the metrics need about one object, computed once per evaluation."""

    obj_id: int
    diameter: float
    symmetric: bool
    syms: np.ndarray  # (S, 4, 4)
    pts: np.ndarray  # evaluation-model vertices (MSSD, MSPD)
    add_pts: np.ndarray  # points for ADD / ADD-S
    mesh: object
    _tree: object = None
    _renderer: object = None

    @property
    def tree(self):
        if self._tree is None:
            from scipy.spatial import cKDTree  # a slow import (~0.2 s) that `pixie estimate` never needs

            self._tree = cKDTree(self.add_pts)
        return self._tree

    @property
    def renderer(self):
        if self._renderer is None:
            self._renderer = Renderer(self.mesh)
        return self._renderer


def load_object_data(
    dataset: BopDataset, obj_id: int, n_points: int | None = None, max_sym_disc_step: float = 0.01
) -> ObjectData:
    """Load the evaluation model and models_info entry of one object.

    ``n_points`` subsamples (deterministically) the vertices used by ADD / ADD-S; MSSD and
    MSPD always use every vertex of the evaluation model, as BOP does.
    """
    info = dataset.model_info(obj_id, eval=True)
    mesh = load_mesh(dataset.model_path(obj_id, eval=True), units="mm")
    pts = np.asarray(mesh.vertices, dtype=np.float64)
    add_pts = pts
    if n_points is not None and 0 < n_points < len(pts):
        idx = np.random.default_rng(obj_id).choice(len(pts), size=n_points, replace=False)
        add_pts = pts[np.sort(idx)]
    return ObjectData(
        obj_id=obj_id,
        diameter=float(info["diameter"]),
        symmetric=is_symmetric(info),
        syms=symmetry_transforms(info, max_sym_disc_step),
        pts=pts,
        add_pts=add_pts,
        mesh=mesh,
    )


def pose_errors(od: ObjectData, T_est: np.ndarray | None, T_gt: np.ndarray) -> dict:
    """ADD(-S) (ADD-S for symmetric objects, ``od.add_pts``), whether it is below 0.1 d, the rotation error
    (degrees, the smallest over the object's symmetries) and the translation error (mm) of one estimate.

    ``T_est=None`` (no pose) gives ``add_ok=False`` and None errors.
    """
    if T_est is None:
        return {"add": None, "add_ok": False, "rot_err": None, "trans_err": None}
    e = M.add_s(T_est, T_gt, od.add_pts, od.symmetric, od.tree)
    rot = M.rotation_error_deg(T_est, T_gt)
    if od.symmetric and len(od.syms):
        rot = min(M.rotation_error_deg(T_est, T_gt @ S) for S in od.syms)
    return {"add": e, "add_ok": bool(e < 0.1 * od.diameter), "rot_err": rot,
            "trans_err": float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))}
