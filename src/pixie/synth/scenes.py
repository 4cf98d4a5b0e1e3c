"""Synthetic BOP-format benchmark of assembly defects and colour variants (the paper's Sec. IV-C setting).

:func:`generate_defect_dataset` writes::

    OUT/
      models/obj_OOOOOO.ply, models/models_info.json     target models (ids 1..A), mm, centred
      models_defective/obj_OOOOOO.ply (+ models_info.json) defective variants (ids 100*a + k)
      models_defective/defective_models.json             defective id -> {target_obj_id, defect, ...}
      models_parts/obj_OOOOOO.glb                        target models with one sub-mesh per part (the union's
                                                         triangles by part, as in sessions 10-15)
      models_parts_solid/obj_OOOOOO.glb                  the same with every part its own closed solid
      camera.json                                        640x480, fx ~ fy ~ 600, depth_scale 0.1
      test/SSSSSS/{rgb,depth,mask,mask_visib}/ ...        rgb PNG, depth uint16 (x 0.1 mm)
      test/SSSSSS/scene_gt.json, scene_camera.json, scene_gt_info.json
      test/SSSSSS/scene_variant.json                     which physical variant the scene shows
      test_targets_bop19.json
      variants.json                                      all scenes' variants (as scene_variant.json)
      table1.json                                        Table I analogue (see :func:`table1`)

One scene = one physical object: assembly ``a`` as its target or as defective variant ``k``,
painted in colour variant ``c``; its images are taken from different viewpoints with clutter
(distractor parts on the table, some in front of the object) and random lights, backgrounds
and camera degradations. ``scene_gt.json`` annotates the *target* object id (the method only
knows the target model) with the GT pose; the defective model shares the target's frame, so the
same pose places it exactly.

Everything is deterministic given ``seed``. :func:`tiny_defect_dataset` makes a 2-scene set in
about a second for tests and demos.

Longer than 500 lines on purpose: scene composition, its BOP writer and the Table I summary share one
seeded generator state, and the writer is the only consumer of the composition.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from pixie.geometry.camera import look_at, make_K
from pixie.eval.shape_metrics import aps, iou3d
from pixie.geometry.mesh import Mesh, from_arrays
from pixie.geometry.render import Renderer, composite
from pixie.synth.assemblies import (
    Assembly,
    bracket_part,
    brick_part,
    cylinder_part,
    make_target_assembly,
    part_palette,
    plate_with_holes_part,
    shaft_part,
)
from pixie.synth.defects import make_defects
from pixie.synth.photo import Material, degrade, random_background, random_color, render_rgb

WIDTH, HEIGHT = 640, 480
DEPTH_SCALE = 0.1  # mm per depth-PNG unit

__all__ = [
    "default_K",
    "PhysicalVariant",
    "build_variants",
    "generate_defect_dataset",
    "tiny_defect_dataset",
    "table1",
    "format_table1",
    "write_ply",
    "write_parts_glb",
    "load_variants",
]


def default_K() -> np.ndarray:
    """Intrinsics of a typical calibrated 640x480 camera (fx ~ fy ~ 600)."""
    return make_K(601.3, 600.2, 321.7, 238.4)


def write_ply(path: Path, mesh: Mesh) -> None:
    """Binary little-endian PLY with vertices (float32, mm) and triangles."""
    v = np.asarray(mesh.vertices, np.float32)
    f = np.asarray(mesh.faces, np.int32)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    faces = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = f
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(v.astype("<f4").tobytes())
        fh.write(faces.tobytes())


def write_parts_glb(path: Path, asm: Assembly, solids: bool = True) -> None:
    """The assembly as a GLB with one named sub-mesh per part (``part_KK_<name>``, in mm), read back by
    :func:`pixie.geometry.mesh.load_mesh` with its parts (``Mesh.face_parts``): the CAD-with-parts input of the part
    report.

    ``solids``: every part its own closed solid where the assembly has it (:meth:`Assembly.to_parts_mesh`), as a
    multi-body CAD export holds them (what :mod:`pixie.geometry.collide` needs); else the union's triangles grouped
    by the part they came from (sessions 10-15's benchmark files: a part's surface is open where it touches
    another).
    """
    import trimesh

    if not solids:
        union, part_of = asm.to_mesh_with_part_ids()
    scene = trimesh.Scene()
    for k, part in enumerate(asm.parts):
        if solids:
            v, f = part.placed_vertices(), part.mesh.faces
        else:
            sel = part_of == k
            if not sel.any():  # a part entirely inside others leaves no surface
                continue
            v, f = union.vertices, union.faces[sel]
        name = f"part_{k:02d}_{part.name}"
        scene.add_geometry(trimesh.Trimesh(v, f, process=False), node_name=name, geom_name=name)
    scene.export(str(path), file_type="glb")


def _model_info(mesh: Mesh) -> dict:
    lo, ext = mesh.bbox_min, mesh.extent
    return {
        "diameter": float(mesh.diameter),
        "min_x": float(lo[0]), "min_y": float(lo[1]), "min_z": float(lo[2]),
        "size_x": float(ext[0]), "size_y": float(ext[1]), "size_z": float(ext[2]),
    }


# --------------------------------------------------------------------------- physical variants


@dataclass
class PhysicalVariant:
    """The physical object shown in one scene."""

    assembly_index: int  # 0-based
    obj_id: int  # target model id (annotated in scene_gt.json)
    defect_index: int  # 0 = the target itself, k >= 1 = defective variant k
    model_obj_id: int  # obj_id for the target, 100 * obj_id + k for a defective variant
    colour_variant: int
    assembly: Assembly
    mesh: Mesh
    part_ids: np.ndarray
    part_colors: list[np.ndarray] = field(default_factory=list, repr=False)

    @property
    def is_defective(self) -> bool:
        return self.defect_index > 0

    def material(self, rng: np.random.Generator) -> Material:
        cols = self.part_colors
        return Material.from_part_colors(self.part_ids, [cols[k] for k in range(len(self.assembly.parts))],
                                         roughness=float(rng.uniform(0.25, 0.6)), specular=float(rng.uniform(0.2, 0.5)),
                                         albedo_noise=float(rng.uniform(0.0, 0.06)))

    def info(self) -> dict:
        return dict(assembly=self.assembly_index + 1, obj_id=self.obj_id,
                    variant="target" if self.defect_index == 0 else "defective",
                    defect_index=self.defect_index, model_obj_id=self.model_obj_id,
                    model_dir="models" if self.defect_index == 0 else "models_defective",
                    colour_variant=self.colour_variant, assembly_name=self.assembly.name,
                    defect=self.assembly.defect)


def _colours_for(asm: Assembly, palettes: dict[str, np.ndarray], rng: np.random.Generator) -> list:
    out = []
    for p in asm.parts:
        if p.color_key not in palettes:
            palettes[p.color_key] = part_palette(1, rng, asm.family)[0]
        out.append(palettes[p.color_key])
    return out


def build_variants(n_assemblies: int, n_defects: int, n_colour_variants: int, seed: int,
                   full_product: bool = False, defect_compound: float = 0.0) -> tuple[list[Assembly], dict[int, list[Assembly]], list[PhysicalVariant]]:
    """Target assemblies, their defective variants and the scenes' physical variants.

    Scenes per assembly: the target in every colour variant, then each defective variant in one
    colour variant (cycling), like the paper's dataset; ``full_product`` takes every
    (variant, colour) pair instead.
    """
    targets = [make_target_assembly(a, seed) for a in range(n_assemblies)]
    defects = {a: make_defects(t, n_defects, seed=seed * 7919 + a, compound=defect_compound) for a, t in enumerate(targets)}
    out: list[PhysicalVariant] = []
    for a, tgt in enumerate(targets):
        obj_id = a + 1
        crng = np.random.default_rng([seed, a, 17])
        palettes = []
        for c in range(n_colour_variants):
            pal: dict[str, np.ndarray] = {}
            _colours_for(tgt, pal, crng)
            palettes.append(pal)
        variants = [(0, tgt)] + [(k + 1, d) for k, d in enumerate(defects[a])]
        for k, asm in variants:
            colours = range(n_colour_variants) if (k == 0 or full_product) else [(k - 1) % n_colour_variants]
            mesh, pid = asm.to_mesh_with_part_ids()
            for c in colours:
                out.append(PhysicalVariant(a, obj_id, k, obj_id if k == 0 else 100 * obj_id + k, c, asm, mesh, pid,
                                           _colours_for(asm, palettes[c], crng)))
    return targets, defects, out


# --------------------------------------------------------------------------- clutter


def _distractor_meshes(seed: int) -> list[Mesh]:
    """A small library of clutter objects (other parts: bricks, cylinders, brackets, bolts, blocks)."""
    rng = np.random.default_rng([seed, 99])
    parts = [
        brick_part(2, 4, 0, 0, 0), brick_part(1, 2, 0, 0, 0), brick_part(2, 2, 0, 0, 0, plates=1),
        brick_part(1, 6, 0, 0, 0), cylinder_part(12, 30, 0, 0, 0, bore=6), cylinder_part(6, 45, 0, 0, 0),
        bracket_part(25, 15, 20, 3, 2, np.eye(4)), shaft_part(3, 35, 0, 0, 0),
        plate_with_holes_part(40, 25, 4, [(8, 8, 3), (32, 8, 3), (20, 17, 5)]),
    ]
    out = [p.mesh for p in parts]
    import trimesh

    for _ in range(3):
        m = trimesh.creation.box(rng.uniform(15, 50, 3))
        out.append(from_arrays(m.vertices, m.faces, name="block"))
    m = trimesh.creation.icosphere(2, radius=float(rng.uniform(8, 15)))
    out.append(from_arrays(m.vertices, m.faces, name="ball"))
    # Centre them (bbox centre at origin) so that placement is simple.
    res = []
    for m in out:
        res.append(from_arrays(m.vertices - m.center, m.faces, name=m.name))
    return res


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _random_upright(rng: np.random.Generator) -> np.ndarray:
    """Rotation of a distractor lying on the table: random yaw, lying on one of its faces."""
    flips = [np.eye(3), np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]]), np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0.0]])]
    return _rot_z(rng.uniform(0, 2 * np.pi)) @ flips[int(rng.integers(3))]


# --------------------------------------------------------------------------- generation


def _table_mesh(size: float = 1500.0) -> Mesh:
    s = size / 2
    v = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    # Closed thin slab so that the mesh validates like any other (two extra faces below).
    v2 = np.concatenate([v, v - [0, 0, 5.0]])
    f2 = np.concatenate([f, f[:, ::-1] + 4])
    return from_arrays(v2, f2, name="table")


# Bumped when what the generator writes changes meaning (2: BOP's box convention, w = last - first;
# 3: invisible objects' boxes are BOP's [-1, -1, -1, -1]).
DATASET_FORMAT = 3


def _bbox(mask: np.ndarray) -> list[int]:
    """BOP's box of a mask: ``[x, y, w, h]`` with ``w = x_last - x_first`` (``bop_toolkit``'s ``calc_2d_bbox``);
    ``[-1, -1, -1, -1]`` for an empty mask, as BOP writes for invisible objects."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())]


def _camera_pose(rng: np.random.Generator, radius: float, K: np.ndarray, w: int, h: int) -> np.ndarray:
    """World(=object-on-table) to camera: random azimuth, elevation 20-75 deg, 280-480 mm away,
    object placed off-centre within the image and a small roll."""
    az = rng.uniform(0, 2 * np.pi)
    el = np.radians(rng.uniform(20, 75))
    dist = rng.uniform(190, 340) * max(radius / 40.0, 0.6)
    eye = dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    T = look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    roll = np.radians(rng.uniform(-15, 15))
    Rr = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1.0]])
    T[:3, :3] = Rr @ T[:3, :3]
    T[:3, 3] = Rr @ T[:3, 3]
    # Shift the object in the image (keep it inside with a margin).
    z = T[2, 3]
    margin = radius * K[0, 0] / z + 20
    du = rng.uniform(-1, 1) * max(w / 2 - margin, 0)
    dv = rng.uniform(-1, 1) * max(h / 2 - margin, 0)
    T[0, 3] += du * z / K[0, 0]
    T[1, 3] += dv * z / K[1, 1]
    return T


def _render_image(pv: PhysicalVariant, target_mesh: Mesh, renderers: dict, distractors: list[Mesh],
                  rng: np.random.Generator, K: np.ndarray, w: int, h: int, n_distractors: tuple[int, int],
                  occlusion_prob: float, degrade_prob: float, table_prob: float, min_visib: float = 0.35):
    """One image of the scene: returns (rgb, depth, T_cam_from_obj, mask, mask_visib, meta)."""
    z0 = float(target_mesh.bbox_min[2])  # the object's base rests on the table (target frame)
    radius = target_mesh.bounding_radius
    for _attempt in range(20):
        rens = None
        T_world = _camera_pose(rng, radius, K, w, h)  # world = object frame
        objs = [(renderers[("obj", pv.model_obj_id)], T_world)]
        # Distractors on the table around the object; with occlusion_prob one sits between the
        # object and the camera.
        n_d = int(rng.integers(n_distractors[0], n_distractors[1] + 1))
        cam_pos = -T_world[:3, :3].T @ T_world[:3, 3]
        cam_dir = cam_pos[:2] / max(np.linalg.norm(cam_pos[:2]), 1e-6)
        placed = []
        for j in range(n_d):
            di = int(rng.integers(len(distractors)))
            R = _random_upright(rng)
            dm = distractors[di]
            v = dm.vertices @ R.T
            half = 0.5 * (v.max(0) - v.min(0))
            occluder = j == 0 and rng.random() < occlusion_prob
            for _ in range(30):
                if occluder:
                    side = np.array([-cam_dir[1], cam_dir[0]])
                    xy = cam_dir * rng.uniform(radius * 1.1 + half[:2].max(), radius * 2.5 + half[:2].max()) \
                        + side * rng.uniform(-0.6, 0.6) * radius
                else:
                    ang = rng.uniform(0, 2 * np.pi)
                    xy = np.array([np.cos(ang), np.sin(ang)]) * rng.uniform(radius + half[:2].max() + 5, radius * 3.5 + 60)
                r_here = float(np.linalg.norm(half[:2]))
                if all(np.linalg.norm(xy - q) > r_here + rq + 2 for q, rq in placed):
                    break
            placed.append((xy, float(np.linalg.norm(half[:2]))))
            Td = np.eye(4)
            Td[:3, :3] = R
            Td[:3, 3] = [xy[0], xy[1], z0 + half[2]]
            objs.append((renderers[("dis", di)], T_world @ Td))
        use_table = rng.random() < table_prob
        if use_table:
            Tt = np.eye(4)
            Tt[2, 3] = z0
            objs.append((renderers[("table",)], T_world @ Tt))
        # Visibility check on geometry only (cheap) before shading.
        full = objs[0][0].render(objs[0][1], K, h, w)
        n_full = int(full.mask.sum())
        if n_full < 200:
            continue
        rens = [full] + [r.render(T, K, h, w) for r, T in objs[1:]]
        _, owner = composite(rens)
        vis = float((owner == 0).sum()) / n_full
        if vis >= min_visib:
            break
    mats = [pv.material(rng)]
    for r, _T in objs[1:]:
        if r.mesh.name == "table":
            tone = random_color(rng, saturated=rng.random() < 0.3)
            tone = 0.6 * tone + 0.4 * tone.mean()  # tables are rarely vivid
            mats.append(Material(tone * 0.9 + 0.05, roughness=0.9,
                                 specular=0.05, albedo_noise=float(rng.uniform(0.1, 0.4))))
        else:
            mats.append(Material.random(rng))
    bg = random_background(h, w, rng)
    photo = render_rgb([o[0] for o in objs], [o[1] for o in objs], K, h, w, mats, rng, background=bg, renders=rens)
    rgb = photo.rgb
    degraded = rng.random() < degrade_prob
    if degraded:
        rgb = degrade(rgb, rng)
    meta = dict(n_distractors=n_d, table=bool(use_table), degraded=bool(degraded))
    return rgb, photo.depth, T_world, photo.masks[0], photo.masks_visib[0], meta


def generate_defect_dataset(
    out_dir: str | Path,
    n_assemblies: int = 3,
    n_defects: int = 3,
    n_colour_variants: int = 3,
    images_per_variant: int = 4,
    seed: int = 0,
    width: int = WIDTH,
    height: int = HEIGHT,
    n_distractors: tuple[int, int] = (1, 4),
    occlusion_prob: float = 0.5,
    degrade_prob: float = 0.7,
    table_prob: float = 0.8,
    full_product: bool = False,
    defect_compound: float = 0.0,
    voxel_size: float = 1.0,
    scene_filter=None,
    overwrite: bool = True,
    progress=None,
) -> dict:
    """Write the synthetic defects benchmark in BOP format and return its Table I summary.

    Parameters
    ----------
    out_dir : dataset root (replaced when ``overwrite``)
    n_assemblies : target assemblies (obj ids 1..A; index 2, 5, ... are mechanical, others LEGO-like)
    n_defects : defective variants per assembly (ids 100 * obj_id + k)
    n_colour_variants : paint variants of each target (the target appears in all; each defect in one)
    images_per_variant : images per scene (viewpoints)
    seed : everything is a function of it
    defect_compound : probability that a defective variant combines two defects (0: one each;
        raise it for deviations as strong as the paper's, whose IoU3D (dev) is 0.77-0.89)
    scene_filter : callable(PhysicalVariant) -> bool, keep only some scenes (e.g. a subset for a bench)
    voxel_size : mm, for IoU3D in the summary
    progress : callable(done, total), optional

    Returns
    -------
    dict with ``table1`` (see :func:`table1`), ``n_scenes``, ``n_images``, ``time_s``.
    """
    t0 = time.perf_counter()
    out = Path(out_dir)
    if out.exists() and overwrite:
        shutil.rmtree(out)
    (out / "models").mkdir(parents=True, exist_ok=True)
    (out / "models_defective").mkdir(parents=True, exist_ok=True)
    (out / "models_parts").mkdir(parents=True, exist_ok=True)
    (out / "models_parts_solid").mkdir(parents=True, exist_ok=True)
    K = default_K() if (width, height) == (WIDTH, HEIGHT) else make_K(600.0 * width / WIDTH, 600.0 * width / WIDTH,
                                                                     (width - 1) / 2, (height - 1) / 2)
    targets, defects, variants = build_variants(n_assemblies, n_defects, n_colour_variants, seed, full_product,
                                                defect_compound)
    if scene_filter is not None:
        variants = [v for v in variants if scene_filter(v)]

    # Models.
    info_t, info_d, dmap = {}, {}, {}
    target_meshes = {}
    for a, tgt in enumerate(targets):
        m = tgt.to_mesh()
        target_meshes[a + 1] = m
        write_ply(out / "models" / f"obj_{a + 1:06d}.ply", m)
        write_parts_glb(out / "models_parts" / f"obj_{a + 1:06d}.glb", tgt, solids=False)
        write_parts_glb(out / "models_parts_solid" / f"obj_{a + 1:06d}.glb", tgt)
        info_t[str(a + 1)] = _model_info(m)
        for k, d in enumerate(defects[a], start=1):
            did = 100 * (a + 1) + k
            dm = d.to_mesh()
            write_ply(out / "models_defective" / f"obj_{did:06d}.ply", dm)
            info_d[str(did)] = _model_info(dm)
            dmap[str(did)] = dict(target_obj_id=a + 1, defect_index=k, name=d.name, defect=d.defect)
    (out / "models" / "models_info.json").write_text(json.dumps(info_t, indent=1))
    (out / "models_defective" / "models_info.json").write_text(json.dumps(info_d, indent=1))
    (out / "models_defective" / "defective_models.json").write_text(json.dumps(dmap, indent=1))
    (out / "assemblies.json").write_text(json.dumps(
        {str(a + 1): dict(target=t.info(), defects=[d.info() for d in defects[a]]) for a, t in enumerate(targets)},
        indent=1, default=_json_default))
    (out / "camera.json").write_text(json.dumps(dict(
        width=width, height=height, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
        depth_scale=DEPTH_SCALE), indent=1))

    # Renderers (built once).
    renderers: dict = {("table",): Renderer(_table_mesh(), smooth_normals=False)}
    for pv in variants:
        if ("obj", pv.model_obj_id) not in renderers:
            renderers[("obj", pv.model_obj_id)] = Renderer(pv.mesh, smooth_normals=False)
    distractors = _distractor_meshes(seed)
    for i, m in enumerate(distractors):
        renderers[("dis", i)] = Renderer(m, smooth_normals=False)

    targets_json, all_variants = [], []
    aps_cache: dict[int, Renderer] = {}
    total = len(variants) * images_per_variant
    done = 0
    for s, pv in enumerate(variants, start=1):
        sd = out / "test" / f"{s:06d}"
        for sub in ("rgb", "depth", "mask", "mask_visib"):
            (sd / sub).mkdir(parents=True, exist_ok=True)
        rng = np.random.default_rng([seed, s, 4242])
        gt, cam, gti = {}, {}, {}
        aps_vals = []
        for im in range(images_per_variant):
            rgb, depth, T, mask, mask_visib, meta = _render_image(
                pv, target_meshes[pv.obj_id], renderers, distractors, rng, K, width, height, n_distractors,
                occlusion_prob, degrade_prob, table_prob)
            cv2.imwrite(str(sd / "rgb" / f"{im:06d}.png"), rgb[..., ::-1])
            d16 = np.round(depth / DEPTH_SCALE)
            d16[d16 > 65535] = 0
            cv2.imwrite(str(sd / "depth" / f"{im:06d}.png"), d16.astype(np.uint16))
            cv2.imwrite(str(sd / "mask" / f"{im:06d}_000000.png"), mask.astype(np.uint8) * 255)
            cv2.imwrite(str(sd / "mask_visib" / f"{im:06d}_000000.png"), mask_visib.astype(np.uint8) * 255)
            gt[str(im)] = [dict(obj_id=pv.obj_id, cam_R_m2c=T[:3, :3].ravel().tolist(), cam_t_m2c=T[:3, 3].tolist())]
            cam[str(im)] = dict(cam_K=K.ravel().tolist(), depth_scale=DEPTH_SCALE)
            n_all, n_vis = int(mask.sum()), int(mask_visib.sum())
            gti[str(im)] = [dict(bbox_obj=_bbox(mask), bbox_visib=_bbox(mask_visib), px_count_all=n_all,
                                 px_count_valid=n_all, px_count_visib=n_vis,
                                 visib_fract=float(n_vis / n_all) if n_all else 0.0)]
            targets_json.append(dict(scene_id=s, im_id=im, obj_id=pv.obj_id, inst_count=1))
            # APS at the GT pose: target model vs the physical (possibly defective) model.
            if pv.obj_id not in aps_cache:
                aps_cache[pv.obj_id] = Renderer(target_meshes[pv.obj_id])
            aps_vals.append(1.0 if not pv.is_defective else
                            aps(aps_cache[pv.obj_id], renderers[("obj", pv.model_obj_id)], T, T, K, height, width))
            gti[str(im)][0]["meta"] = meta
            done += 1
            if progress:
                progress(done, total)
        (sd / "scene_gt.json").write_text(json.dumps(gt, indent=1))
        (sd / "scene_camera.json").write_text(json.dumps(cam, indent=1))
        (sd / "scene_gt_info.json").write_text(json.dumps(gti, indent=1))
        v = dict(scene_id=s, **pv.info(), n_images=images_per_variant, aps_gt=[float(x) for x in aps_vals])
        (sd / "scene_variant.json").write_text(json.dumps(v, indent=1, default=_json_default))
        all_variants.append(v)
    (out / "test_targets_bop19.json").write_text(json.dumps(targets_json))
    (out / "variants.json").write_text(json.dumps(all_variants, indent=1, default=_json_default))

    # IoU3D per physical model.
    ious = {}
    for a, tgt in enumerate(targets):
        for k, d in enumerate(defects[a], start=1):
            ious[100 * (a + 1) + k] = iou3d(target_meshes[a + 1], d.to_mesh(), voxel_size)
    summary = table1(all_variants, ious, n_defects_per_assembly={a + 1: len(defects[a]) for a in range(len(targets))})
    result = dict(table1=summary, n_scenes=len(all_variants), n_images=len(targets_json),
                  iou3d={str(k): v for k, v in ious.items()}, voxel_size=voxel_size,
                  time_s=time.perf_counter() - t0, seed=seed, format=DATASET_FORMAT,
                  params=dict(n_assemblies=n_assemblies, n_defects=n_defects, n_colour_variants=n_colour_variants,
                              images_per_variant=images_per_variant, full_product=full_product,
                              defect_compound=defect_compound))
    (out / "table1.json").write_text(json.dumps(result, indent=1, default=_json_default))
    return result


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, (np.bool_,)):
        return bool(o)
    raise TypeError(type(o).__name__)


def table1(variants: list[dict], ious: dict[int, float], n_defects_per_assembly: dict[int, int] | None = None) -> list[dict]:
    """Table I analogue, one row per assembly plus a total row.

    Columns: #M (assembly), #Sc. (scenes), #Img., #T. (colour variants of the target),
    #D. (defective models shown), APS at P_gt over all images (defective images only in
    ``aps_dev``), IoU3D over all scenes' physical models (targets count 1; defective only in
    ``iou3d_dev``).
    """
    rows = []
    by_a: dict[int, list[dict]] = {}
    for v in variants:
        by_a.setdefault(int(v["assembly"]), []).append(v)
    all_rows = []
    for a in sorted(by_a):
        vs = by_a[a]
        row = _t1_row(str(a), vs, ious)
        rows.append(row)
        all_rows += vs
    rows.append(_t1_row("sum", all_rows, ious))
    return rows


def _t1_row(name: str, vs: list[dict], ious: dict[int, float]) -> dict:
    aps_all = [x for v in vs for x in v["aps_gt"]]
    aps_dev = [x for v in vs if v["defect_index"] > 0 for x in v["aps_gt"]]
    iou_all = [1.0 if v["defect_index"] == 0 else ious[v["model_obj_id"]] for v in vs]
    iou_dev = [ious[v["model_obj_id"]] for v in vs if v["defect_index"] > 0]
    return {
        "M": name,
        "scenes": len(vs),
        "images": sum(v["n_images"] for v in vs),
        "textured": len({(v["assembly"], v["colour_variant"]) for v in vs if v["defect_index"] == 0}),
        "defects": len({v["model_obj_id"] for v in vs if v["defect_index"] > 0}),
        "aps": float(np.mean(aps_all)) if aps_all else float("nan"),
        "aps_dev": float(np.mean(aps_dev)) if aps_dev else float("nan"),
        "iou3d": float(np.mean(iou_all)) if iou_all else float("nan"),
        "iou3d_dev": float(np.mean(iou_dev)) if iou_dev else float("nan"),
    }


def format_table1(rows: list[dict]) -> str:
    lines = ["| #M | #Sc. | #Img. | #T. | #D. | APS (dev) | IoU3D (dev) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['M']} | {r['scenes']} | {r['images']} | {r['textured']} | {r['defects']} | "
                     f"{r['aps']:.2f} ({r['aps_dev']:.2f}) | {r['iou3d']:.2f} ({r['iou3d_dev']:.2f}) |")
    return "\n".join(lines)


def load_variants(root: str | Path) -> list[dict]:
    """The scenes' physical variants (``variants.json``) of a generated dataset."""
    return json.loads((Path(root) / "variants.json").read_text())


def tiny_defect_dataset(out_dir: str | Path, seed: int = 0, images_per_variant: int = 2,
                        width: int = 320, height: int = 240) -> dict:
    """A tiny set regenerated in about a second: one LEGO assembly, its target and one defective
    variant (one colour each), ``images_per_variant`` images per scene at 320x240."""
    return generate_defect_dataset(out_dir, n_assemblies=1, n_defects=1, n_colour_variants=1,
                                   images_per_variant=images_per_variant, seed=seed, width=width, height=height,
                                   n_distractors=(1, 2), voxel_size=2.0)


def main(argv=None) -> int:
    """``python -m pixie.synth.scenes OUT [--tiny] [--assemblies 3 --defects 3 --colours 3 --images 4 --seed 0]``"""
    ap = argparse.ArgumentParser(description="Generate the synthetic assembly-defects benchmark (BOP format).")
    ap.add_argument("out", type=Path)
    ap.add_argument("--tiny", action="store_true", help="the 2-scene 320x240 set of tests and demos")
    ap.add_argument("--assemblies", type=int, default=3)
    ap.add_argument("--defects", type=int, default=3)
    ap.add_argument("--colours", type=int, default=3)
    ap.add_argument("--images", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--full-product", action="store_true", help="every defective variant in every colour")
    ap.add_argument("--compound", type=float, default=0.0, help="probability of a second defect per variant")
    args = ap.parse_args(argv)
    if args.tiny:
        res = tiny_defect_dataset(args.out, seed=args.seed)
    else:
        res = generate_defect_dataset(args.out, args.assemblies, args.defects, args.colours, args.images, args.seed,
                                      full_product=args.full_product, defect_compound=args.compound)
    print(format_table1(res["table1"]))
    print(f"{res['n_scenes']} scenes, {res['n_images']} images in {res['time_s']:.1f} s -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
