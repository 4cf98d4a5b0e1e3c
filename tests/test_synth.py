"""Synthetic assemblies, defects, photo renderer and the BOP defects benchmark generator."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("manifold3d")

from pixie.eval import shape_metrics as metrics  # noqa: E402
from pixie.geometry.camera import look_at, make_K  # noqa: E402
from pixie.geometry.collide import part_solids  # noqa: E402
from pixie.eval.datasets import BopDataset  # noqa: E402
from pixie.geometry.mesh import from_arrays, load_mesh  # noqa: E402
from pixie.pipeline.query import bbox_from_mask  # noqa: E402
from pixie.geometry.render import Renderer  # noqa: E402
from pixie.synth.assemblies import BRICK_H, STUD_PITCH, brick_part, lego_assembly, make_target_assembly  # noqa: E402
from pixie.synth.defects import (  # noqa: E402
    DEFECT_TYPES,
    apply_defect,
    make_defects,
    missing_part,
    passes_through,
    shifted_part,
)
from pixie.synth.photo import (  # noqa: E402
    DirectionalLight,
    LightRig,
    Material,
    degrade,
    random_background,
    render_rgb,
)
from pixie.synth.scenes import tiny_defect_dataset  # noqa: E402

K = make_K(600.0, 600.0, 159.5, 119.5)
H, W = 240, 320


@pytest.fixture(scope="module")
def asm():
    return lego_assembly(3, n_bricks=6, base=(6, 6))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny_defects")
    summary = tiny_defect_dataset(root, seed=0)
    return root, summary


# --------------------------------------------------------------------------- assemblies, defects


def test_brick_dimensions():
    p = brick_part(2, 4, 0, 0, 0)
    lo, hi = p.bounds()
    assert np.allclose(hi[:2] - lo[:2], [2 * STUD_PITCH - 0.2, 4 * STUD_PITCH - 0.2], atol=1e-4)
    assert hi[2] == pytest.approx(BRICK_H + 1.7, abs=1e-3)  # body + studs
    body = 15.8 * 31.8 * 9.6
    studs = 8 * np.pi * 2.4**2 * 1.7
    assert p.volume() == pytest.approx(body + studs, rel=0.01)  # 20-gon studs: ~1.6% under a circle


def test_assembly_is_closed_solid_with_part_ids(asm):
    mesh, pid = asm.to_mesh_with_part_ids()
    assert len(pid) == len(mesh.faces)
    assert set(np.unique(pid)) <= set(range(len(asm.parts)))
    assert np.allclose(asm.bounds()[0] + asm.bounds()[1], 0.0, atol=1e-6)  # centred
    assert asm.volume() > 0


def test_missing_part_lowers_iou3d_by_its_volume_share(asm):
    d = missing_part(asm, np.random.default_rng(0))
    k = d.defect["part"]
    vt, vd = asm.volume(), d.volume()
    removed = asm.parts[k].volume()
    # The union loses the part minus what it shared with its neighbours (studs inside it).
    assert 0.8 * removed <= vt - vd <= removed + 1e-6
    iou = metrics.iou3d(asm.to_mesh(), d.to_mesh(), voxel_size=0.8)
    # Defective subset of the target: IoU = V_d / V_t; voxel error ~ surface * voxel / volume.
    assert iou == pytest.approx(vd / vt, abs=0.02)
    assert iou < 1.0 - 0.5 * removed / vt


def test_defect_operators_change_geometry(asm):
    rng = np.random.default_rng(1)
    m0 = asm.to_mesh()
    for kind in DEFECT_TYPES:
        d = apply_defect(asm, kind, rng)
        assert d.defect["type"] == kind
        iou = metrics.iou3d(m0, d.to_mesh(), voxel_size=1.5)
        assert 0.5 < iou < 0.995, (kind, iou)
    # The base plate is never the defective part.
    assert all(d.defect["part"] != 0 for d in make_defects(asm, 5, seed=2) if d.defect["type"] != "extra")


def test_defects_never_pass_a_part_into_another():
    """The benchmark's first assembly (seed 0) drawn without the physical check has a brick shifted into its
    neighbour (its parts overlap ~4 mm deep, against the studs' ~0.9); the generator redraws it."""
    tgt = make_target_assembly(0, 0)
    tol = part_solids(tgt.to_parts_mesh()).tolerance
    loose = make_defects(tgt, 6, seed=0, physical=False)
    assert any(passes_through(d, tol) for d in loose)
    kept = make_defects(tgt, 6, seed=0)
    assert len(kept) == 6 and not any(passes_through(d, tol) for d in kept)
    m = tgt.to_parts_mesh()  # the parts as closed solids, one part each (what a multi-body CAD file holds)
    assert m.n_parts == len(tgt.parts) and all(part_solids(m).closed)


def test_aps_target_vs_itself_and_shifted(asm):
    T = look_at([0.0, -90.0, 160.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    rt = Renderer(asm.to_mesh())
    assert metrics.aps(rt, rt, T, T, K, H, W) == pytest.approx(1.0)
    d = shifted_part(asm, np.random.default_rng(0))
    rd = Renderer(d.to_mesh())
    v = metrics.aps(rt, rd, T, T, K, H, W)
    assert 0.5 < v < 0.995


def test_determinism_from_seed():
    a1, a2 = make_target_assembly(0, 5), make_target_assembly(0, 5)
    assert np.array_equal(a1.to_mesh().vertices, a2.to_mesh().vertices)
    d1 = [d.to_mesh().vertices for d in make_defects(a1, 3, seed=4)]
    d2 = [d.to_mesh().vertices for d in make_defects(a2, 3, seed=4)]
    assert all(np.array_equal(x, y) for x, y in zip(d1, d2))
    v6 = make_target_assembly(0, 6).to_mesh().vertices
    v5 = a1.to_mesh().vertices
    assert v6.shape != v5.shape or not np.allclose(v6, v5)  # another seed, another assembly


# --------------------------------------------------------------------------- photo renderer


def _ground_and_box():
    import trimesh

    g = trimesh.creation.box((200.0, 200.0, 4.0))
    g.apply_translation((0, 0, -2.0))
    b = trimesh.creation.box((30.0, 30.0, 30.0))
    b.apply_translation((0, 0, 40.0))  # floating above the ground: casts a detached shadow
    return from_arrays(g.vertices, g.faces, "ground"), from_arrays(b.vertices, b.faces, "box")


def test_render_rgb_shapes_and_ranges():
    rng = np.random.default_rng(0)
    g, b = _ground_and_box()
    T = look_at([0.0, -250.0, 300.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    res = render_rgb([Renderer(g), Renderer(b)], [T, T], K, H, W, [Material.random(rng), Material.random(rng)], rng)
    assert res.rgb.shape == (H, W, 3) and res.rgb.dtype == np.uint8
    assert res.depth.shape == (H, W) and res.depth.dtype == np.float32
    assert res.owner.dtype == np.int32 and set(np.unique(res.owner)) <= {-1, 0, 1}
    assert len(res.masks_visib) == 2 and res.masks_visib[1].any()
    assert np.array_equal(res.masks_visib[1], res.owner == 1)
    assert (res.depth[res.owner >= 0] > 0).all() and (res.depth[res.owner < 0] == 0).all()
    assert 0.0 < res.visib_fract(0) < 1.0  # the box hides part of the ground
    out = degrade(res.rgb, rng, blur=True, noise=True, jpeg=True, resample=True)
    assert out.shape == res.rgb.shape and out.dtype == np.uint8
    for kind in ("gradient", "noise", "texture", "clutter"):
        bg = random_background(H, W, rng, kind)
        assert bg.shape == (H, W, 3) and bg.dtype == np.uint8 and bg.std() > 0


def test_shadows_darken_pixels_hidden_from_the_light():
    g, b = _ground_and_box()
    T = look_at([0.0, -250.0, 300.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    # Light from straight above the ground (world +z) expressed in the camera frame.
    light_dir = T[:3, :3] @ np.array([0.2, 0.1, 1.0])
    rig = LightRig([DirectionalLight(light_dir, (1, 1, 1), 1.0)], ambient=0.2)
    bg = np.zeros((H, W, 3), np.uint8)
    mats = [Material((0.8, 0.8, 0.8), roughness=1.0, specular=0.0), Material((0.2, 0.4, 0.9))]
    rs = [Renderer(g), Renderer(b)]
    lit = render_rgb(rs, [T, T], K, H, W, mats, np.random.default_rng(0), bg, rig, shadows=False)
    sh = render_rgb(rs, [T, T], K, H, W, mats, np.random.default_rng(0), bg, rig, shadows=True)
    ground = sh.owner == 0
    shadowed = ground & (sh.shadow > 0.5)
    # Erode so that anti-aliased borders do not count.
    import cv2

    inner = cv2.erode(ground.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert (shadowed & inner).sum() > 100, "the box casts a shadow onto the ground"
    s = shadowed & inner
    assert sh.rgb[s].mean() < 0.7 * lit.rgb[s].mean()
    free = inner & (sh.shadow == 0)
    assert np.array_equal(sh.rgb[free], lit.rgb[free])


# --------------------------------------------------------------------------- BOP scenes


def test_tiny_dataset_is_bop_readable_and_masks_match_renders(tiny):
    root, summary = tiny
    ds = BopDataset(root)
    targets = ds.targets()
    assert len(targets) == 4 and ds.has_depth()
    assert ds.obj_ids() == [1]
    variants = json.loads((root / "variants.json").read_text())
    assert [v["variant"] for v in variants] == ["target", "defective"]
    dmap = json.loads((root / "models_defective" / "defective_models.json").read_text())
    assert dmap["101"]["target_obj_id"] == 1
    for tg in targets:
        v = variants[tg.scene_id - 1]
        model_dir = root / v["model_dir"]
        mesh = load_mesh(model_dir / f"obj_{v['model_obj_id']:06d}.ply")
        (inst,) = ds.instances(tg.scene_id, tg.im_id)
        cam = ds.camera(tg.scene_id, tg.im_id)
        h, w = ds.image_size(tg.scene_id, tg.im_id)
        assert ds.load_rgb(tg.scene_id, tg.im_id).shape == (h, w, 3)
        r = Renderer(mesh).render(inst.T_cam_from_obj, cam.K, h, w)
        mv = ds.load_mask_visib(tg.scene_id, tg.im_id, 0)
        depth = ds.load_depth(tg.scene_id, tg.im_id)
        assert mv.sum() == inst.px_count_visib > 0
        assert not (mv & ~r.mask).any()  # visible pixels are object pixels
        assert np.abs(depth[mv] - r.depth[mv]).max() < 0.1  # PNG depth is quantised to 0.1 mm
        assert inst.visib_fract == pytest.approx(mv.sum() / r.mask.sum(), abs=1e-6)
        x, y, bw, bh = inst.bbox_visib  # BOP's convention: w = last - first
        ys, xs = np.nonzero(mv)
        assert (x, y, x + bw, y + bh) == (xs.min(), ys.min(), xs.max(), ys.max())
        assert np.array_equal(inst.box_visib, bbox_from_mask(mv))  # pixie's convention: w counts pixels
    rows = summary["table1"]
    assert rows[-1]["scenes"] == 2 and rows[-1]["defects"] == 1
    assert rows[-1]["aps"] <= 1.0 and rows[-1]["aps_dev"] < 1.0 and rows[-1]["iou3d_dev"] < 1.0


def test_tiny_dataset_is_deterministic(tiny, tmp_path):
    root, _ = tiny
    again = tmp_path / "again"
    tiny_defect_dataset(again, seed=0)
    for rel in ("test/000002/scene_gt.json", "test_targets_bop19.json", "models/models_info.json"):
        assert (root / rel).read_text() == (again / rel).read_text()
    import cv2

    a = cv2.imread(str(root / "test/000002/rgb/000001.png"))
    b = cv2.imread(str(again / "test/000002/rgb/000001.png"))
    assert np.array_equal(a, b)


def test_compound_defects_are_stronger(asm):
    single = make_defects(asm, 4, seed=3)
    double = make_defects(asm, 4, seed=3, compound=1.0)
    assert all("+" in d.defect["type"] and len(d.defect["steps"]) == 2 for d in double)
    m0 = asm.to_mesh()
    iou1 = np.mean([metrics.iou3d(m0, d.to_mesh(), 1.5) for d in single])
    iou2 = np.mean([metrics.iou3d(m0, d.to_mesh(), 1.5) for d in double])
    assert iou2 < iou1
