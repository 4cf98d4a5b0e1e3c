"""Synthetic data: photo renderer, LEGO-like / mechanical assemblies, assembly defects, BOP scenes.

Modules
-------
photo       shaded RGB photos of posed meshes (materials, lights, shadows, backgrounds, degradation)
assemblies  parts (bricks on a stud grid, plates with holes, cylinders, brackets) and ``Assembly``
defects     defect operators: missing / shifted / rotated / wrong / extra part
scenes      BOP-format scene generation (``generate_defect_dataset``) and the tiny demo set
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
