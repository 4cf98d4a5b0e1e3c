"""pixie: zero-shot 6D object pose from one RGB photo and an untextured CAD model.

The public API is these few names (everything else is importable from its module, see ARCHITECTURE.md)::

    import pixie

    result = pixie.estimate_pose("part.stl", "photo.png", K="600,600,320,240", bbox=(x, y, w, h))   # one call

    from pixie.app.runner import make_matcher                    # or step by step:

    mesh = pixie.load_mesh("part.ply")                       # units auto-detected (mm unless under 2 units across)
    cfg = pixie.PixieConfig.from_preset("default")
    refs = pixie.build_reference_set(mesh, cfg.refs, matcher=make_matcher(cfg), shape=cfg.shape)  # or load_reference_set
    est = pixie.PoseEstimator(refs, cfg)
    result = est.estimate(pixie.load_image("photo.png"), K, bbox=(x, y, w, h))
    result.T_cam_from_obj, result.failed                       # every error is a pixie.PixieError

The packages follow the data flow (ARCHITECTURE.md)::

    geometry (rotations, camera, mesh, render) -> references (views, encode, templates, set) -> matching
    -> pose (solve, plausibility, results) -> cues (edges, region, refine, shape) -> pipeline (query, estimator)
    eval, synth, train beside; viz; app (cluster, runner, batch, api, demo, cli) on top

Conventions (everywhere): OpenCV camera (x right, y down, z forward), millimetres,
``T_cam_from_obj`` 4x4 rigid transforms mapping object points to camera points, intrinsics ``K`` 3x3.
"""

from __future__ import annotations

from importlib import import_module

from pixie._version import __version__

# The facade loads its modules on first use (PEP 562): ``import pixie.threads`` (the ``pixie`` command's first
# step) then runs before numpy and torch are imported and can still set their thread environment.
_EXPORTS = {
    "estimate_pose": "pixie.app.api",
    "PixieConfig": "pixie.config",
    "PixieError": "pixie.errors",
    "PoseEstimator": "pixie.pipeline.estimator",
    "load_mesh": "pixie.geometry.mesh",
    "load_image": "pixie.pipeline.query",
    "build_reference_set": "pixie.references.set",
    "load_reference_set": "pixie.references.store",
    "find_objects": "pixie.pipeline.find",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'pixie' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
