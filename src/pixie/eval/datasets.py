"""Reading BOP datasets (scene-wise layout) and BOP'19 result files.

Layout understood (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md)::

    ROOT/
      camera.json                      optional: width, height, fx, fy, cx, cy, depth_scale
      test_targets_bop19.json          [{scene_id, im_id, obj_id, inst_count}, ...]
      models/obj_OOOOOO.ply            full-resolution CAD models (mm)
      models/models_info.json          diameter, bbox, symmetries_discrete, symmetries_continuous
      models_eval/obj_OOOOOO.ply       decimated models used by the BOP metrics (optional)
      test/SSSSSS/scene_gt.json        per image: [{obj_id, cam_R_m2c (row-major), cam_t_m2c (mm)}]
      test/SSSSSS/scene_camera.json    per image: {cam_K (row-major), depth_scale}
      test/SSSSSS/scene_gt_info.json   per instance: bbox_obj, bbox_visib, px_count_*, visib_fract
      test/SSSSSS/rgb/IIIIII.png|jpg   (or gray/)
      test/SSSSSS/depth/IIIIII.png     optional, uint16, depth_mm = value * depth_scale
      test/SSSSSS/mask_visib/IIIIII_GGGGGG.png   optional

Result files are BOP'19 CSV: ``scene_id,im_id,obj_id,score,R,t,time`` with R nine row-major
values and t three values in mm, both space-separated.

Every problem with a file raises :class:`pixie.errors.DatasetError` naming the file.

Longer than 500 lines on purpose: it is the one reader and writer of one file format (records, the
dataset class, result files), and splitting it would spread BOP's conventions over several modules.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import cv2
import numpy as np

from pixie.errors import DatasetError
from pixie.geometry.rotations import rodrigues
from pixie.paths import write_atomic

RESULTS_HEADER = "scene_id,im_id,obj_id,score,R,t,time"
# Tolerance on |R R^T - I| for rotations read from result files. BOP files carry ~6-8
# decimals, but some GT annotations themselves deviate by ~2e-3 (LM-O), so be lenient.
ROTATION_ATOL = 1e-2


# --------------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Target:
    """One BOP'19 estimation target: ``inst_count`` instances of ``obj_id`` in one image."""

    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int


@dataclass
class GtInstance:
    """One ground-truth object instance in an image.

    Attributes
    ----------
    gt_id : int
        Index of the instance in the image's ``scene_gt.json`` list (used by mask file names).
    obj_id : int
    T_cam_from_obj : (4, 4) float64, translation in mm
    bbox_obj, bbox_visib : [x, y, w, h] as stored by BOP (``w`` = last − first column, one less than the
        pixel count), or None without scene_gt_info.json; :attr:`box_visib` / :attr:`box_obj` give them in
        pixie's convention
    visib_fract : float or None
    px_count_all, px_count_valid, px_count_visib : int or None
    """

    gt_id: int
    obj_id: int
    T_cam_from_obj: np.ndarray
    bbox_obj: list[int] | None = None
    bbox_visib: list[int] | None = None
    visib_fract: float | None = None
    px_count_all: int | None = None
    px_count_valid: int | None = None
    px_count_visib: int | None = None

    @property
    def box_visib(self) -> np.ndarray | None:
        """``bbox_visib`` in pixie's box convention (see :func:`box_from_bop`): the crop to give the estimator."""
        return box_from_bop(self.bbox_visib)

    @property
    def box_obj(self) -> np.ndarray | None:
        """``bbox_obj`` (amodal box) in pixie's box convention."""
        return box_from_bop(self.bbox_obj)


def box_from_bop(bbox) -> np.ndarray | None:
    """A BOP ``[x, y, w, h]`` box in pixie's convention: ``w``, ``h`` count pixels.

    BOP (``bop_toolkit`` ``calc_2d_bbox``) stores ``w = x_last - x_first`` for a mask spanning columns
    ``x_first..x_last``; pixie boxes (like OpenCV's ``boundingRect``, COCO and :func:`pixie.pipeline.query.bbox_from_mask`)
    have ``w = x_last - x_first + 1``, the extent a projected object covers. The pixel matters: depth from the
    box size is ~1 % off on an 80 px object without it. BOP's box of an invisible object, ``[-1, -1, -1, -1]``
    (any negative ``w`` or ``h``), stays as it is: an empty box, which the estimator rejects by name.
    """
    if bbox is None:
        return None
    b = np.asarray(bbox, np.float64).reshape(-1)
    if b.shape != (4,):
        raise DatasetError(f"a BOP box is [x, y, w, h], got {list(bbox)!r}")
    if b[2] < 0 or b[3] < 0:
        return b
    return b + np.array([0.0, 0.0, 1.0, 1.0])


@dataclass
class CameraInfo:
    """Intrinsics of one image. ``depth_scale`` converts raw depth PNG values to mm."""

    K: np.ndarray
    depth_scale: float = 1.0


@dataclass
class PoseEstimate:
    """One row of a BOP'19 results file."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    T_cam_from_obj: np.ndarray
    time: float = -1.0


# --------------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------------


def load_json(path: Path) -> Any:
    """Read a JSON file, raising :class:`DatasetError` that names the file on any problem."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"missing file: {path}")
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except json.JSONDecodeError as exc:
        raise DatasetError(f"malformed JSON in {path}: line {exc.lineno} col {exc.colno}: {exc.msg}") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from exc


def _int_keys(d: Any, path: Path) -> dict[int, Any]:
    if not isinstance(d, dict):
        raise DatasetError(f"{path}: expected a JSON object keyed by id, got {type(d).__name__}")
    try:
        return {int(k): v for k, v in d.items()}
    except ValueError as exc:
        raise DatasetError(f"{path}: non-integer key ({exc})") from exc


def _floats(values: Any, n: int, what: str, path: Path) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: {what} is not numeric ({exc})") from exc
    if arr.size != n:
        raise DatasetError(f"{path}: {what} has {arr.size} values, expected {n}")
    if not np.all(np.isfinite(arr)):
        raise DatasetError(f"{path}: {what} has NaN/inf values")
    return arr


def pose_from_Rt(R: Iterable[float], t: Iterable[float]) -> np.ndarray:
    """4x4 ``T_cam_from_obj`` from a row-major 3x3 (or 9 values) rotation and a translation (mm)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def is_symmetric(model_info: dict) -> bool:
    """True when models_info declares any discrete or continuous symmetry."""
    return bool(model_info.get("symmetries_discrete")) or bool(model_info.get("symmetries_continuous"))


def symmetry_transforms(model_info: dict, max_sym_disc_step: float = 0.01) -> np.ndarray:
    """Discrete set of symmetry transforms of an object, as used by BOP's MSSD/MSPD.

    The set is the product of the discrete symmetries (identity included) with the
    discretised continuous ones. A continuous symmetry about an axis through ``offset`` is
    sampled with ``n = ceil(pi / max_sym_disc_step)`` equal rotation steps of ``2 pi / n``:
    a vertex at distance ≤ diameter/2 from the axis then travels at most
    ``(diameter/2) * (2 pi / n) ≤ max_sym_disc_step * diameter`` between neighbouring samples.

    Parameters
    ----------
    model_info : dict
        One entry of ``models_info.json`` (keys ``symmetries_discrete``: list of 16 row-major
        values with translation in mm; ``symmetries_continuous``: list of ``{axis, offset}``).
    max_sym_disc_step : float
        Maximum displacement between consecutive samples, as a fraction of the diameter.

    Returns
    -------
    (N, 4, 4) float64 array; element 0 is the identity. ``N = 1`` for asymmetric objects.
    """
    disc = [np.eye(4)]
    for s in model_info.get("symmetries_discrete", []) or []:
        S = np.asarray(s, dtype=np.float64).reshape(4, 4).copy()
        S[3] = (0.0, 0.0, 0.0, 1.0)
        disc.append(S)
    cont: list[np.ndarray] = []
    for s in model_info.get("symmetries_continuous", []) or []:
        axis = np.asarray(s["axis"], dtype=np.float64).reshape(3)
        offset = np.asarray(s.get("offset", (0.0, 0.0, 0.0)), dtype=np.float64).reshape(3)
        n = int(math.ceil(math.pi / max_sym_disc_step))
        for i in range(n):
            R = rodrigues(axis, 2.0 * math.pi * i / n)
            C = np.eye(4)
            C[:3, :3] = R
            C[:3, 3] = offset - R @ offset  # rotation about the axis through ``offset``
            cont.append(C)
    if not cont:
        return np.stack(disc)
    return np.stack([C @ D for D in disc for C in cont])


# --------------------------------------------------------------------------------------------
# Dataset
# --------------------------------------------------------------------------------------------


@dataclass
class _Scene:
    gt: dict[int, list[dict]]
    camera: dict[int, dict]
    gt_info: dict[int, list[dict]] | None


@dataclass
class BopDataset:
    """A BOP dataset split in the scene-wise layout.

    Parameters
    ----------
    root : path
        Dataset folder (holding ``models/``, ``test/`` ...).
    split : str
        Split folder name, ``'test'`` by default.
    targets_file : str
        Name of the targets file in ``root``.

    Notes
    -----
    JSON files are read lazily and cached; nothing heavy happens in the constructor except
    checking that the folder exists.
    """

    root: Path
    split: str = "test"
    targets_file: str = "test_targets_bop19.json"
    _scenes: dict[int, _Scene] = field(default_factory=dict, repr=False)
    _models_info: dict[bool, dict[int, dict]] = field(default_factory=dict, repr=False)
    _camera_json: dict | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        if not self.root.is_dir():
            raise DatasetError(f"dataset folder not found: {self.root}")

    @property
    def name(self) -> str:
        return self.root.name

    @property
    def split_dir(self) -> Path:
        return self.root / self.split

    # ---- targets, scenes -------------------------------------------------------------------

    def targets(self) -> list[Target]:
        """Estimation targets from ``test_targets_bop19.json`` (in file order)."""
        path = self.root / self.targets_file
        data = load_json(path)
        if not isinstance(data, list):
            raise DatasetError(f"{path}: expected a JSON list of targets, got {type(data).__name__}")
        out = []
        for i, d in enumerate(data):
            try:
                out.append(
                    Target(int(d["scene_id"]), int(d["im_id"]), int(d["obj_id"]), int(d.get("inst_count", 1)))
                )
            except (KeyError, TypeError, ValueError) as exc:
                raise DatasetError(f"{path}: target #{i} is malformed ({type(exc).__name__}: {exc}): {d!r}") from exc
        return out

    def scene_ids(self) -> list[int]:
        """Numeric scene folders present under the split."""
        if not self.split_dir.is_dir():
            raise DatasetError(f"split folder not found: {self.split_dir}")
        return sorted(int(p.name) for p in self.split_dir.iterdir() if p.is_dir() and p.name.isdigit())

    def scene_dir(self, scene_id: int) -> Path:
        return self.split_dir / f"{scene_id:06d}"

    def _scene(self, scene_id: int) -> _Scene:
        if scene_id not in self._scenes:
            d = self.scene_dir(scene_id)
            if not d.is_dir():
                raise DatasetError(f"scene folder not found: {d}")
            gt_path, cam_path, info_path = d / "scene_gt.json", d / "scene_camera.json", d / "scene_gt_info.json"
            gt = _int_keys(load_json(gt_path), gt_path)
            cam = _int_keys(load_json(cam_path), cam_path)
            info = _int_keys(load_json(info_path), info_path) if info_path.is_file() else None
            self._scenes[scene_id] = _Scene(gt, cam, info)
        return self._scenes[scene_id]

    def image_ids(self, scene_id: int) -> list[int]:
        """Image ids with a camera entry in the scene."""
        return sorted(self._scene(scene_id).camera)

    # ---- per-image -------------------------------------------------------------------------

    def instances(self, scene_id: int, im_id: int) -> list[GtInstance]:
        """Ground-truth instances of one image, in ``scene_gt.json`` order."""
        sc = self._scene(scene_id)
        gt_path = self.scene_dir(scene_id) / "scene_gt.json"
        if im_id not in sc.gt:
            raise DatasetError(f"{gt_path}: no entry for image {im_id}")
        entries = sc.gt[im_id]
        infos = None
        if sc.gt_info is not None:
            info_path = self.scene_dir(scene_id) / "scene_gt_info.json"
            infos = sc.gt_info.get(im_id)
            if infos is None or len(infos) != len(entries):
                raise DatasetError(
                    f"{info_path}: image {im_id} has {0 if infos is None else len(infos)} entries "
                    f"but scene_gt.json has {len(entries)}"
                )
        out = []
        for gt_id, e in enumerate(entries):
            where = f"image {im_id} instance {gt_id}"
            try:
                R = _floats(e["cam_R_m2c"], 9, f"{where} cam_R_m2c", gt_path)
                t = _floats(e["cam_t_m2c"], 3, f"{where} cam_t_m2c", gt_path)
                obj_id = int(e["obj_id"])
            except (KeyError, TypeError) as exc:
                raise DatasetError(f"{gt_path}: {where} is malformed ({type(exc).__name__}: {exc})") from exc
            inst = GtInstance(gt_id=gt_id, obj_id=obj_id, T_cam_from_obj=pose_from_Rt(R, t))
            if infos is not None:
                info = infos[gt_id]
                inst.bbox_obj = info.get("bbox_obj")
                inst.bbox_visib = info.get("bbox_visib")
                inst.visib_fract = None if info.get("visib_fract") is None else float(info["visib_fract"])
                inst.px_count_all = info.get("px_count_all")
                inst.px_count_valid = info.get("px_count_valid")
                inst.px_count_visib = info.get("px_count_visib")
            out.append(inst)
        return out

    def camera(self, scene_id: int, im_id: int) -> CameraInfo:
        """Intrinsics and depth scale of one image."""
        sc = self._scene(scene_id)
        path = self.scene_dir(scene_id) / "scene_camera.json"
        if im_id not in sc.camera:
            raise DatasetError(f"{path}: no entry for image {im_id}")
        e = sc.camera[im_id]
        if "cam_K" not in e:
            raise DatasetError(f"{path}: image {im_id} has no cam_K")
        K = _floats(e["cam_K"], 9, f"image {im_id} cam_K", path).reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise DatasetError(f"{path}: image {im_id} cam_K has non-positive focal length")
        return CameraInfo(K=K, depth_scale=float(e.get("depth_scale", 1.0)))

    def _camera_json_data(self) -> dict:
        if self._camera_json is None:
            p = self.root / "camera.json"
            self._camera_json = load_json(p) if p.is_file() else {}
        return self._camera_json

    def image_path(self, scene_id: int, im_id: int) -> Path:
        """Path of the RGB (or gray) image; raises if none exists."""
        d = self.scene_dir(scene_id)
        for sub in ("rgb", "gray"):
            for ext in (".png", ".jpg", ".jpeg", ".tif"):
                p = d / sub / f"{im_id:06d}{ext}"
                if p.is_file():
                    return p
        raise DatasetError(f"no image for scene {scene_id} image {im_id} in {d / 'rgb'}")

    def image_size(self, scene_id: int, im_id: int) -> tuple[int, int]:
        """(height, width) of an image: from camera.json when present, else from the file."""
        cj = self._camera_json_data()
        if "width" in cj and "height" in cj:
            return int(cj["height"]), int(cj["width"])
        return self.load_rgb(scene_id, im_id).shape[:2]

    def load_rgb(self, scene_id: int, im_id: int) -> np.ndarray:
        """RGB image (H, W, 3) uint8."""
        p = self.image_path(scene_id, im_id)
        im = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if im is None:
            raise DatasetError(f"cannot decode image {p}")
        return cv2.cvtColor(im, cv2.COLOR_BGR2RGB)

    def depth_path(self, scene_id: int, im_id: int) -> Path:
        return self.scene_dir(scene_id) / "depth" / f"{im_id:06d}.png"

    def has_depth(self) -> bool:
        """True when the first scene of the split has a depth folder."""
        ids = self.scene_ids()
        return bool(ids) and (self.scene_dir(ids[0]) / "depth").is_dir()

    def load_depth(self, scene_id: int, im_id: int) -> np.ndarray | None:
        """Depth (H, W) float32 in mm (0 = no measurement), or None if the dataset has none."""
        p = self.depth_path(scene_id, im_id)
        if not p.is_file():
            return None
        raw = cv2.imread(str(p), cv2.IMREAD_ANYDEPTH)
        if raw is None:
            raise DatasetError(f"cannot decode depth image {p}")
        return raw.astype(np.float32) * np.float32(self.camera(scene_id, im_id).depth_scale)

    def load_mask_visib(self, scene_id: int, im_id: int, gt_id: int) -> np.ndarray | None:
        """Visible-part mask (H, W) bool of one GT instance, or None if absent."""
        p = self.scene_dir(scene_id) / "mask_visib" / f"{im_id:06d}_{gt_id:06d}.png"
        if not p.is_file():
            return None
        m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if m is None:
            raise DatasetError(f"cannot decode mask {p}")
        return m > 0

    # ---- models ----------------------------------------------------------------------------

    def models_dir(self, eval: bool = False) -> Path:
        """``models_eval/`` when ``eval`` and present, else ``models/``."""
        if eval and (self.root / "models_eval").is_dir():
            return self.root / "models_eval"
        return self.root / "models"

    def model_path(self, obj_id: int, eval: bool = False) -> Path:
        """Path of an object's PLY (the BOP evaluation model when ``eval``)."""
        p = self.models_dir(eval) / f"obj_{obj_id:06d}.ply"
        if not p.is_file():
            raise DatasetError(f"model file not found: {p}")
        return p

    def models_info(self, eval: bool = False) -> dict[int, dict]:
        """All of models_info.json, keyed by integer object id."""
        if eval not in self._models_info:
            path = self.models_dir(eval) / "models_info.json"
            info = _int_keys(load_json(path), path)
            for oid, d in info.items():
                if not isinstance(d, dict) or "diameter" not in d:
                    raise DatasetError(f"{path}: object {oid} has no diameter")
                if not (float(d["diameter"]) > 0):
                    raise DatasetError(f"{path}: object {oid} has non-positive diameter {d['diameter']}")
                for s in d.get("symmetries_discrete", []) or []:
                    if len(s) != 16:
                        raise DatasetError(
                            f"{path}: object {oid} has a discrete symmetry with {len(s)} values, expected 16"
                        )
                for s in d.get("symmetries_continuous", []) or []:
                    if "axis" not in s:
                        raise DatasetError(f"{path}: object {oid} has a continuous symmetry without an axis")
            self._models_info[eval] = info
        return self._models_info[eval]

    def model_info(self, obj_id: int, eval: bool = False) -> dict:
        """One object's models_info entry (diameter in mm, symmetries ...)."""
        info = self.models_info(eval)
        if obj_id not in info:
            raise DatasetError(f"{self.models_dir(eval) / 'models_info.json'}: no entry for object {obj_id}")
        return info[obj_id]

    def obj_ids(self) -> list[int]:
        return sorted(self.models_info())


# --------------------------------------------------------------------------------------------
# Results I/O
# --------------------------------------------------------------------------------------------


def _parse_result_line(line: str, lineno: int, path: Path) -> PoseEstimate:
    where = f"{path} line {lineno}"
    cols = line.split(",")
    if len(cols) != 7:
        raise DatasetError(f"{where}: {len(cols)} comma-separated columns, expected 7 ({RESULTS_HEADER})")
    try:
        scene_id, im_id, obj_id = (int(c) for c in cols[:3])
    except ValueError as exc:
        raise DatasetError(f"{where}: scene_id/im_id/obj_id must be integers ({exc})") from exc
    try:
        score = float(cols[3])
        R = np.array([float(v) for v in cols[4].split()], dtype=np.float64)
        t = np.array([float(v) for v in cols[5].split()], dtype=np.float64)
        tm = float(cols[6])
    except ValueError as exc:
        raise DatasetError(f"{where}: non-numeric value ({exc})") from exc
    if R.size != 9:
        raise DatasetError(f"{where}: R has {R.size} values, expected 9 (row-major, space-separated)")
    if t.size != 3:
        raise DatasetError(f"{where}: t has {t.size} values, expected 3 (mm, space-separated)")
    R = check_pose_values(R, t, score, tm, where)
    return PoseEstimate(scene_id, im_id, obj_id, score, pose_from_Rt(R, t), tm)


def check_pose_values(R, t, score: float, tm: float, where: str, error: type[Exception] = DatasetError) -> np.ndarray:
    """The one check of an estimate's numbers (results files and :func:`pixie.eval.evaluate` alike): finite score,
    R, t and time, R a rotation (orthonormal within ``ROTATION_ATOL``, det +1). Returns R as (3, 3).

    Raises
    ------
    ``error`` naming ``where`` and what is wrong.
    """
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
    for name, v in (("score", np.array([score], np.float64)), ("R", R), ("t", t), ("time", np.array([tm], np.float64))):
        if not np.all(np.isfinite(v)):
            raise error(f"{where}: {name} has NaN/inf values")
    R = R.reshape(3, 3)
    dev = float(np.abs(R @ R.T - np.eye(3)).max())
    if dev > ROTATION_ATOL:
        raise error(f"{where}: R is not orthonormal, so not a rotation (max |R R^T - I| = {dev:.3g})")
    if np.linalg.det(R) < 0:
        raise error(f"{where}: R is a reflection (det < 0)")
    return R


def read_results_csv(path: str | Path) -> list[PoseEstimate]:
    """Read a BOP'19 results CSV with validation.

    The header line is optional; blank lines are skipped.

    Raises
    ------
    DatasetError
        Missing file, or a line with a wrong column count, non-numeric or NaN values,
        R without 9 values or not orthonormal, t without 3 values. The message names the
        file and the line.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"results file not found: {path}")
    out = []
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path} is not UTF-8 text (byte {exc.start}): is it a BOP results CSV?") from exc
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if lineno == 1 and s.replace(" ", "").startswith("scene_id"):
            if s.replace(" ", "") != RESULTS_HEADER:
                raise DatasetError(f"{path} line 1: header {s!r}, expected {RESULTS_HEADER!r}")
            continue
        out.append(_parse_result_line(s, lineno, path))
    return out


def write_results_csv(path: str | Path, estimates: Iterable[PoseEstimate]) -> Path:
    """Write estimates as a BOP'19 results CSV (with header). Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [RESULTS_HEADER]
    for e in estimates:
        T = np.asarray(e.T_cam_from_obj, dtype=np.float64)
        R = " ".join(f"{v:.9g}" for v in T[:3, :3].reshape(-1))
        t = " ".join(f"{v:.9g}" for v in T[:3, 3])
        lines.append(f"{e.scene_id},{e.im_id},{e.obj_id},{e.score:.9g},{R},{t},{e.time:.6g}")
    return write_atomic(path, "\n".join(lines) + "\n")


def gt_as_estimates(dataset: BopDataset, targets: list[Target] | None = None) -> list[PoseEstimate]:
    """The ground truth of every target written as pose estimates (score 1, time -1).

    For a target with ``inst_count = k`` the ``k`` most visible instances are used, as in
    BOP'19 scoring. Useful to check an evaluation pipeline: scoring these gives recall 1.
    """
    targets = dataset.targets() if targets is None else targets
    out = []
    for tg in targets:
        insts = [g for g in dataset.instances(tg.scene_id, tg.im_id) if g.obj_id == tg.obj_id]
        insts.sort(key=lambda g: -(g.visib_fract if g.visib_fract is not None else 1.0))
        for g in insts[: tg.inst_count]:
            out.append(PoseEstimate(tg.scene_id, tg.im_id, tg.obj_id, 1.0, g.T_cam_from_obj.copy(), -1.0))
    return out
