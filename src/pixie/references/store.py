"""Reference sets on disk: ``.npz`` files written atomically, read back, and upgraded once with contour templates.

A file holds a format version (``FORMAT_VERSION``), the mesh's content hash and the build config; a stale, foreign
or corrupt file raises :class:`ReferenceSetError`. Depth and normals are stored quantised (uint16 steps per view,
int8), left in the file by a load and read and decoded on first access (:class:`_FileArray`,
:class:`pixie.references.set.ReferenceSet` fields), so a load does not pay for arrays inference never reads; the
mesh's convex-hull vertices and the aligning renderer's corner normals are stored too. Contour templates are stored under ``tpl/`` keys with their own version
(``TEMPLATES_VERSION``); :func:`ensure_templates` builds them for a set that lacks them (a file written before they
were stored, or other ``shape.*`` settings) and saves them back into a writable file, once.
"""

from __future__ import annotations

import json
import logging
import os
import time
import zipfile
import zlib
from pathlib import Path
from typing import Callable

import numpy as np

from pixie._version import __version__
from pixie.config import RefsConfig, ShapeConfig
from pixie.errors import OutputError, PixieError, ReferenceSetError
from pixie.geometry.mesh import Mesh, from_arrays, load_mesh
from pixie.paths import output_file, remove_stale_temps, write_atomic
from pixie.references.set import ReferenceSet, _Decoded, _build_templates
from pixie.references.templates import ContourTemplates

FORMAT_VERSION = 1
TEMPLATES_VERSION = 1  # contour templates stored under tpl/ (absent or another version: rebuilt, see ensure_templates)

log = logging.getLogger(__name__)


def templates_fit(refs: ReferenceSet, shape: ShapeConfig) -> bool:
    """The set holds contour templates built with ``shape``'s views, size and points."""
    if not refs.templates:
        return False
    tpl = ContourTemplates.from_arrays(refs.templates)
    return tpl.n_views == shape.views and tpl.size == shape.size and tpl.n_points == shape.points


def ensure_templates(refs: ReferenceSet, shape: ShapeConfig, save: bool = True) -> bool:
    """Give ``refs`` the contour templates of ``shape`` (when enabled) if it lacks them; True when they were built.

    A set loaded from a file (``refs.source_path``) gets them saved back into that file, atomically, when
    ``save`` and the file and its folder are writable, so that the next load has them (a one-time upgrade of a
    set written before templates were stored). Either way one INFO message says what happened.
    """
    if not shape.enabled or templates_fit(refs, shape):
        return False
    t0, had = time.perf_counter(), refs.templates is not None
    refs.templates = _build_templates(refs.mesh, shape).to_arrays()
    what = (f"contour templates ({shape.views} views at {shape.size} px) built in {time.perf_counter() - t0:.1f} s: "
            f"the set {'had none that fit shape.*' if had else 'had none'}")
    path = refs.source_path
    if save and path is not None and os.access(path, os.W_OK) and os.access(path.parent, os.W_OK):
        save_reference_set(refs, path)
        log.info("%s: %s; saved into it (upgraded once)", path, what)
    else:
        log.info("%s: %s; kept in memory only (%s)", path or "reference set", what,
                 "not writable" if path is not None else "not from a file")
    return True


# ----------------------------------------------------------------------------------------- I/O


def check_output_path(path: str | Path, force: bool = True) -> Path:
    """The path a set will be written to, exactly as given (no suffix added); its folder is created and must
    be writable; an existing file is refused unless ``force`` (:func:`pixie.paths.output_file`)."""
    try:
        return output_file(path, force=force, what="reference set")
    except OutputError as exc:
        raise ReferenceSetError(str(exc)) from exc


def save_reference_set(refs: ReferenceSet, path: str | Path, force: bool = True) -> Path:
    """Write ``refs`` to ``path`` (.npz) atomically: a killed write leaves no partial file. Without ``force`` an
    existing file is refused, also one another process wrote meanwhile (:func:`pixie.paths.write_atomic`)."""
    path = check_output_path(path, force=force)
    meta = {
        "format_version": FORMAT_VERSION,
        "pixie_version": __version__,
        "mesh_name": refs.mesh.name,
        "mesh_hash": refs.mesh.source_hash,
        "mesh_file_units": refs.mesh.file_units,  # the units the mesh file was read in (vertices are stored in mm)
        "mesh_part_names": list(refs.mesh.part_names),  # the part report's parts (empty: the mesh has none)
        "config": refs.config.__dict__,
        "build_seconds": refs.build_seconds,
        "encodings": list(refs.encodings),
        "features": sorted(refs.features),
    }
    arrays = {
        "meta": np.frombuffer(json.dumps(meta).encode(), np.uint8),
        "poses": refs.poses, "Ks": refs.Ks, "K_start": refs.K_start, "canonical": refs.canonical,
        **(_stored_arrays(refs, "depth") or _quantise_depth(refs.depth)),
        **(_stored_arrays(refs, "normals") or {"normals_q": np.round(refs.normals * 127.0).astype(np.int8)}),
        "mesh_vertices": refs.mesh.vertices, "mesh_faces": refs.mesh.faces.astype(np.int32),
        "mesh_hull": refs.mesh.hull_vertices,  # the estimator's box points: a convex hull (scipy) not redone per load
        # the aligning renderer's smooth normals, float32 as the renderer uses them (~0.2 s per load otherwise)
        "mesh_corner_normals": refs.mesh.corner_normals().astype(np.float32),
    }
    if refs.mesh.face_parts is not None:
        arrays["mesh_face_parts"] = refs.mesh.face_parts.astype(np.int16)
    if refs.config.store_rotated_encodings:  # roll-0 encodings are re-derived from D and N on load
        for name, img in refs.encodings.items():
            arrays[f"enc/{name}"] = img
    for key, packed in refs.features.items():
        for k, v in packed.items():
            arrays[f"feat/{key}/{k}"] = v
    if refs.templates is not None:
        meta["templates_version"] = TEMPLATES_VERSION
        arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
        arrays.update({f"tpl/{k}": np.asarray(v) for k, v in refs.templates.items()})
    # atomic (a killed write leaves no partial file) and 0644; a file object, else numpy appends '.npz'
    try:
        return write_atomic(path, lambda fh: np.savez_compressed(fh, **arrays), force=force)
    except OutputError as exc:
        raise ReferenceSetError(str(exc)) from exc


def load_reference_set(path: str | Path, mesh: Mesh | str | Path | None = None) -> ReferenceSet:
    """Read a reference set; with ``mesh`` given (a :class:`Mesh` or a mesh file), refuse a set built from another
    mesh file. Array shapes are checked against each other (:class:`ReferenceSetError` naming the set and the field)."""
    if not isinstance(path, (str, os.PathLike)):
        raise ReferenceSetError(f"reference set path must be a str or Path, got {type(path).__name__}")
    if isinstance(mesh, (str, os.PathLike)):
        mesh = load_mesh(mesh)
    elif mesh is not None and not isinstance(mesh, Mesh):
        raise ReferenceSetError(f"mesh must be a Mesh or a mesh file path, got {type(mesh).__name__}")
    path = Path(path)
    remove_stale_temps(path.parent)  # a killed save's temporary file
    if not path.is_file():
        raise ReferenceSetError(f"reference set not found: {path} (build it with `pixie refs build MESH -o {path}`)")
    try:
        with np.load(path, allow_pickle=False) as z:
            # depth and normals (~2/3 of a load's decompression) are read on first access, never by inference
            data = {k: z[k] for k in z.files if k not in _FROM_FILE}
            data.update({k: _FileArray(path, k, z.zip) for k in _FROM_FILE if k in z.files})
    except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError) as exc:
        raise ReferenceSetError(f"reference set {path} is corrupt or not a pixie file: {exc}") from exc
    if "meta" not in data:
        raise ReferenceSetError(f"{path} is not a pixie reference set (no metadata)")
    try:
        meta = json.loads(data["meta"].tobytes().decode())
    except ValueError as exc:
        raise ReferenceSetError(f"{path}: unreadable metadata") from exc
    if not isinstance(meta, dict):
        raise ReferenceSetError(f"{path}: unreadable metadata")
    if meta.get("format_version") != FORMAT_VERSION:
        raise ReferenceSetError(
            f"{path} has format version {meta.get('format_version')}, this pixie reads {FORMAT_VERSION}: rebuild it"
        )
    if mesh is not None and mesh.source_hash != meta["mesh_hash"]:
        raise ReferenceSetError(f"{path} was built from another mesh ({meta['mesh_name']}, hash differs): rebuild it")
    try:
        stored_mesh = from_arrays(data["mesh_vertices"], data["mesh_faces"], name=meta["mesh_name"])
        stored_mesh.source_hash = meta["mesh_hash"]
        stored_mesh.file_units = str(meta.get("mesh_file_units", "unknown"))  # not recorded by older sets
        if "mesh_hull" in data:  # sets written before it was stored compute it on first use
            stored_mesh._hull_vertices = data["mesh_hull"]
        if "mesh_corner_normals" in data:  # likewise (float32: what the renderer reads)
            stored_mesh._corner_normals = data["mesh_corner_normals"]
        if "mesh_face_parts" in data:  # sets of meshes with parts (older sets have none)
            stored_mesh.with_parts(data["mesh_face_parts"], meta.get("mesh_part_names", ()))
        cfg = RefsConfig(**meta["config"])
        _check_shapes(path, data, cfg)
        feats: dict[str, dict[str, np.ndarray]] = {}
        for k, v in data.items():
            if k.startswith("feat/"):
                key, _, field_name = k[5:].rpartition("/")
                feats.setdefault(key, {})[field_name] = v
        return ReferenceSet(
            mesh=mesh or stored_mesh, config=cfg, poses=data["poses"], Ks=data["Ks"], K_start=data["K_start"],
            canonical=data["canonical"], depth=_Lazy(_dequantise_depth, data, data["depth_q"].shape),
            normals=_Lazy(_dequantise_normals, data, data["normals_q"].shape),
            encodings={k[4:]: v for k, v in data.items() if k.startswith("enc/")},
            features=feats, build_seconds=float(meta.get("build_seconds", 0.0)),
            templates=_templates_from(data) if meta.get("templates_version") == TEMPLATES_VERSION else None,
            source_path=path,
        )
    except (KeyError, TypeError) as exc:
        raise ReferenceSetError(f"{path} is missing data ({exc}): rebuild it") from exc
    except ReferenceSetError:
        raise
    except PixieError as exc:  # an invalid stored config or mesh
        raise ReferenceSetError(f"{path} holds invalid data ({exc}): rebuild it") from exc


def _check_shapes(path: Path, data: dict, cfg: RefsConfig) -> None:
    """Every per-view array agrees with ``poses`` (V views x R rolls) and the image size; raise naming the field."""
    def bad(field: str, shape, want: str) -> ReferenceSetError:
        return ReferenceSetError(f"reference set {path} is inconsistent: {field} has shape {tuple(shape)}, expected "
                                 f"{want}: rebuild it")

    poses = data["poses"]
    if poses.ndim != 4 or poses.shape[2:] != (4, 4) or 0 in poses.shape[:2]:
        raise bad("poses", poses.shape, "(views, rolls, 4, 4)")
    V, R = poses.shape[:2]
    S = data["depth_q"].shape[1] if data["depth_q"].ndim == 3 else -1
    want = {"Ks": (V, R, 3, 3), "K_start": (3, 3), "canonical": (V,), "depth_q": (V, S, S), "depth_lo": (V,),
            "depth_step": (V,), "normals_q": (V, S, S, 3)}
    for k, shape in want.items():
        if tuple(data[k].shape) != shape or S <= 0:
            raise bad(k, data[k].shape, str(shape).replace("-1", "S"))
    for k, v in data.items():
        if k.startswith("enc/") and not (v.ndim >= 3 and v.shape[0] == V
                                         and (v.shape[1:3] == (S, S) or v.shape[1:4] == (R, S, S))):
            raise bad(k, v.shape, f"({V}, {S}, {S}[, 3]) or ({V}, {R}, {S}, {S}[, 3])")
        if k.startswith("feat/") and k.endswith("/feat_image_sizes") and len(v.reshape(-1, 2)) not in (V, V * R):
            raise bad(k, v.shape, f"one entry per view ({V}) or per view and roll ({V * R})")
    if cfg.rotations != R:
        raise bad("poses", poses.shape, f"{cfg.rotations} rolls per view (its config's refs.rotations)")
    F = len(data["mesh_faces"])
    if "mesh_corner_normals" in data and data["mesh_corner_normals"].shape != (F, 3, 3):
        raise bad("mesh_corner_normals", data["mesh_corner_normals"].shape, f"({F}, 3, 3): one normal per face corner")


def _templates_from(data: dict) -> dict[str, np.ndarray] | None:
    """Contour-template arrays stored under 'tpl/' keys (pixie.references.templates.ContourTemplates.from_arrays reads them)."""
    return {k[4:]: v for k, v in data.items() if k.startswith("tpl/")} or None


def _quantise_depth(depth: np.ndarray) -> dict[str, np.ndarray]:
    """Depth as uint16 steps between each view's near and far z (0 = background); error < 0.01 mm."""
    mask = depth > 0
    lo = np.where(mask.any((1, 2)), np.where(mask, depth, np.inf).min((1, 2)), 0).astype(np.float64)
    hi = np.where(mask.any((1, 2)), depth.max((1, 2)), 1).astype(np.float64)
    step = np.maximum(hi - lo, 1e-6) / 65534.0
    q = np.round((depth - lo[:, None, None]) / step[:, None, None]) + 1
    return {"depth_q": np.where(mask, q, 0).astype(np.uint16), "depth_lo": lo, "depth_step": step}


def _dequantise_depth(data: dict) -> np.ndarray:
    q = data["depth_q"].astype(np.float64)
    d = data["depth_lo"][:, None, None] + (q - 1) * data["depth_step"][:, None, None]
    return np.where(q > 0, d, 0).astype(np.float32)


class _FileArray:
    """One array of a reference-set file, read on first use (picklable: the path, the key and the file's identity).

    Its ``shape``, ``ndim`` and ``dtype`` come from the array's header alone. Reading it after the file was
    replaced (another build wrote the same path) raises :class:`ReferenceSetError` instead of mixing two sets.
    """

    def __init__(self, path: Path, key: str, zf: zipfile.ZipFile):
        """``zf``: the file, open (its header is read from it)."""
        self.path, self.key, self._stamp = Path(path), key, _stamp(path)
        with zf.open(key + ".npy") as fh:
            fmt = np.lib.format
            header = fmt.read_array_header_1_0 if fmt.read_magic(fh) == (1, 0) else fmt.read_array_header_2_0
            self.shape, _, self.dtype = header(fh)
        self.ndim = len(self.shape)

    def read(self) -> np.ndarray:
        if _stamp(self.path) != self._stamp:
            raise ReferenceSetError(f"reference set {self.path} changed on disk since it was loaded: load it again")
        try:
            with np.load(self.path, allow_pickle=False) as z:
                return z[self.key]
        except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, KeyError) as exc:
            raise ReferenceSetError(f"reference set {self.path} is corrupt: {self.key}: {exc}") from exc


def _stamp(path: Path) -> tuple[int, int, int]:
    st = os.stat(path)
    return st.st_ino, st.st_size, st.st_mtime_ns


_FROM_FILE = ("depth_q", "normals_q")


class _Lazy:
    """``decode(data)`` deferred (picklable: a module-level function and a dict of arrays or :class:`_FileArray`),
    with its shape."""

    def __init__(self, decode: Callable[[dict], np.ndarray], data: dict, shape: tuple):
        self.decode, self.data, self.shape = decode, {k: data[k] for k in _LAZY_KEYS[decode.__name__]}, tuple(shape)

    def arrays(self) -> dict[str, np.ndarray]:
        """The stored arrays, those left in the file read now."""
        return {k: v.read() if isinstance(v, _FileArray) else v for k, v in self.data.items()}

    def __call__(self) -> np.ndarray:
        return self.decode(self.arrays())


def _stored_arrays(refs: ReferenceSet, name: str) -> dict | None:
    """The arrays field ``name`` was loaded from, when it was not replaced since (saved back bit for bit)."""
    stored = _Decoded.stored(refs, name)
    return stored.arrays() if isinstance(stored, _Lazy) else None


def _dequantise_normals(data: dict) -> np.ndarray:
    return _unit(data["normals_q"].astype(np.float32) / 127.0)


_LAZY_KEYS = {"_dequantise_depth": ("depth_q", "depth_lo", "depth_step"), "_dequantise_normals": ("normals_q",)}


def _unit(n: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(norm > 0, n / np.maximum(norm, 1e-12), 0).astype(np.float32)
