"""One call from a CAD model (or a reference set) and a photo to a pose: :func:`estimate_pose`."""

from __future__ import annotations

import os
import sys
import warnings
from collections import OrderedDict
from pathlib import Path
from typing import Any, Sequence


from pixie.geometry.camera import parse_K
from pixie.config import DEFAULT_PRESET, PixieConfig
from pixie.errors import ImageError
from pixie.pipeline.estimator import PoseEstimator
from pixie.geometry.mesh import Mesh, load_mesh, units_note
from pixie.pipeline.query import load_image
from pixie.pose.results import NO_BOX_MESSAGE
from pixie.references.set import ReferenceSet
from pixie.references.store import ensure_templates, load_reference_set
from pixie.app.notes import annotate, collect_warnings
from pixie.app.console import tqdm_progress
from pixie.app.runner import cached_reference_set, reference_cache_path
from pixie.app.track import read_pose_file
from pixie.weights import cache_dir

__all__ = ["estimate_pose"]

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb", ".gltf")
_ESTIMATORS: "OrderedDict[tuple, Any]" = OrderedDict()  # a few ready estimators, so repeated calls skip loading
_MAX_ESTIMATORS = 2


def _refs_cache() -> Path:

    return cache_dir().parent / "refs"


def _reference_set(obj: Any, cfg: PixieConfig, units: str, cache: Path | None, quiet: bool = False):
    """A ReferenceSet from a ReferenceSet, a Mesh, a mesh file (built once, cached) or a reference-set file.

    Unless ``quiet``, the mesh's units and a first build (tens of seconds) are announced on stderr, with a bar."""

    if isinstance(obj, ReferenceSet):
        return obj, ("refs", id(obj))
    if isinstance(obj, Mesh):
        mesh = obj
    else:
        path = Path(os.fspath(obj))
        if path.suffix.lower() not in MESH_SUFFIXES:
            refs = load_reference_set(path)
            ensure_templates(refs, cfg.shape)  # an older set: templates built once and saved into it
            return refs, ("file", str(path.resolve()), path.stat().st_mtime_ns)
        mesh = load_mesh(path, units=units)
        if not quiet:
            print(units_note(mesh), file=sys.stderr, flush=True)
    where = reference_cache_path(mesh, cfg, cache or _refs_cache())
    progress = None
    if not quiet and not where.is_file():
        print(f"pixie: building the references of {mesh.name} once (preset {cfg.preset}; tens of seconds) -> {where}",
              file=sys.stderr, flush=True)
        progress = tqdm_progress("view")
    refs = cached_reference_set(mesh, cfg, cache or _refs_cache(), progress=progress)
    return refs, ("mesh", mesh.source_hash, mesh.file_units)


def _stage_line(stage: str) -> None:
    """The API's status line on stderr (``quiet=False``): the stage that is running."""
    print(f"\rpixie: estimating: {stage} ..." + " " * 20, end="", file=sys.stderr, flush=True)


def estimate_pose(mesh_or_refs: Any, image: Any, K: Any, bbox: Sequence[float] | None = None,
                  mask: Any = None, *, preset: str = DEFAULT_PRESET, config: PixieConfig | None = None,
                  units: str = "auto", device: str | None = None, cache_dir: str | Path | None = None,
                  init_pose: Any = None, quiet: bool = False):
    """Estimate ``T_cam_from_obj`` of an object in one photo, in one call.

    >>> import pixie
    >>> result = pixie.estimate_pose("bracket.stl", "photo.png", K="600,600,320,240", bbox=(250, 180, 120, 110))
    >>> result.T_cam_from_obj, result.confidence, result.failed

    Parameters
    ----------
    mesh_or_refs
        A CAD file (PLY/OBJ/STL/OFF/GLB; its reference set is built with the preset on first use and cached
        in ``cache_dir``, default ``~/.cache/pixie/refs``), a reference-set file from ``pixie refs build``, a
        :class:`~pixie.geometry.mesh.Mesh` or a :class:`~pixie.references.set.ReferenceSet`.
    image
        A file path, or an RGB ``uint8`` array (H, W, 3).
    K
        3x3 intrinsics, ``(fx, fy, cx, cy)`` or ``"fx,fy,cx,cy"`` (OpenCV, pixels).
    bbox, mask
        The object's box ``(x, y, w, h)`` (``w``, ``h`` counting pixels) or its mask (boolean array or image
        path, white = object). One of them is required: pixie does not guess where the object is.
    preset, config
        ``config`` as is, else the preset (``fast``, ``default``, ``paper``).
    units
        Units of a mesh file (``auto`` by default: metres if under 2 units across, else mm).
    device
        ``auto``, ``cpu`` or ``cuda`` for the matcher (default: the config's).
    init_pose
        A starting pose (4x4, mm, OpenCV camera; or a pose JSON file): refined by edge alignment instead of
        searching all views (:meth:`~pixie.pipeline.estimator.PoseEstimator.estimate_from_prior`); box optional.
    quiet
        No lines on stderr (the mesh's units, a first reference build and its progress bar).

    Returns
    -------
    pixie.pipeline.estimator.PoseResult
        ``T_cam_from_obj`` (mm, OpenCV camera), ``failed``, ``confidence``, ``hypotheses``, ``timings``;
        ``to_dict()`` for JSON.

    Raises
    ------
    pixie.PixieError
        Missing inputs, no box or mask, unreadable files, bad intrinsics.
    """

    if bbox is None and mask is None and init_pose is None:
        raise ImageError(NO_BOX_MESSAGE)
    if isinstance(init_pose, (str, os.PathLike)):
        init_pose = read_pose_file(init_pose)
    cfg = config if config is not None else PixieConfig.from_preset(preset)
    if device is not None:
        cfg.match.device = device
    with collect_warnings() as notes:  # kept in result.warnings, and warned again below as usual
        if isinstance(image, (str, os.PathLike)):
            image = load_image(image)
        if mask is not None and isinstance(mask, (str, os.PathLike)):
            mask = load_image(mask)[..., 0] > 127
        refs, refs_id = _reference_set(mesh_or_refs, cfg, units, Path(cache_dir) if cache_dir else None, quiet)
        key = (refs_id, cfg.digest())
        est = _ESTIMATORS.get(key)
        if est is None:
            est = PoseEstimator(refs, PixieConfig.from_dict(cfg.to_dict()))
            est.cfg.preset = cfg.preset
            _ESTIMATORS[key] = est
            while len(_ESTIMATORS) > _MAX_ESTIMATORS:
                _ESTIMATORS.popitem(last=False)
        else:
            _ESTIMATORS.move_to_end(key)
        if init_pose is not None:
            res = est.estimate_from_prior(image, parse_K(K), init_pose, bbox=bbox, mask=mask)
        else:
            res = est.estimate(image, parse_K(K), bbox=bbox, mask=mask,
                               progress=None if quiet else _stage_line)
            if not quiet:
                print(f"\rpixie: estimated in {res.timings.get('total', 0.0):.1f} s" + " " * 40, file=sys.stderr,
                      flush=True)
    for message in notes.items:  # the caller's own warning handling sees them as before
        warnings.warn(message, UserWarning, stacklevel=2)
    return annotate(res, est, cfg, notes)
