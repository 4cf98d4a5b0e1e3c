"""Everything inference needs about one object, built offline.

Modules (imports go down this list): ``views`` (reference viewpoints and crops), ``encode`` (depth / normal /
shading / edge encodings), ``templates`` (contour templates of the shape cues), ``set`` (``ReferenceSet``: build,
save, load, upgrade). The package ``__init__`` imports nothing: import the module.
"""
