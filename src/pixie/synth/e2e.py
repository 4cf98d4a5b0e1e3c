"""The end-to-end scene of the test suite and ``bench/e2e_margin.py``: a procedural part, generic poses and
photo-like renders of it (a random colour per CAD face, Lambertian shading, a noisy background); and the edge
alignment's convergence trials (tests/test_edge_align.py, ``bench/align_rendered.py``): the part in a cluttered,
anti-aliased photo, optionally half covered by a plate, aligned from a turned start.

One home for what the tests and the bench share (no bench script imports the tests).
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from pixie.config import PixieConfig
from pixie.cues.edge_align import align, coarse_kwargs, coarse_levels, photo_edges
from pixie.geometry.camera import look_at, make_K, make_T, rotation_angle_deg
from pixie.geometry.mesh import from_arrays
from pixie.geometry.render import Renderer
from pixie.references.views import roll
from pixie.synth.photo import Material, random_background, render_rgb

__all__ = ["K_Q", "H", "W", "E2E_POSES", "e2e_config", "procedural_part", "cad_faces", "render_photo",
           "generic_pose", "pose_errors", "K_ALIGN", "facing_pose", "turned_pose", "clutter_photo", "plate_renderer",
           "align_trials"]

K_Q = make_K(600.0, 600.0, 319.5, 239.5)
H, W = 480, 640

# Generic viewpoints (azimuth, elevation, roll in degrees), fixed before looking at any result: three-quarter
# views from above and below the horizon, rolled both ways, spread over the sphere.
E2E_POSES = [(35.0, 35.0, 15.0), (-120.0, 25.0, -10.0), (200.0, 50.0, 30.0), (80.0, 20.0, 0.0),
             (150.0, -20.0, 60.0), (-40.0, 70.0, -30.0), (10.0, 5.0, 45.0), (260.0, -35.0, -60.0),
             (100.0, 60.0, 90.0), (-75.0, -10.0, 120.0), (170.0, 15.0, -150.0), (300.0, 40.0, 170.0),
             (45.0, -50.0, -20.0), (220.0, 75.0, 5.0)]


def e2e_config(matcher_name: str) -> PixieConfig:
    """The modest reference set of the end-to-end test (46 views at 256 px), the shipped ``default`` preset
    otherwise: roll-0 features, the query crop rotated, no render-at-estimate refinement, shape cues, alignment."""
    cfg = PixieConfig.from_preset("default")
    cfg.refs = replace(cfg.refs, n_fibonacci=40, rotations=8, size=256, encodings=["shade3_edges"])
    cfg.match.matcher = matcher_name
    return cfg


def procedural_part():
    """An asymmetric part, about 80 x 70 x 65 mm: a block with a cylinder, a peg and a notch.

    Boolean operations use manifold3d when installed; otherwise the parts are concatenated
    (interior faces are hidden from outside views, so rendering is the same up to the notch).
    """
    import trimesh

    box = trimesh.creation.box(extents=[80.0, 50.0, 30.0])
    cyl = trimesh.creation.cylinder(radius=12.0, height=40.0, sections=32)
    cyl.apply_translation([20.0, 5.0, 30.0])
    peg = trimesh.creation.box(extents=[10.0, 30.0, 10.0])
    peg.apply_translation([-25.0, 30.0, 0.0])
    notch = trimesh.creation.box(extents=[30.0, 30.0, 40.0])
    notch.apply_translation([-35.0, -20.0, 10.0])
    try:
        m = trimesh.boolean.union([box, cyl, peg], engine="manifold")
        m = trimesh.boolean.difference([m, notch], engine="manifold")
    except Exception:  # noqa: BLE001 - no boolean engine: a concatenation (no notch) is still asymmetric
        m = trimesh.util.concatenate([box, cyl, peg])
    return m


def cad_faces(mesh, crease_deg: float = 30.0) -> np.ndarray:
    """Label of each triangle's CAD face: triangles joined across edges flatter than ``crease_deg``."""
    import trimesh

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    edges = tm.face_adjacency[tm.face_adjacency_angles < np.radians(crease_deg)]
    return trimesh.graph.connected_component_labels(edges, node_count=len(mesh.faces))


def render_photo(mesh, T, K, seed: int = 0):
    """A synthetic 'photo': Lambertian shading x a random colour per CAD face on a noisy background.

    Returns the RGB image, the object's (x, y, w, h) box and its mask.
    """
    rng = np.random.default_rng(seed)
    r = Renderer(mesh).render(T, K, H, W)  # crease-aware normals: flat faces, smooth cylinder
    labels = cad_faces(mesh)
    albedo = rng.uniform(0.35, 1.0, (labels.max() + 1, 3))[labels]
    light = np.array([-0.4, -0.5, -1.0]) / np.linalg.norm([-0.4, -0.5, -1.0])
    lam = np.clip(r.normals @ light.astype(np.float32), 0.0, 1.0)
    img = cv2.GaussianBlur(rng.normal(110.0, 35.0, (H, W, 3)), (0, 0), 1.5)
    colour = albedo[np.maximum(r.tri_ids, 0)] * (0.25 + 0.75 * lam[..., None]) * 255.0
    img[r.mask] = colour[r.mask]
    img = np.clip(img + rng.normal(0.0, 4.0, img.shape), 0, 255).astype(np.uint8)
    ys, xs = np.nonzero(r.mask)
    bbox = (int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1))
    return img, bbox, r.mask


def generic_pose(mesh, azimuth_deg, elevation_deg, roll_deg, distance_factor=3.0, shift_px=(60.0, -40.0)):
    """A camera on a sphere about the part (z up), rolled, with the part shifted off the image centre."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    T = look_at(mesh.center + distance_factor * mesh.diameter * d, mesh.center, np.array([0.0, 0.0, 1.0]))
    T = roll(T, np.radians(roll_deg))
    T[0, 3] += shift_px[0] * T[2, 3] / K_Q[0, 0]
    T[1, 3] += shift_px[1] * T[2, 3] / K_Q[1, 1]
    return T


def pose_errors(T_est, T_true, diameter):
    return rotation_angle_deg(T_est[:3, :3], T_true[:3, :3]), float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) / diameter)


# ------------------------------------------------------------------------------------ alignment trials

K_ALIGN = make_K(600.0, 605.0, 321.5, 238.0)  # a VGA camera, principal point slightly off-centre


def facing_pose(mesh, rng: np.random.Generator, distance_factor: float = 4.0, offset_px: float = 0.0,
                K: np.ndarray | None = None) -> np.ndarray:
    """A uniformly random rotation with the mesh centre ``distance_factor`` diameters in front of the camera,
    shifted sideways by up to about ``offset_px`` pixels (focal ``K[0, 0]``, 600 px without ``K``)."""
    from scipy.spatial.transform import Rotation

    R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    z = distance_factor * mesh.diameter
    f = 600.0 if K is None else K[0, 0]
    shift = rng.uniform(-1, 1, 2) * offset_px * z / f
    return make_T(R, np.array([shift[0], shift[1], z]) - R @ mesh.center)


def turned_pose(T: np.ndarray, K: np.ndarray, centre: np.ndarray, deg: float, dz: float, shift_px: float,
                rng: np.random.Generator, signed_dz: bool = False) -> np.ndarray:
    """``T`` turned ``deg`` about a random axis through the object centre, depth x (1 + dz) (x (1 ± dz), the sign
    drawn, with ``signed_dz``), the centre's image shifted ``shift_px`` pixels in a random direction. Draws, in this
    order: the axis, the sign (``signed_dz`` only), the shift's direction."""
    axis = rng.normal(size=3)
    R = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.radians(deg))[0]
    c = T[:3, :3] @ centre + T[:3, 3]
    if signed_dz:
        dz = dz if rng.random() < 0.5 else -dz
    phi = rng.uniform(0, 2 * np.pi)
    u = K[0, 0] * c[0] / c[2] + K[0, 2] + shift_px * np.cos(phi)
    v = K[1, 1] * c[1] / c[2] + K[1, 2] + shift_px * np.sin(phi)
    z = c[2] * (1.0 + dz)
    cn = np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
    R0 = R @ T[:3, :3]
    return make_T(R0, cn - R0 @ centre)


def clutter_photo(renderers, poses, seed: int, K: np.ndarray = K_ALIGN):
    """A 640 x 480 photo (2x supersampled: edges anti-aliased like a camera's) with random colours, a cluttered
    background and lights (no cast shadows: cheaper). Returns the image, the first object's visible box (x0, y0, x1,
    y1) and its visible share."""
    rng = np.random.default_rng(seed)
    K2 = K.copy()
    K2[:2, :2] *= 2
    K2[0, 2], K2[1, 2] = 2 * K[0, 2] + 0.5, 2 * K[1, 2] + 0.5
    ph = render_rgb(renderers, poses, K2, 960, 1280, [Material.random(rng) for _ in poses], rng,
                    background=random_background(960, 1280, rng), shadows=False)
    img = cv2.resize(ph.rgb, (640, 480), interpolation=cv2.INTER_AREA)
    vis = cv2.resize(ph.masks_visib[0].astype(np.float32), (640, 480), interpolation=cv2.INTER_AREA) > 0.5
    full = cv2.resize(ph.masks[0].astype(np.float32), (640, 480), interpolation=cv2.INTER_AREA) > 0.5
    ys, xs = np.nonzero(vis)
    return img, np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64), vis.sum() / full.sum()


def plate_renderer() -> Renderer:
    """A flat 200 x 200 x 10 mm plate: the distractor that covers half of the part."""
    import trimesh

    b = trimesh.creation.box(extents=[200.0, 200.0, 10.0])
    return Renderer(from_arrays(np.asarray(b.vertices), np.asarray(b.faces), name="plate"))


def align_trials(mesh, renderer: Renderer, align_kw: dict, n: int = 12, plate: Renderer | None = None,
                 deg: float = 10.0, dz: float = 0.05, shift_px: float = 3.0,
                 coarse_ac=None, photo_kw: dict | None = None) -> list[tuple[float, float]]:
    """Edge alignment from a turned start on ``n`` seeded photos of ``mesh`` (3.5 diameters away, up to 60 px off
    centre); with ``plate`` a plate 60 mm in front of the part, shifted sideways to cover about half of it; with
    ``coarse_ac`` (a ``config.align`` whose ``coarse_px`` > 0) the first scales run on a coarse crop as the estimator
    runs them; ``photo_kw``: keywords of :func:`photo_edges` (``edge_align.photo_edges_kwargs`` of a ``config.align``:
    the silhouette inset, the edge detector; None = its defaults). Returns (rotation error in degrees, relative depth
    error) per trial."""
    pkw = dict(photo_kw or {})
    out = []
    for seed in range(n):
        T = facing_pose(mesh, np.random.default_rng(100 + seed), 3.5, 60.0, K_ALIGN)
        rng = np.random.default_rng(1000 + seed)
        if plate is None:
            img, box, _ = clutter_photo([renderer], [T], seed)
        else:
            c = T[:3, :3] @ mesh.center + T[:3, 3]
            side = 1.0 if seed % 2 else -1.0
            img, box, _ = clutter_photo([renderer, plate], [T, make_T(np.eye(3), c + [side * 105.0, 0.0, -60.0])],
                                        seed)
        T0 = turned_pose(T, K_ALIGN, mesh.center, deg, dz, shift_px, rng)
        kw = dict(align_kw)
        if coarse_ac is not None and coarse_levels(coarse_ac):
            kw |= coarse_kwargs(coarse_ac, photo_edges(img, K_ALIGN, box, **(pkw | {"object_px": coarse_ac.coarse_px})))
        Ta = align(renderer, photo_edges(img, K_ALIGN, box, **pkw), T0, hull=mesh.hull_vertices, **kw).T_cam_from_obj
        out.append((rotation_angle_deg(Ta[:3, :3], T[:3, :3]), abs(Ta[2, 3] - T[2, 3]) / T[2, 3]))
    return out
