"""pixie: zero-shot 6D object pose from one RGB photo and an untextured CAD model.

The public API is these few names (everything else is importable from its module, see ARCHITECTURE.md)::

    import pixie

    result = pixie.estimate_pose("part.stl", "photo.png", K="600,600,320,240", bbox=(x, y, w, h))   # one call

    from pixie.runner import make_matcher                    # or step by step:

    mesh = pixie.load_mesh("part.ply")                       # units auto-detected (mm unless under 2 units across)
    cfg = pixie.PixieConfig.from_preset("default")
    refs = pixie.build_reference_set(mesh, cfg.refs, matcher=make_matcher(cfg))  # or pixie.load_reference_set(path, mesh)
    est = pixie.PoseEstimator(refs, cfg)
    result = est.estimate(pixie.load_image("photo.png"), K, bbox=(x, y, w, h))
    result.T_cam_from_obj, result.failed                       # every error is a pixie.PixieError

The pipeline follows the data flow, one module per stage (ARCHITECTURE.md)::

    geometry (mesh, camera, render, views, encode) -> references -> matching -> pose -> refine -> estimator
    eval beside; runner, cli, demo on top

Conventions (everywhere): OpenCV camera (x right, y down, z forward), millimetres,
``T_cam_from_obj`` 4x4 rigid transforms mapping object points to camera points, intrinsics ``K`` 3x3.
"""

from pixie._version import __version__
from pixie.api import estimate_pose
from pixie.config import PixieConfig
from pixie.errors import PixieError
from pixie.estimator import PoseEstimator
from pixie.mesh import load_mesh
from pixie.query import load_image
from pixie.references import build_reference_set, load_reference_set

__all__ = [
    "__version__",
    "estimate_pose",
    "PixieConfig",
    "PixieError",
    "PoseEstimator",
    "build_reference_set",
    "load_image",
    "load_mesh",
    "load_reference_set",
]
