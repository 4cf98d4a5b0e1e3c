"""The per-photo pipeline.

Modules: ``query`` (photo loading, the per-query record's crops; low in the layers, the cues use it) and
``estimator`` (``PoseEstimator``: the stages in order). The ``__init__`` imports nothing: import the module.
"""
