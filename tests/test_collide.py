"""Whether the parts of an assembly pass through each other (pixie.geometry.collide), against hand-computed
overlaps of boxes."""

from __future__ import annotations

import numpy as np
import pytest

from pixie.geometry.collide import collides, max_overlap_depth, overlap_depth, part_solids
from pixie.geometry.mesh import from_arrays


def _boxes(boxes, open_part: int | None = None):
    """A mesh with one closed box per part (``open_part``: that box without its top face)."""
    import trimesh

    V, F, P = [], [], []
    for k, (lo, hi) in enumerate(boxes):
        b = trimesh.creation.box(bounds=[lo, hi])
        f = np.asarray(b.faces, np.int64)
        if k == open_part:  # drop the two triangles of the top face
            top = np.all(np.asarray(b.vertices)[f][:, :, 2] > hi[2] - 1e-9, axis=1)
            f = f[~top]
        F.append(f + sum(len(v) for v in V))
        V.append(np.asarray(b.vertices, np.float64))
        P.append(np.full(len(f), k))
    return from_arrays(np.vstack(V), np.vstack(F)).with_parts(np.concatenate(P), [f"p{k}" for k in range(len(boxes))])


def _shift(dx=0.0, dy=0.0, dz=0.0):
    M = np.eye(4)
    M[:3, 3] = dx, dy, dz
    return M


def test_touching_boxes_do_not_overlap_and_a_box_pushed_in_overlaps_half_the_shared_thickness():
    # a 40 x 40 x 10 plate and a 10 mm cube standing on it
    mesh = _boxes([([-20, -20, -10], [20, 20, 0]), ([-5, -5, 0], [5, 5, 10])])
    s = part_solids(mesh)
    assert all(s.closed)
    assert max_overlap_depth(s) <= s.pitch  # touching: at most a voxel of contact
    for push in (4.0, 8.0):  # pushed down into the plate: the overlap is a push-thick slab, its depth push / 2
        d = overlap_depth(s, 1, 0, _shift(dz=-push))
        assert abs(d - push / 2) <= 1.5 * s.pitch, (push, d, s.pitch)
        assert collides(s, 1, _shift(dz=-push))
    assert not collides(s, 1, _shift(dz=+5.0))  # lifted: free
    assert not collides(s, 1, _shift(dx=12.0))  # slid along the plate: touching only


def test_the_assemblys_own_overlaps_set_the_tolerance():
    # a cube whose 2 mm-thick "stud" sits inside the box above (a solid CAD brick): that depth is allowed
    mesh = _boxes([([-20, -20, -10], [20, 20, 0]), ([-5, -5, -2], [5, 5, 10])])
    s = part_solids(mesh)
    own = max_overlap_depth(s)
    assert abs(own - 1.0) <= 1.5 * s.pitch
    assert s.tolerance == pytest.approx(1.5 * max(own, s.pitch))
    assert not collides(s, 1, _shift(dx=3.0))  # the same overlap elsewhere: a contact
    assert collides(s, 1, _shift(dz=-6.0))  # 8 mm deep: 4 mm overlap depth


def test_a_part_whose_surface_is_open_is_never_said_to_collide():
    mesh = _boxes([([-20, -20, -10], [20, 20, 0]), ([-5, -5, 0], [5, 5, 10])], open_part=1)
    s = part_solids(mesh)
    assert s.closed == [True, False]
    assert not collides(s, 1, _shift(dz=-8.0)) and not collides(s, 0, _shift(dz=8.0))


def test_a_mesh_without_parts_is_refused():
    import trimesh

    b = trimesh.creation.box(bounds=[[0, 0, 0], [10, 10, 10]])
    with pytest.raises(ValueError, match="no parts"):
        part_solids(from_arrays(np.asarray(b.vertices, np.float64), np.asarray(b.faces, np.int64)))
