"""Reference sets: everything inference needs about one object, rendered and extracted offline.

For each view i (6 canonical + N Fibonacci) and in-plane roll j the set holds the pose
``T_cam_from_obj[i, j]`` and the intrinsics ``K[i, j]`` of an object-centred square crop rendered
directly at ``size`` px (no resampling). For roll 0 it stores depth D_i, normals N_i and, derived
exactly from them, object-space XYZ_i (back-projection with K then T⁻¹). Matcher features of every
encoded image are stored together with the object-space XYZ of each keypoint, so inference neither
renders nor re-extracts anything.

The set also owns the offline part of the shape cues: contour templates (:mod:`pixie.references.templates`),
built with the set (``build_reference_set(..., shape=cfg.shape)``), stored under ``tpl/`` keys with their own
version (``TEMPLATES_VERSION``) and loaded with it. A set without fitting templates (written before they were
stored, or for other ``shape.*`` settings) is upgraded once by :func:`ensure_templates`: built, logged, and saved
back into the file it came from when that file is writable.

Files are ``.npz`` written atomically (temp file + rename) with a format version, the mesh's content
hash and the build config; a stale, foreign or corrupt file raises :class:`ReferenceSetError`.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from pixie.geometry.camera import backproject, backproject_depth, invert_T, transform_points
from pixie.config import PixieConfig, RefsConfig, ShapeConfig
from pixie.references.encode import check_encodings, encode
from pixie.errors import ReferenceSetError
from pixie.features import Features, pack_features, unpack_features
from pixie.geometry.rotations import nearest_pixel
from pixie.geometry.mesh import Mesh
from pixie.threads import one_thread_while_forking
from pixie.geometry.render import Renderer
from pixie.references.templates import ContourTemplates, build_templates
from pixie.references.views import camera_distance, roll, roll_angles, square_crop_K, start_K, view_poses


class _Decoded:
    """A field stored in a compact form and decoded on first access: given a callable (``load_reference_set``
    gives the depth and normals so, ~1.3 s of a 20 MB set's load when inference never reads them), the
    attribute is its result, computed once; given an array, the array."""

    def __set_name__(self, owner, name: str) -> None:
        self.slot = "_decoded_" + name

    def __get__(self, obj, objtype=None):
        if obj is None:
            raise AttributeError(self.slot)  # no class-level default: the dataclass field stays required
        value = obj.__dict__[self.slot]
        if value is None:
            value = obj.__dict__[self.slot] = obj.__dict__[self.slot + "_stored"]()
        return value

    def __set__(self, obj, value) -> None:
        lazy = callable(value)
        obj.__dict__[self.slot + "_stored"] = value if lazy else None  # the stored form, saved back unchanged
        obj.__dict__[self.slot] = None if lazy else value

    @staticmethod
    def stored(obj, name: str):
        """The stored (undecoded) form of field ``name``, or None when it was set as an array."""
        return obj.__dict__.get(f"_decoded_{name}_stored")


@dataclass
class ReferenceSet:
    """Offline references of one mesh.

    Attributes
    ----------
    poses : (V, R, 4, 4) T_cam_from_obj of every view and roll
    Ks : (V, R, 3, 3) intrinsics of each object-centred ``size`` x ``size`` reference image
    K_start : (3, 3) the uncropped rendering intrinsics
    canonical : (V,) bool, True for the 6 box-aligned views
    depth : (V, S, S) float32, roll 0, mm (0 = background)
    normals : (V, S, S, 3) float32, roll 0, camera frame
    encodings : name -> (V, S, S[, 3]) uint8 (roll 0) or (V, R, S, S[, 3]) when all rolls are kept
    features : key "matcher/encoding" -> packed arrays (:func:`pixie.features.pack_features`), one entry per
        (view, roll) in row-major order, plus "xyz" (object-space point of each keypoint, NaN off-mask).
        Read them with :meth:`features_for`, write them with :meth:`set_features`: the packing is this
        class's contract, nobody else's.
    """

    mesh: Mesh
    config: RefsConfig
    poses: np.ndarray
    Ks: np.ndarray
    K_start: np.ndarray
    canonical: np.ndarray
    depth: np.ndarray = _Decoded()
    normals: np.ndarray = _Decoded()
    encodings: dict[str, np.ndarray] = field(default_factory=dict)
    features: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    build_seconds: float = 0.0
    templates: dict[str, np.ndarray] | None = None  # contour templates as arrays (pixie.references.templates), when built
    source_path: Path | None = field(default=None, repr=False, compare=False)  # the file it was loaded from
    _xyz: np.ndarray | None = field(default=None, repr=False)

    @property
    def n_views(self) -> int:
        return self.poses.shape[0]

    @property
    def n_rolls(self) -> int:
        return self.poses.shape[1]

    @property
    def size(self) -> int:
        stored = _Decoded.stored(self, "depth")
        return stored.shape[1] if stored is not None else self.depth.shape[1]

    @property
    def masks(self) -> np.ndarray:
        return self.depth > 0

    @property
    def xyz(self) -> np.ndarray:
        """(V, S, S, 3) object-space points of roll 0, back-projected from depth with K then T⁻¹."""
        if self._xyz is None:
            out = np.zeros((*self.depth.shape, 3), np.float32)
            for i in range(self.n_views):
                Xc = backproject_depth(self.Ks[i, 0], self.depth[i])
                out[i] = np.where(self.masks[i][..., None], transform_points(invert_T(self.poses[i, 0]), Xc), 0)
            self._xyz = out
        return self._xyz

    def feature_key(self, matcher: str, encoding: str) -> str:
        return f"{matcher}/{encoding}"

    def has_features(self, matcher: str, encodings: list[str]) -> bool:
        return all(self.feature_key(matcher, e) in self.features for e in encodings)

    def feature_rolls(self, matcher: str, encoding: str) -> int:
        """How many rolls per view have stored features (all rolls, or 1 when only roll 0 was extracted)."""
        n = len(self.features[self.feature_key(matcher, encoding)]["feat_image_sizes"])
        return self.n_rolls if n == self.n_views * self.n_rolls else 1

    def set_features(self, matcher: str, encoding: str, features: Sequence[Features],
                     xyz: Sequence[np.ndarray]) -> None:
        """Store one :class:`~pixie.features.Features` and its keypoints' object XYZ ``(N, 3)`` per image,
        images in (view, roll) row-major order; replaces what was stored for (``matcher``, ``encoding``)."""
        if len(features) != len(xyz):
            raise ReferenceSetError(f"{len(features)} feature sets but {len(xyz)} XYZ arrays")
        packed = pack_features(features)
        packed["xyz"] = np.concatenate(xyz).astype(np.float32) if len(xyz) else np.zeros((0, 3), np.float32)
        self.features[self.feature_key(matcher, encoding)] = packed

    def features_for(self, matcher: str, encoding: str) -> tuple[list[Features], list[np.ndarray]]:
        """The stored features of ``matcher`` on ``encoding`` images and each keypoint's object XYZ.

        Returns
        -------
        features : list of Features
            One per stored image, (view, roll) row-major: ``V * feature_rolls`` entries.
        xyz : list of (N_k, 3) float32
            Object-space point (mm) under each keypoint of ``features[k]``; NaN off the object.

        Raises
        ------
        ReferenceSetError
            When the set holds no such features (``add_features`` extracts them), or they are inconsistent.
        """
        key = self.feature_key(matcher, encoding)
        if key not in self.features:
            raise ReferenceSetError(f"reference set has no {matcher} features of {encoding!r} images "
                                    f"(stored: {sorted(self.features) or 'none'})")
        packed = self.features[key]
        feats = unpack_features(packed)
        if "xyz" not in packed or len(packed["xyz"]) != sum(len(f) for f in feats):
            raise ReferenceSetError(f"features {key!r} lack the XYZ of their keypoints: rebuild the set")
        offs = np.cumsum([0] + [len(f) for f in feats])
        return feats, [packed["xyz"][offs[k]:offs[k + 1]] for k in range(len(feats))]


def build_reference_set(
    mesh: Mesh,
    config: RefsConfig | None = None,
    matcher=None,
    progress: Callable[[int, int], None] | None = None,
    workers: int = 1,
    shape: ShapeConfig | None = None,
) -> ReferenceSet:
    """Render, encode and (optionally) extract matcher features for every view and roll; build the contour
    templates of the shape cues.

    Parameters
    ----------
    mesh : Mesh
    config : RefsConfig (or a PixieConfig, whose ``refs`` section is used)
    matcher : pixie.matching Matcher, optional
        When given, features of every encoded image (all rolls) are extracted and stored.
    progress : callable(done, total), optional
        Called after each view with (done, total): the views, then (with ``shape.enabled``) the contour templates.
    workers : int
        Processes that render and encode in parallel (views are independent); features are
        extracted in this process while the workers render the next views.
    shape : ShapeConfig, optional
        The shape cues' settings: their contour templates are built (and saved with the set) when
        ``shape.enabled``. Default: the ``shape`` section of a PixieConfig ``config``; with a RefsConfig, none
        (a PoseEstimator with shape cues then builds them in memory, with an INFO message).
    """
    if shape is None:
        shape = config.shape if isinstance(config, PixieConfig) else ShapeConfig(enabled=False)
    if not isinstance(shape, ShapeConfig):
        raise ReferenceSetError(f"shape must be a ShapeConfig, got {type(shape).__name__}")
    if not isinstance(mesh, Mesh):
        raise ReferenceSetError(f"build_reference_set needs a pixie Mesh (pixie.load_mesh), got {type(mesh).__name__}")
    cfg = config.refs if isinstance(config, PixieConfig) else (config or RefsConfig())
    if not isinstance(cfg, RefsConfig):
        raise ReferenceSetError(f"config must be a RefsConfig or PixieConfig, got {type(config).__name__}")
    if isinstance(workers, bool) or not isinstance(workers, int):
        raise ReferenceSetError(f"workers must be a whole number, got {workers!r}")
    encs = check_encodings(cfg.encodings)
    t0 = time.perf_counter()
    S = int(cfg.size)
    K0 = start_K(S, cfg.focal_factor)
    dist = camera_distance(mesh.bounding_radius, K0[0, 0], S, fill=1.0 / cfg.crop_pad)
    base = view_poses(mesh.center, dist, cfg.n_fibonacci, cfg.canonical)
    V, R = len(base), max(int(cfg.rotations), 1)
    total = V + (int(shape.views) if shape.enabled else 0)  # progress counts the views, then the contour templates
    poses = np.zeros((V, R, 4, 4))
    Ks = np.zeros((V, R, 3, 3))
    depth = np.zeros((V, S, S), np.float32)
    normals = np.zeros((V, S, S, 3), np.float32)
    enc_store: dict[str, list] = {e: [] for e in encs}
    feats: dict[str, list] = {e: [] for e in encs}
    xyzs: dict[str, list] = {e: [] for e in encs}
    n_render = rolls_to_render(cfg, features=matcher is not None, images=cfg.store_rotated_encodings)
    for i, view in enumerate(_iter_rendered_views(mesh, cfg, base, K0, workers, n_render)):
        poses[i], Ks[i] = view["poses"], view["Ks"]
        depth[i], normals[i] = view["depth"][0], view["normals0"]
        for e in encs:
            imgs = view["enc"][e]
            enc_store[e].append(imgs if cfg.store_rotated_encodings else imgs[0])
            if matcher is None:
                continue
            for j in range(R if cfg.feature_rolls == "all" else 1):
                f = matcher.extract(imgs[j], mask=view["depth"][j] > 0)
                feats[e].append(f)
                xyzs[e].append(keypoint_xyz_from_depth(view["depth"][j], Ks[i, j], poses[i, j], f.keypoints))
        if progress:
            progress(i + 1, total)
    refs = ReferenceSet(
        mesh=mesh, config=cfg, poses=poses, Ks=Ks, K_start=K0,
        canonical=np.arange(V) < (6 if cfg.canonical else 0),
        depth=depth, normals=normals,
        encodings={e: np.stack(v) for e, v in enc_store.items()},
    )
    if matcher is not None:
        _store_features(refs, matcher.name, feats, xyzs)
    if shape.enabled:  # the contour templates continue the same progress count (no silent seconds after the views)
        tp = None if progress is None else (lambda j, n: progress(V + j, total))
        refs.templates = _build_templates(refs.mesh, shape, tp).to_arrays()
    refs.build_seconds = time.perf_counter() - t0
    return refs


def _build_templates(mesh: Mesh, shape: ShapeConfig,
                     progress: Callable[[int, int], None] | None = None) -> ContourTemplates:
    return build_templates(mesh, shape.views, shape.size, shape.points, progress=progress)


def _store_features(refs: ReferenceSet, matcher_name: str, feats: dict, xyzs: dict) -> None:
    for e in feats:
        refs.set_features(matcher_name, e, feats[e], xyzs[e])


_WORKER_STATE: dict = {}


def rolls_to_render(cfg: RefsConfig, features: bool, images: bool) -> int:
    """How many rolls of each view must be rendered: all of them, or only roll 0.

    Roll 0 is always rendered (its depth and normals are stored). The other rolls are rendered only
    when their images are used: to extract features of every roll, or to store their encodings.
    Poses and intrinsics of every roll are computed either way.

    Parameters
    ----------
    cfg : RefsConfig
    features : bool
        Matcher features are extracted (of every roll when ``cfg.feature_rolls == 'all'``).
    images : bool
        The encodings of every roll are kept.

    Returns
    -------
    int
        ``cfg.rotations`` (at least 1) or 1.
    """
    n_rolls = max(int(cfg.rotations), 1)
    return n_rolls if images or (features and cfg.feature_rolls == "all") else 1


def _render_view(mesh: Mesh, cfg: RefsConfig, T_base: np.ndarray, K0: np.ndarray,
                 renderer: Renderer | None = None, n_render: int | None = None) -> dict:
    """Pose every roll of one view and render and encode the first ``n_render`` (runs in a worker process).

    Returns
    -------
    dict
        ``poses`` (R, 4, 4) and ``Ks`` (R, 3, 3) of all R rolls; ``depth`` (n_render, S, S),
        ``normals0`` (S, S, 3) of roll 0 and ``enc`` name -> (n_render, S, S[, 3]) of the rendered rolls.
    """
    renderer = renderer or Renderer(mesh, smooth_normals=cfg.smooth_normals)
    S, R = int(cfg.size), max(int(cfg.rotations), 1)
    n_render = R if n_render is None else min(max(int(n_render), 1), R)
    out = {"poses": np.zeros((R, 4, 4)), "Ks": np.zeros((R, 3, 3)), "depth": np.zeros((n_render, S, S), np.float32),
           "enc": {e: [] for e in cfg.encodings}}
    for j, a in enumerate(roll_angles(R)):
        T = roll(T_base, a)
        K, box = square_crop_K(K0, T, mesh.vertices, S, cfg.crop_pad)
        out["poses"][j], out["Ks"][j] = T, K
        if j >= n_render:
            continue
        # Rays only inside the box of the projected vertices (= the silhouette's box).
        pad = (box[2] - box[2] / cfg.crop_pad) / 2 * box[3]
        lo, hi = int(np.floor(pad)) - 2, int(np.ceil(S - pad)) + 2
        r = renderer.render(T, K, S, S, roi=(max(lo, 0), max(lo, 0), min(hi, S), min(hi, S)))
        out["depth"][j] = r.depth
        if j == 0:
            out["normals0"] = r.normals
        for e in cfg.encodings:
            out["enc"][e].append(encode(e, r.depth, r.normals, r.mask))
    out["enc"] = {e: np.stack(v) for e, v in out["enc"].items()}
    return out


def _die_with_parent(parent_pid: int) -> None:
    """Make this worker process die with its parent (Linux: PR_SET_PDEATHSIG) and leave Ctrl-C to the parent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and stops the pool
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # blocked since the fork (_sigint_held): now ignored
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: workers end when the pool's pipe closes
        pass
    if os.getppid() != parent_pid:  # the parent died before the line above
        os._exit(1)


@contextlib.contextmanager
def _sigint_held():
    """Hold Ctrl-C (SIGINT blocked, not lost) while the pool forks: a worker inherits the block and ignores SIGINT
    before unblocking it (:func:`_die_with_parent`), so a Ctrl-C that reaches the process group in the moment after a
    fork no longer raises KeyboardInterrupt inside a worker (a traceback on stderr); the parent gets it on leaving."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _worker_init(mesh: Mesh, cfg: RefsConfig, K0: np.ndarray, n_render: int | None, parent_pid: int) -> None:
    _die_with_parent(parent_pid)
    _WORKER_STATE.update(mesh=mesh, cfg=cfg, K0=K0, n_render=n_render,
                         renderer=Renderer(mesh, smooth_normals=cfg.smooth_normals))


def _worker_render(T_base: np.ndarray) -> dict:
    st = _WORKER_STATE
    return _render_view(st["mesh"], st["cfg"], T_base, st["K0"], st["renderer"], st["n_render"])


def _iter_rendered_views(mesh: Mesh, cfg: RefsConfig, base: np.ndarray, K0: np.ndarray, workers: int,
                         n_render: int | None = None):
    """Yield the views in order (first ``n_render`` rolls rendered), from ``workers`` processes (or inline for 1)."""
    if workers <= 1:
        renderer = Renderer(mesh, smooth_normals=cfg.smooth_normals)
        for T in base:
            yield _render_view(mesh, cfg, T, K0, renderer, n_render)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    ctx = mp.get_context("fork")
    init_args = (mesh, cfg, K0, n_render, os.getpid())
    ex = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init, initargs=init_args)
    try:
        with one_thread_while_forking(), _sigint_held():  # map() forks the workers now: one OpenCV thread each
            views = ex.map(_worker_render, list(base), chunksize=1)
        yield from views
    finally:  # on Ctrl-C or an error: drop the queued views instead of rendering them all first
        ex.shutdown(wait=True, cancel_futures=True)


def keypoint_xyz_from_depth(depth: np.ndarray, K: np.ndarray, T_cam_from_obj: np.ndarray,
                            keypoints: np.ndarray) -> np.ndarray:
    """Object-space point under each keypoint's nearest pixel (back-projected depth); NaN on background."""
    if len(keypoints) == 0:
        return np.zeros((0, 3), np.float32)
    c, r = nearest_pixel(keypoints, depth.shape)
    z = depth[r, c].astype(np.float64)
    X = transform_points(invert_T(T_cam_from_obj), backproject(K, np.stack([c, r], 1).astype(np.float64), z))
    X[z <= 0] = np.nan
    return X.astype(np.float32)


def add_features(refs: ReferenceSet, matcher, encodings: list[str] | None = None,
                 progress: Callable[[int, int], None] | None = None, workers: int = 1) -> None:
    """Extract (and store in ``refs``) features of ``matcher`` for encodings not yet present.

    Rotated references are re-rendered from the stored poses (never resampled).
    """
    encs = [e for e in (encodings or refs.config.encodings) if refs.feature_key(matcher.name, e) not in refs.features]
    if not encs:
        return
    cfg = RefsConfig(**{**refs.config.__dict__, "encodings": encs})
    feats: dict[str, list] = {e: [] for e in encs}
    xyzs: dict[str, list] = {e: [] for e in encs}
    n_render = rolls_to_render(cfg, features=True, images=False)  # only features are added
    for i, view in enumerate(_iter_rendered_views(refs.mesh, cfg, refs.poses[:, 0], refs.K_start, workers, n_render)):
        for e in encs:
            for j in range(refs.n_rolls if refs.config.feature_rolls == "all" else 1):
                f = matcher.extract(view["enc"][e][j], mask=view["depth"][j] > 0)
                feats[e].append(f)
                xyzs[e].append(keypoint_xyz_from_depth(view["depth"][j], view["Ks"][j], view["poses"][j], f.keypoints))
        if progress:
            progress(i + 1, refs.n_views)
    _store_features(refs, matcher.name, feats, xyzs)


def encoding_images(refs: ReferenceSet, name: str) -> np.ndarray:
    """Roll-0 images (V, S, S[, 3]) of one encoding, derived from the stored D and N when not stored."""
    if name not in refs.encodings:
        imgs = [encode(name, refs.depth[i], refs.normals[i], refs.depth[i] > 0) for i in range(refs.n_views)]
        refs.encodings[name] = np.stack(imgs)
    imgs = refs.encodings[name]
    return imgs[:, 0] if imgs.ndim >= 4 and imgs.shape[1] == refs.n_rolls and refs.config.store_rotated_encodings else imgs
