"""The end-to-end scene of the test suite and ``bench/e2e_margin.py``: a procedural part, generic poses and
photo-like renders of it (a random colour per CAD face, Lambertian shading, a noisy background).

One home for what the tests and the bench share (no bench script imports the tests).
"""

from __future__ import annotations

import cv2
import numpy as np

from pixie.config import PixieConfig, RefsConfig
from pixie.geometry.camera import look_at, make_K, rotation_angle_deg
from pixie.geometry.render import Renderer
from pixie.references.views import roll

__all__ = ["K_Q", "H", "W", "E2E_POSES", "e2e_config", "procedural_part", "cad_faces", "render_photo",
           "generic_pose", "pose_errors"]

K_Q = make_K(600.0, 600.0, 319.5, 239.5)
H, W = 480, 640

# Generic viewpoints (azimuth, elevation, roll in degrees), fixed before looking at any result: three-quarter
# views from above and below the horizon, rolled both ways, spread over the sphere.
E2E_POSES = [(35.0, 35.0, 15.0), (-120.0, 25.0, -10.0), (200.0, 50.0, 30.0), (80.0, 20.0, 0.0),
             (150.0, -20.0, 60.0), (-40.0, 70.0, -30.0), (10.0, 5.0, 45.0), (260.0, -35.0, -60.0),
             (100.0, 60.0, 90.0), (-75.0, -10.0, 120.0), (170.0, 15.0, -150.0), (300.0, 40.0, 170.0),
             (45.0, -50.0, -20.0), (220.0, 75.0, 5.0)]


def e2e_config(matcher_name: str) -> PixieConfig:
    """The modest reference set of the end-to-end test, the default pipeline otherwise."""
    cfg = PixieConfig()
    cfg.refs = RefsConfig(n_fibonacci=40, rotations=8, size=256, encodings=["shade3_edges"])
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
