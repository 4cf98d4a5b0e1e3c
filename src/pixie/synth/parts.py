"""Procedural mechanical parts for synthetic training data (CSG with manifold3d).

Every part is deterministic from an integer seed: :func:`random_part` picks a family (plate, bracket,
flange, gear, shaft, housing, profile, block, or a smooth 'organic' union of ellipsoids) and its parameters, builds it as a solid with boolean
operations (boxes, cylinders, holes, counterbores, ribs, chamfer / fillet approximations by hulls of
bevelled shapes) and returns a :class:`pixie.geometry.mesh.Mesh` in millimetres whose vertices are split at
sharp creases (> 30°), so smooth vertex normals stay flat on planar faces and round on cylinders.

No mesh of any benchmark is used here; the wheels installed with pixie (trimesh 5.2) ship no test
models, so every training shape is procedural.
"""

from __future__ import annotations

import numpy as np

from pixie.geometry.mesh import Mesh, from_arrays

FAMILIES = ("plate", "bracket", "flange", "gear", "shaft", "housing", "profile", "block", "organic")


def _m3():
    import manifold3d as m3

    return m3


def _box(sx, sy, sz, center=True):
    return _m3().Manifold.cube([float(sx), float(sy), float(sz)], center)


def _cyl(h, r, r2=None, segs=48, center=True):
    return _m3().Manifold.cylinder(float(h), float(r), float(r if r2 is None else r2), int(segs), center)


def _chamfer_box(rng, sx, sy, sz):
    """Box with its vertical edges chamfered or rounded (hull of corner cylinders / inset boxes)."""
    m3 = _m3()
    r = float(rng.uniform(0.05, 0.25)) * min(sx, sy)
    kind = rng.integers(3)
    if kind == 0 or r < 0.5:
        return _box(sx, sy, sz)
    segs = 4 if kind == 1 else 24  # 4 segments: a 45° chamfer; 24: a fillet
    corners = []
    for x in (-1, 1):
        for y in (-1, 1):
            c = _cyl(sz, r, segs=segs)
            if segs == 4:
                c = c.rotate([0, 0, 45])
            corners.append(c.translate([x * (sx / 2 - r), y * (sy / 2 - r), 0]))
    return m3.Manifold.batch_hull(corners)


def _holes(rng, part, sx, sy, sz, n_max=6, axis_z=True):
    """Through holes (some counterbored) on the top face of a ``sx x sy`` footprint."""
    n = int(rng.integers(0, n_max + 1))
    rmax = 0.18 * min(sx, sy)
    for _ in range(n):
        r = float(rng.uniform(0.04, 1.0)) * rmax
        x = float(rng.uniform(-sx / 2 + r * 1.6, sx / 2 - r * 1.6)) if sx > 3.2 * r else 0.0
        y = float(rng.uniform(-sy / 2 + r * 1.6, sy / 2 - r * 1.6)) if sy > 3.2 * r else 0.0
        h = _cyl(sz * 3, r, segs=int(rng.choice([16, 32, 48])))
        part = part - h.translate([x, y, 0])
        if rng.random() < 0.3:
            cb = _cyl(sz * 0.4, r * 1.7, segs=32).translate([x, y, sz / 2])
            part = part - cb
    return part


def _plate(rng, s):
    sx, sy = s * rng.uniform(0.6, 1.0), s * rng.uniform(0.3, 0.9)
    sz = s * rng.uniform(0.06, 0.25)
    p = _chamfer_box(rng, sx, sy, sz)
    if rng.random() < 0.5:  # pocket or slot
        px, py = sx * rng.uniform(0.2, 0.5), sy * rng.uniform(0.15, 0.4)
        pocket = _box(px, py, sz).translate([rng.uniform(-0.2, 0.2) * sx, rng.uniform(-0.2, 0.2) * sy, sz * 0.55])
        p = p - pocket
    if rng.random() < 0.5:  # boss
        r = min(sx, sy) * rng.uniform(0.1, 0.25)
        p = p + _cyl(sz * rng.uniform(1.0, 3.0), r, segs=48).translate([rng.uniform(-0.25, 0.25) * sx, 0, sz / 2])
    return _holes(rng, p, sx, sy, sz)


def _bracket(rng, s):
    """L (or T) profile with holes in both legs and optional triangular ribs."""
    a, b = s * rng.uniform(0.5, 1.0), s * rng.uniform(0.4, 0.9)
    w = s * rng.uniform(0.3, 0.8)
    t = s * rng.uniform(0.06, 0.15)
    base = _holes(rng, _box(a, w, t), a, w, t, n_max=4).translate([a / 2, 0, t / 2])
    leg = _holes(rng, _box(b, w, t), b, w, t, n_max=4)
    leg = leg.rotate([0, -90, 0]).translate([t / 2, 0, b / 2])
    p = base + leg
    if rng.random() < 0.7:
        m3 = _m3()
        tri = m3.CrossSection([[[0.0, 0.0], [a * 0.6, 0.0], [0.0, b * 0.6]]])
        rt = t * rng.uniform(0.5, 1.0)
        rib = m3.Manifold.extrude(tri, rt).rotate([90, 0, 0])
        for y in ([0.0] if rng.random() < 0.5 else [-w / 2 + rt / 2, w / 2 - rt / 2]):
            p = p + rib.translate([t * 0.99, y + rt / 2, t * 0.99])
    if rng.random() < 0.3:  # T: a second leg on the other side
        p = p + leg.translate([a - t, 0, 0])
    return p


def _flange(rng, s):
    R = s / 2 * rng.uniform(0.7, 1.0)
    t = s * rng.uniform(0.06, 0.2)
    p = _cyl(t, R, segs=int(rng.choice([6, 8, 64, 96])))
    hub_r = R * rng.uniform(0.3, 0.6)
    hub_h = s * rng.uniform(0.15, 0.5)
    p = p + _cyl(hub_h, hub_r, segs=64).translate([0, 0, hub_h / 2])
    bore = hub_r * rng.uniform(0.3, 0.8)
    p = p - _cyl(s * 3, bore, segs=48)
    n = int(rng.integers(3, 9))
    rb = R * rng.uniform(0.05, 0.12)
    rc = 0.5 * (hub_r + R)
    for k in range(n):
        ang = 2 * np.pi * k / n
        p = p - _cyl(t * 3, rb, segs=24).translate([rc * np.cos(ang), rc * np.sin(ang), 0])
    if rng.random() < 0.5:  # keyway
        p = p - _box(bore * 0.5, bore * 1.2, s * 3).translate([bore, 0, 0])
    return p


def _gear(rng, s):
    m3 = _m3()
    R = s / 2 * rng.uniform(0.7, 1.0)
    n = int(rng.integers(8, 30))
    depth = R * rng.uniform(0.08, 0.18)
    pts = []
    for k in range(n):
        for frac, rad in ((0.0, R - depth), (0.2, R - depth), (0.3, R), (0.7, R), (0.8, R - depth)):
            a = 2 * np.pi * (k + frac) / n
            pts.append([rad * np.cos(a), rad * np.sin(a)])
    t = s * rng.uniform(0.1, 0.35)
    g = m3.Manifold.extrude(m3.CrossSection([pts]), t).translate([0, 0, -t / 2])
    bore = R * rng.uniform(0.1, 0.35)
    g = g - _cyl(s * 3, bore, segs=48)
    if rng.random() < 0.5:
        g = g + _cyl(t * rng.uniform(1.5, 2.5), bore * rng.uniform(1.6, 2.2), segs=48) - _cyl(s * 3, bore, segs=48)
    if rng.random() < 0.5:  # lightening holes
        k = int(rng.integers(3, 7))
        rr = (R - depth) * 0.6
        for i in range(k):
            a = 2 * np.pi * i / k
            g = g - _cyl(t * 3, (R - depth) * 0.15, segs=32).translate([rr * np.cos(a), rr * np.sin(a), 0])
    return g


def _shaft(rng, s):
    """Stepped shaft: a stack of cylinders, with grooves, flats and chamfered ends."""
    L = s * rng.uniform(0.8, 1.0)
    n = int(rng.integers(2, 5))
    lens = rng.dirichlet(np.ones(n)) * L
    rmax = s * rng.uniform(0.1, 0.3)
    z = -L / 2
    p = None
    for i in range(n):
        r = rmax * rng.uniform(0.45, 1.0)
        segs = 6 if rng.random() < 0.15 else 64
        c = _cyl(lens[i], r, r * (0.85 if rng.random() < 0.3 else 1.0), segs=segs, center=False).translate([0, 0, z])
        p = c if p is None else p + c
        z += lens[i]
    if rng.random() < 0.5:
        p = p - _box(rmax * 3, rmax * 3, L * 0.3).translate([rmax * 2.6, 0, L * rng.uniform(-0.3, 0.3)])
    if rng.random() < 0.5:  # cross hole
        p = p - _cyl(rmax * 5, rmax * 0.25, segs=24).rotate([90, 0, 0]).translate([0, 0, L * rng.uniform(-0.4, 0.4)])
    return p.rotate([0, 90, 0])


def _housing(rng, s):
    """Hollow box (a shell) with an open side, mounting ears and holes."""
    sx, sy, sz = s * rng.uniform(0.5, 1.0), s * rng.uniform(0.4, 0.9), s * rng.uniform(0.25, 0.6)
    wall = min(sx, sy, sz) * rng.uniform(0.08, 0.2)
    p = _chamfer_box(rng, sx, sy, sz)
    p = p - _box(sx - 2 * wall, sy - 2 * wall, sz).translate([0, 0, wall])
    if rng.random() < 0.6:
        ear = _holes(rng, _box(sx * 0.25, sy * 0.3, wall), sx * 0.25, sy * 0.3, wall, n_max=1)
        p = p + ear.translate([sx / 2 + sx * 0.12, 0, -sz / 2 + wall / 2])
        p = p + ear.translate([-sx / 2 - sx * 0.12, 0, -sz / 2 + wall / 2])
    if rng.random() < 0.5:
        r = min(sy, sz) * rng.uniform(0.1, 0.3)
        p = p - _cyl(sx * 3, r, segs=48).rotate([0, 90, 0])
    return p


def _profile(rng, s):
    """Extruded U / T / I / Z section with holes through the web."""
    m3 = _m3()
    w, h = s * rng.uniform(0.2, 0.5), s * rng.uniform(0.2, 0.5)
    t = min(w, h) * rng.uniform(0.12, 0.3)
    kind = rng.choice(["U", "T", "I", "Z"])
    rects = {
        "U": [(0, 0, w, t), (0, 0, t, h), (w - t, 0, t, h)],
        "T": [(0, h - t, w, t), (w / 2 - t / 2, 0, t, h)],
        "I": [(0, 0, w, t), (0, h - t, w, t), (w / 2 - t / 2, 0, t, h)],
        "Z": [(0, 0, w / 2 + t / 2, t), (w / 2 - t / 2, 0, t, h), (w / 2 - t / 2, h - t, w / 2 + t / 2, t)],
    }[kind]
    cs = None
    for x, y, a, b in rects:
        r = m3.CrossSection.square([float(a), float(b)]).translate([float(x), float(y)])
        cs = r if cs is None else cs + r
    L = s * rng.uniform(0.6, 1.0)
    p = m3.Manifold.extrude(cs, L).translate([-w / 2, -h / 2, -L / 2])
    for _ in range(int(rng.integers(0, 4))):
        p = p - _cyl(s * 3, t * rng.uniform(0.3, 0.8), segs=24).rotate([90, 0, 0]).translate(
            [rng.uniform(-w / 3, w / 3), 0, rng.uniform(-L / 2.5, L / 2.5)])
    if rng.random() < 0.5:  # mitred end
        p = p - _box(s * 2, s * 2, s).rotate([0, 45, 0]).translate([0, 0, L / 2 + s * 0.3])
    return p


def _block(rng, s):
    """Random union of boxes and cylinders with steps, then holes and a chamfered / filleted edge."""
    p = _chamfer_box(rng, s * rng.uniform(0.5, 1.0), s * rng.uniform(0.4, 0.8), s * rng.uniform(0.2, 0.6))
    for _ in range(int(rng.integers(1, 4))):
        if rng.random() < 0.5:
            q = _box(*(s * rng.uniform(0.15, 0.5, 3)))
        else:
            q = _cyl(s * rng.uniform(0.1, 0.6), s * rng.uniform(0.05, 0.25), segs=int(rng.choice([6, 8, 48])))
            q = q.rotate([float(rng.choice([0, 90])), float(rng.choice([0, 90])), 0])
        q = q.translate(list(s * rng.uniform(-0.3, 0.3, 3)))
        p = p + q if rng.random() < 0.7 else p - q
    if rng.random() < 0.5:  # a bevel cut along one edge
        p = p - _box(s, s * 0.3, s * 0.3).rotate([45, 0, 0]).translate([0, s * 0.4, s * 0.3])
    if p.is_empty() or p.volume() < 1e-3 * s ** 3:
        p = _box(s * 0.6, s * 0.5, s * 0.4)
    return _holes(rng, p, s * 0.5, s * 0.4, s * 2, n_max=3)


def _organic(rng, s):
    """Smooth free-form body: union of 3-7 ellipsoids (toys, handles, castings), a few with holes."""
    m3 = _m3()
    p = None
    for i in range(int(rng.integers(3, 8))):
        e = m3.Manifold.sphere(1.0, 32).scale(list(s * rng.uniform(0.1, 0.3, 3)))
        e = e.rotate(list(rng.uniform(0, 180, 3))).translate(list(s * rng.uniform(-0.25, 0.25, 3)))
        p = e if p is None else p + e
    if rng.random() < 0.3:
        p = p - _cyl(s * 3, s * rng.uniform(0.03, 0.08), segs=24).rotate(list(rng.uniform(0, 180, 3)))
    return p


_BUILDERS = {
    "plate": _plate, "bracket": _bracket, "flange": _flange, "gear": _gear,
    "shaft": _shaft, "housing": _housing, "profile": _profile, "block": _block, "organic": _organic,
}


def build_part(family: str, seed: int, size_mm: float | None = None) -> Mesh:
    """One part of ``family`` from ``seed``; ``size_mm`` is its rough diameter (random 60-220 mm if None)."""
    rng = np.random.default_rng([int(seed), FAMILIES.index(family)])
    s = float(size_mm) if size_mm is not None else float(rng.uniform(60.0, 220.0))
    solid = _BUILDERS[family](rng, s)
    if solid.is_empty() or solid.num_tri() < 4:
        solid = _box(s * 0.6, s * 0.5, s * 0.4)
    mesh = solid.to_mesh()
    v = np.asarray(mesh.vert_properties)[:, :3].astype(np.float64)
    f = np.asarray(mesh.tri_verts).astype(np.int64)
    v, f = split_creases(v, f, angle_deg=30.0)
    v = v - 0.5 * (v.min(0) + v.max(0))  # bounding-box centre at the origin
    return from_arrays(v, f, name=f"{family}_{seed}")


def random_part(seed: int, families: tuple[str, ...] = FAMILIES) -> Mesh:
    """A part of a random family (deterministic from ``seed``)."""
    rng = np.random.default_rng([int(seed), 7919])
    return build_part(str(families[int(rng.integers(len(families)))]), seed)


def split_creases(v: np.ndarray, f: np.ndarray, angle_deg: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """Duplicate vertices along edges sharper than ``angle_deg`` (smooth shading groups)."""
    import trimesh

    tm = trimesh.Trimesh(v, f, process=False)
    try:
        sm = trimesh.graph.smooth_shade(tm, angle=np.radians(angle_deg))
        return np.asarray(sm.vertices, np.float64), np.asarray(sm.faces, np.int64)
    except Exception:  # noqa: BLE001 - fall back to flat (one vertex per face corner)
        return v[f].reshape(-1, 3), np.arange(len(f) * 3).reshape(-1, 3)
