"""From 2D-3D matches to scored pose hypotheses.

Modules (independent of each other): ``solve`` (the one lift, PnP +
RANSAC, background similarity, pair ranking, hypothesis scoring, box depth), ``plausibility`` (why a pose
contradicts its box and K), ``results`` (``Hypothesis``, ``PoseResult``). The ``__init__`` imports nothing.
"""
