"""Synthetic data: photo renderer, LEGO-like / mechanical assemblies, assembly defects, BOP scenes.

Modules
-------
photo       shaded RGB photos of posed meshes (materials, lights, shadows, backgrounds, degradation)
assemblies  parts (bricks on a stud grid, plates with holes, cylinders, brackets) and ``Assembly``
defects     defect operators: missing / shifted / rotated / wrong / extra part
scenes      BOP-format defects benchmark (``generate_defect_dataset``, Table I) and the tiny demo
            set (``tiny_defect_dataset``: two scenes at 320x240, a few seconds)
pairs       labelled photo-crop / geometry-reference pairs for matcher training (built on ``photo``)
"""

from pixie.synth.photo import (  # noqa: F401
    DirectionalLight,
    LightRig,
    Material,
    PhotoResult,
    degrade,
    random_background,
    render_rgb,
)
