"""Cues beside the matcher that score or refine pose hypotheses: where new edge refinement code lands.

Modules (imports go down this list): ``edges`` (edge / contour agreement), ``region`` (region-based
refinement), ``refine`` (render-at-estimate refinement), ``shape`` (the shape-cue stage: verification and
fusion), ``edge_photo`` (the photo's edges for alignment), ``edge_align`` (edge-based 6-DoF alignment, the
aligned fit), ``part_moves`` (parts' contours in a render, the 3D move search) and ``parts`` (the part report). They may import ``geometry``, ``references``, ``features``, ``matching``, ``pose`` and
``pipeline.query``; never ``pipeline.estimator``, ``eval`` or ``app``. The ``__init__`` imports nothing.
"""
