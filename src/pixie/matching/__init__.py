"""Local features and 2D-2D matching between a query photo and reference renders.

The records it produces (:class:`~pixie.features.Features`, :class:`~pixie.features.Matches`) are defined
in :mod:`pixie.features`, below this package, so that reference sets can hold them without torch.

Matchers
    :func:`get_matcher` builds a :class:`Matcher` by backend name (see :func:`available_matchers`):

    ``aliked-nn``, ``disk-nn``, ``xfeat-nn``, ``sift-nn``, ``superpoint-nn``
        detector/descriptor + mutual nearest neighbour, with an optional spatial ``window`` (pixels), ratio
        test and minimum cosine similarity. One query against hundreds of references runs batched in torch
        (chunks of references, one matrix product each).
    ``aliked-lg``, ``disk-lg``
        kornia's LightGlue with the LightGlue weights of the cvg release.
    ``xfeat-lighterglue``
        XFeat + LighterGlue (kornia's LightGlue network in the XFeat configuration).
    ``minima-sp-lg``
        SuperPoint + the MINIMA LightGlue weights (``minima_lightglue.pth``) of the pixie paper.
    ``aliked-ft-nn``
        ALIKED-n16 (top-k detections) whose descriptors pass through the adapter fine-tuned on synthetic
        photo/geometry pairs (``pixie/data/weights/aliked_n16_geoadapter.pt``); optional reference-mask grid.

Every weight file is found by :func:`pixie.weights.resolve_weights`; nothing is downloaded unless
``allow_download`` is true (the default of :func:`get_matcher`, a user-facing loader).

Conventions: keypoints are ``(x, y)`` pixels with integer values at pixel centres (OpenCV and kornia);
images are checked by :func:`pixie.geometry.rotations.check_image`; masks are boolean ``HxW``.

Modules (imports go down this list): ``checkpoints`` (weight files, key remapping) -> ``base`` (extractor base
class, keypoint selection, reference banks) -> one module per extractor family (``aliked``, ``disk``,
``xfeat``, ``sift``, ``superpoint``) -> ``adapter`` (fine-tuned descriptor adapter on ALIKED) -> ``mnn``
(mutual nearest neighbour), ``lightglue`` -> ``registry`` (names -> matchers).
"""

from pixie.features import Features, Matches, matched_keypoints, pack_features, unpack_features
from pixie.matching.base import Extractor, RefBank, local_maxima, select_keypoints
from pixie.matching.checkpoints import remap_lightglue_state
from pixie.matching.lightglue import LightGlueAssigner, build_lightglue
from pixie.matching.mnn import MutualNNAssigner, mutual_nn_match_many
from pixie.matching.registry import (
    Matcher,
    available_matchers,
    backend_weights,
    get_matcher,
    matcher_from_config,
    resolve_device,
)
from pixie.matching.superpoint import SuperPointNet

__all__ = [
    "Features",
    "Matches",
    "RefBank",
    "Matcher",
    "Extractor",
    "pack_features",
    "unpack_features",
    "matched_keypoints",
    "mutual_nn_match_many",
    "get_matcher",
    "available_matchers",
    "backend_weights",
    "matcher_from_config",
    "resolve_device",
    "SuperPointNet",
    "MutualNNAssigner",
    "LightGlueAssigner",
    "build_lightglue",
    "remap_lightglue_state",
    "local_maxima",
    "select_keypoints",
]
