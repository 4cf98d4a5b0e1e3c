"""Geometry shared by every stage (no pixie imports above ``errors``).

Modules (imports go down this list): ``rotations`` (rotations, nearest-pixel lookups, the one image / mask rule),
``camera`` (pinhole camera, rigid poses, the one K parser and the one crop-intrinsics helper), ``mesh`` (meshes in
mm), ``collide`` (whether parts pass through each other), ``render`` (ray casting). The package ``__init__`` imports nothing: import the module.
"""
