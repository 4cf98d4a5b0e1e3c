"""pixie: zero-shot 6D object pose from one RGB photo and an untextured CAD model.

The pipeline follows the data flow, one module per stage::

    mesh -> render -> views/encode -> references -> matching -> pose -> refine -> estimator

Conventions (everywhere): OpenCV camera (x right, y down, z forward), millimetres,
``T_cam_from_obj`` 4x4 rigid transforms mapping object points to camera points, intrinsics ``K`` 3x3.
"""

__version__ = "0.1.0"

from pixie.errors import PixieError  # noqa: F401
from pixie.api import estimate_pose  # noqa: F401
from pixie.config import PixieConfig  # noqa: F401
from pixie.estimator import PoseEstimator  # noqa: F401
from pixie.mesh import load_mesh  # noqa: F401
from pixie.query import load_image  # noqa: F401
from pixie.references import build_reference_set, load_reference_set  # noqa: F401
