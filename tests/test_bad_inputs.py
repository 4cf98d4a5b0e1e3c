"""Hostile inputs through the command line and the public API: every one ends in a one-line error that
names the problem (exit 2), a result flagged failed, or a documented warning -- never a traceback, never a
silently wrong pose, never lost or half-written output.

The tests drive ``pixie.app.cli.main`` in-process (exit code, stdout, stderr) and, for signals, a ``pixie``
subprocess. Fixtures are tiny (a 6-view, 2-roll, 64 px reference set of a ~90 mm procedural part) so the
whole file runs in seconds.
"""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import assert_cli_error, run_cli, write_tiny_part


SRC = Path(__file__).resolve().parents[1] / "src"
W, H = 320, 240
K_TEXT = "300,300,159.5,119.5"


cli = run_cli  # conftest: the command line in this process, (exit code, stdout, stderr)
assert_error = assert_cli_error  # conftest: exit 2 and ONE `pixie: error` line naming every needle


# ------------------------------------------------------------------------------------------ fixtures


@pytest.fixture(scope="module")
def work(tmp_path_factory, proc_trimesh):
    """Folder with part.ply (the procedural part), photo.png (it rendered at 320x240), mask.png and refs.npz."""
    d = tmp_path_factory.mktemp("bad_inputs")
    w = write_tiny_part(d, proc_trimesh)
    (d / "bad.txt").write_text("not a folder")
    return {**w, "box": ",".join(str(v) for v in w["box"]), "file": d / "bad.txt"}


SMALL = ["--views", "8", "--rotations", "1", "--size", "32", "--matcher", "none", "--set", "refs.encodings=[depth]"]
FAST = ["--set", "refine.render_iters=0", "--set", "match.matcher=sift-nn", "--set", "match.max_keypoints=128"]


def estimate(work, *extra, image=None, K=K_TEXT, box="default"):
    args = ["estimate", "--refs", work["refs"], "--image", image or work["photo"], f"--K={K}"]
    if box == "default":
        args += [f"--bbox={work['box']}"]
    elif box is not None:
        args += [f"--bbox={box}"]
    return cli(*args, *FAST, *extra)


def write_ply(path: Path, vertices, faces, binary: bool = False) -> Path:
    head = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}", "property float x", "property float y",
            "property float z"]
    if faces is not None:
        head += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    lines = head + ["end_header"] + [" ".join(map(str, v)) for v in vertices]
    lines += [f"{len(f)} " + " ".join(map(str, f)) for f in (faces or [])]
    path.write_text("\n".join(lines) + "\n")
    return path


TETRA = [(0, 0, 0), (60, 0, 0), (0, 40, 0), (0, 0, 30)]
TETRA_F = [(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)]


# ------------------------------------------------------------------------------------------- meshes


def test_baseline_refs_build_writes_the_named_file(work, tmp_path):
    rc, out, err = cli("refs", "build", work["mesh"], "-o", tmp_path / "set.npz", *SMALL)
    assert rc == 0, err
    assert (tmp_path / "set.npz").is_file() and "wrote" in out
    assert oct((tmp_path / "set.npz").stat().st_mode & 0o777) == oct(0o644 & ~_umask())


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


@pytest.mark.parametrize("name, content, needles", [
    ("missing.ply", None, ["not found", "missing.ply"]),
    ("empty.ply", b"", ["empty"]),
    ("garbage.ply", b"\x00\x01garbage" * 50, ["cannot read mesh"]),
    ("garbage.obj", b"v 1 2\nf 1 2 3 4 5\nxx\n", ["garbage.obj"]),
    ("text.stl", b"solid x\n facet normal 0 0 1\n endfacet\nendsolid\n", ["text.stl"]),
])
def test_unreadable_meshes(work, tmp_path, name, content, needles):
    if content is not None:
        (tmp_path / name).write_bytes(content)
    assert_error(cli("refs", "build", tmp_path / name, "-o", tmp_path / "o.npz", *SMALL), *needles)
    assert not (tmp_path / "o.npz").exists()


def test_face_index_out_of_range(tmp_path):
    path = write_ply(tmp_path / "bad_index.ply", TETRA, [(0, 1, 2), (0, 1, 7)])
    assert_error(cli("refs", "build", path, "-o", tmp_path / "o.npz", *SMALL), "face", "4 vertices")


def test_negative_face_index(tmp_path):
    path = write_ply(tmp_path / "neg_index.ply", TETRA, [(0, 1, 2), (0, -1, 3)])
    assert_error(cli("refs", "build", path, "-o", tmp_path / "o.npz", *SMALL), "face")


def test_point_cloud(tmp_path):
    path = write_ply(tmp_path / "cloud.ply", TETRA, None)
    assert_error(cli("refs", "build", path, "-o", tmp_path / "o.npz", *SMALL), "point cloud", "4 vertices")


def test_degenerate_mesh(tmp_path):
    path = write_ply(tmp_path / "flat.ply", [(0, 0, 0), (1, 1, 1), (2, 2, 2)], [(0, 1, 2)])
    assert_error(cli("refs", "build", path, "-o", tmp_path / "o.npz", *SMALL), "zero surface area")


def test_nan_vertices(tmp_path):
    path = write_ply(tmp_path / "nan.ply", [*TETRA[:3], ("nan", 0, 0)], TETRA_F)
    assert_error(cli("refs", "build", path, "-o", tmp_path / "o.npz", *SMALL), "nan")


def test_metre_scale_mesh_is_auto_detected_and_announced(tmp_path):
    path = write_ply(tmp_path / "metres.ply", [tuple(c / 1000 for c in v) for v in TETRA], TETRA_F)
    rc, out, err = cli("refs", "build", path, "-o", tmp_path / "o.npz", *SMALL)
    assert rc == 0, err
    assert "metres (auto-detected" in out and "diameter 72" in out and "--units" in out
    rc, out, err = cli("refs", "build", path, "-o", tmp_path / "o2.npz", "--units", "m", *SMALL)
    assert rc == 0, err
    assert "diameter 72" in out  # 60 x 40 x 30 mm tetrahedron: the longest edge is sqrt(60^2 + 40^2) = 72.1 mm


def test_implausible_size_without_units_is_refused(tmp_path):
    path = write_ply(tmp_path / "huge.ply", [tuple(c * 1000 for c in v) for v in TETRA], TETRA_F)
    assert_error(cli("refs", "build", path, "-o", tmp_path / "o.npz", *SMALL), "mm across", "--units")


def test_explicit_mm_units_accept_a_tiny_part_with_a_warning(tmp_path):
    path = write_ply(tmp_path / "tiny.ply", [tuple(c / 1000 for c in v) for v in TETRA], TETRA_F)
    rc, out, err = cli("refs", "build", path, "-o", tmp_path / "o.npz", "--units", "mm", *SMALL)
    assert rc == 0 and "Traceback" not in err
    assert "pixie: warning:" in err and "implausible" in err


def test_mesh_is_a_folder(tmp_path):
    assert_error(cli("refs", "build", tmp_path, "-o", tmp_path / "o.npz", *SMALL), "not found")


# ---------------------------------------------------------------------------------- output paths


def test_output_name_with_a_dot_keeps_its_exact_name(work, tmp_path):
    """``-o part_v1.2`` writes exactly part_v1.2, never part_v1.npz (which must survive untouched) nor part_v1.2.npz."""
    other = tmp_path / "part_v1.npz"
    other.write_bytes(b"someone else's set")
    rc, out, err = cli("refs", "build", work["mesh"], "-o", tmp_path / "part_v1.2", *SMALL)
    assert rc == 0, err
    assert (tmp_path / "part_v1.2").is_file() and not (tmp_path / "part_v1.2.npz").exists()
    assert other.read_bytes() == b"someone else's set"
    assert "part_v1.2 " in out


def test_existing_output_is_refused_before_any_work(work, tmp_path):
    target = tmp_path / "set.npz"
    target.write_bytes(b"precious")
    t0 = time.perf_counter()
    msg = assert_error(cli("refs", "build", work["mesh"], "-o", target, "--views", "400", "--matcher", "none"),
                       "exists", "--force")
    assert time.perf_counter() - t0 < 5.0, "the existing output was found only after rendering"
    assert target.read_bytes() == b"precious" and str(target) in msg


def test_force_overwrites(work, tmp_path):
    target = tmp_path / "set.npz"
    target.write_bytes(b"old")
    rc, _, err = cli("refs", "build", work["mesh"], "-o", target, "--force", *SMALL)
    assert rc == 0, err
    assert target.read_bytes()[:2] == b"PK"


def test_output_is_an_existing_folder(work, tmp_path):
    assert_error(cli("refs", "build", work["mesh"], "-o", tmp_path, *SMALL), "folder")


def test_output_is_dev_null(work):
    """A device is written into, never replaced or renamed (no /dev/null.npz)."""
    rc, _, err = cli("refs", "build", work["mesh"], "-o", "/dev/null", *SMALL)
    assert rc == 0, err
    assert Path("/dev/null").is_char_device() and not Path("/dev/null.npz").exists()


def test_output_folder_cannot_be_created(work):
    assert_error(cli("refs", "build", work["mesh"], "-o", work["file"] / "sub" / "x.npz", *SMALL), "cannot create")
    assert_error(cli("refs", "build", work["mesh"], "-o", "/proc/pixie_test/x.npz", *SMALL), "cannot create")


def test_estimate_json_output_checked_before_estimating(work, tmp_path):
    (tmp_path / "res.json").mkdir()
    assert_error(estimate(work, "-o", tmp_path / "res.json"), "folder")
    assert_error(estimate(work, "-o", work["file"] / "r.json"), "bad.txt", "not a folder")


def test_estimate_existing_json_output_refused(work, tmp_path):
    (tmp_path / "res.json").write_text("{}")
    assert_error(estimate(work, "-o", tmp_path / "res.json"), "exists")
    assert (tmp_path / "res.json").read_text() == "{}"


def test_estimate_overlay_output_checked(work):
    assert_error(estimate(work, "--overlay", work["file"] / "o.png"), "not a folder")


def test_refs_show_output_checked(work, tmp_path):
    assert_error(cli("refs", "show", work["refs"], "-o", tmp_path), "folder")


def test_refs_show_bad_tile(work, tmp_path):
    assert_error(cli("refs", "show", work["refs"], "-o", tmp_path / "s.png", "--tile", "100000"), "--tile")


def test_blank_photo_is_a_failed_pose_not_a_confident_one(work, tmp_path):
    cv2.imwrite(str(tmp_path / "grey.png"), np.full((H, W, 3), 128, np.uint8))
    rc, out, err = estimate(work, "-o", tmp_path / "r.json", image=tmp_path / "grey.png")
    assert rc == 1 and "Traceback" not in err, (out, err)
    res = json.loads((tmp_path / "r.json").read_text())
    assert res["failed"] and ("contrast" in res["message"] or "no pose" in res["message"])


def test_refs_show_bad_view_list(work, tmp_path):
    assert_error(cli("refs", "show", work["refs"], "-o", tmp_path / "s.png", "--views", "0,x"), "--views")
    assert_error(cli("refs", "show", work["refs"], "-o", tmp_path / "s.png", "--views", "0,99"), "99")


def test_run_output_is_a_file(work, lmo_dir):
    assert_error(cli("run", lmo_dir, "-o", work["file"], "--max-targets", "1"), "not a folder")


def test_eval_output_is_a_file(work, lmo_dir, tmp_path):
    csv = tmp_path / "r.csv"
    csv.write_text("scene_id,im_id,obj_id,score,R,t,time\n2,3,1,0.5,1 0 0 0 1 0 0 0 1,0 0 800,1.0\n")
    assert_error(cli("eval", lmo_dir, "--results", csv, "-o", work["file"]), "not a folder")


# ------------------------------------------------------------------------------------------ images


def test_baseline_estimate(work, tmp_path):
    rc, out, err = estimate(work, "-o", tmp_path / "r.json")
    assert rc in (0, 1) and "Traceback" not in err, err
    res = json.loads((tmp_path / "r.json").read_text())
    assert "confidence" in res and oct((tmp_path / "r.json").stat().st_mode & 0o777) == oct(0o644 & ~_umask())


def _png_header_only(path: Path, w: int, h: int) -> Path:
    """A PNG whose header claims w x h 8-bit RGB and which holds a tiny compressed stream."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 1000))
                     + chunk(b"IEND", b""))
    return path


@pytest.mark.parametrize("name, maker, needles", [
    ("missing.png", None, ["not found"]),
    ("empty.png", lambda p: p.write_bytes(b""), ["empty"]),
    ("garbage.png", lambda p: p.write_bytes(os.urandom(2000)), ["cannot decode"]),
    ("text.jpg", lambda p: p.write_text("hello"), ["cannot decode"]),
])
def test_unreadable_images(work, tmp_path, name, maker, needles):
    if maker:
        maker(tmp_path / name)
    assert_error(estimate(work, image=tmp_path / name), name, *needles)


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_truncated_image(work, tmp_path, ext):
    img = cv2.imread(str(work["photo"]))
    ok, buf = cv2.imencode(ext, img)
    data = buf.tobytes()
    (tmp_path / f"cut{ext}").write_bytes(data[: len(data) // 2])
    assert_error(estimate(work, image=tmp_path / f"cut{ext}"), "truncated")


def test_huge_image_header_refused_before_decoding(work, tmp_path):
    path = _png_header_only(tmp_path / "huge.png", 60000, 60000)
    t0 = time.perf_counter()
    assert_error(estimate(work, image=path), "3600 MP", "at most")
    assert time.perf_counter() - t0 < 5.0


def test_image_channel_formats_load_as_rgb(work, tmp_path):
    from pixie.pipeline.query import load_image

    rgb = cv2.imread(str(work["photo"]))[..., ::-1]
    grey = rgb[..., 0]
    cv2.imwrite(str(tmp_path / "grey.png"), grey)
    cv2.imwrite(str(tmp_path / "rgba.png"), np.dstack([rgb[..., ::-1], np.full(grey.shape, 7, np.uint8)]))
    cv2.imwrite(str(tmp_path / "sixteen.png"), rgb[..., ::-1].astype(np.uint16) * 257)
    cv2.imwrite(str(tmp_path / "grey16.png"), grey.astype(np.uint16) * 257)
    assert np.array_equal(load_image(tmp_path / "grey.png"), np.dstack([grey] * 3))
    assert np.array_equal(load_image(tmp_path / "rgba.png"), rgb)
    assert np.array_equal(load_image(tmp_path / "sixteen.png"), rgb)
    assert np.array_equal(load_image(tmp_path / "grey16.png"), np.dstack([grey] * 3))


def test_rgba_and_grey_photos_estimate(work, tmp_path):
    grey = cv2.imread(str(work["photo"]), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(tmp_path / "grey.png"), grey)
    rc, out, err = estimate(work, image=tmp_path / "grey.png")
    assert rc in (0, 1) and "Traceback" not in err and "pose" in out


def _jpeg_with_orientation(src: Path, dst: Path, orientation: int) -> Path:
    from PIL import Image

    im = Image.open(src)
    exif = Image.Exif()
    exif[0x0112] = orientation
    im.save(dst, exif=exif.tobytes(), quality=95)
    return dst


def test_exif_rotated_jpeg_keeps_stored_pixels_and_says_so(work, tmp_path):
    from pixie.pipeline.query import load_image

    plain = load_image(_jpeg_with_orientation(work["photo"], tmp_path / "plain.jpg", 1))
    with pytest.warns(UserWarning, match="EXIF orientation"):
        rotated = load_image(_jpeg_with_orientation(work["photo"], tmp_path / "rot.jpg", 6))
    assert rotated.shape == (H, W, 3)  # the stored pixels, which K and the box describe
    assert np.array_equal(rotated, plain)
    rc, out, err = estimate(work, image=tmp_path / "rot.jpg")
    assert rc in (0, 1) and "pixie: warning:" in err and "EXIF orientation 6" in err


def test_float_array_image_refused_by_api(work):
    from pixie.errors import ImageError
    from pixie.pipeline.estimator import PoseEstimator
    from pixie.config import PixieConfig
    from pixie.references.store import load_reference_set

    est = PoseEstimator(load_reference_set(work["refs"]), _fast_cfg())
    with pytest.raises(ImageError, match="uint8"):
        est.estimate(np.zeros((H, W, 3), np.float32), np.eye(3) * 300 + [[0, 0, 159.5], [0, 0, 119.5], [0, 0, -299]])
    assert PixieConfig  # imported for the type


def _fast_cfg():
    from pixie.config import PixieConfig

    cfg = PixieConfig()
    for item in ("refine.render_iters=0", "match.matcher=sift-nn", "match.max_keypoints=128", "shape.enabled=false"):
        cfg.set(*item.split("="))
    return cfg


# --------------------------------------------------------------------------------------- intrinsics


@pytest.mark.parametrize("K, needles", [
    ("a,b,c,d", ["cannot parse intrinsics"]),
    ("300,300,160", ["3 values"]),
    ("", ["intrinsics"]),
    ("0,300,160,120", ["focal"]),
    ("-300,300,160,120", ["focal"]),
    ("nan,300,160,120", ["non-finite"]),
    ("inf,300,160,120", ["non-finite"]),
    ("300,300,900,120", ["principal point"]),
    ("300,0,-5,0,300,0,0,0,1", ["principal point"]),
    ("300,0,160,0,300,120,0,1,1", ["last row"]),
    ("4.2,4.2,160,120", ["field of view", "4.2"]),
    ("1e9,1e9,160,120", ["field of view"]),
])
def test_bad_intrinsics(work, K, needles):
    assert_error(estimate(work, K=K), *needles)


@pytest.mark.parametrize("K, needle", [("300,150,159.5,119.5", "fx/fy"), ("300,300,0,0", "principal point"),
                                       ("30000,30000,159.5,119.5", "field of view")])
def test_unusual_intrinsics_warn(work, K, needle):
    rc, out, err = estimate(work, K=K)
    assert rc in (0, 1) and "Traceback" not in err
    assert "pixie: warning:" in err and needle in err


def test_intrinsics_separated_by_spaces(work):
    rc, out, err = estimate(work, K="300 300 159.5 119.5", box=work["box"].replace(",", " "))
    assert rc in (0, 1) and "Traceback" not in err and "pose" in out, err


def test_output_that_is_an_input_is_refused_even_with_force(work, tmp_path):
    photo = tmp_path / "photo.png"
    photo.write_bytes(work["photo"].read_bytes())
    assert_error(estimate(work, "--overlay", photo, "--force", image=photo), "also an input")
    assert photo.read_bytes() == work["photo"].read_bytes()


# ---------------------------------------------------------------------------------------- boxes/masks


@pytest.mark.parametrize("box, needles", [
    ("a,b,c,d", ["--bbox", "a,b,c,d"]),
    ("10,10,50", ["--bbox", "4"]),
    ("", ["--bbox"]),
    ("10,10,nan,50", ["--bbox"]),
    ("1000,1000,50,50", ["covers no part"]),
    ("-500,-500,50,50", ["covers no part"]),
    ("10,10,-50,50", ["bbox"]),
    ("100,100,2,2", ["too small", "2x2"]),
    ("100,100,200,3", ["too small"]),
])
def test_bad_boxes(work, box, needles):
    assert_error(estimate(work, box=box), *needles)


def test_mask_of_another_size(work, tmp_path):
    cv2.imwrite(str(tmp_path / "m.png"), np.full((100, 100), 255, np.uint8))
    assert_error(estimate(work, "--mask", tmp_path / "m.png", box=None), "100x100", f"{W}x{H}")


def test_empty_mask(work, tmp_path):
    cv2.imwrite(str(tmp_path / "m.png"), np.zeros((H, W), np.uint8))
    assert_error(estimate(work, "--mask", tmp_path / "m.png", box=None), "mask is empty")


def test_missing_mask(work, tmp_path):
    assert_error(estimate(work, "--mask", tmp_path / "none.png", box=None), "not found", "none.png")


def test_mask_and_box_disjoint(work, tmp_path):
    m = np.zeros((H, W), np.uint8)
    m[:20, :20] = 255
    cv2.imwrite(str(tmp_path / "m.png"), m)
    assert_error(estimate(work, "--mask", tmp_path / "m.png", box="200,150,60,60"), "mask", "box")


def test_api_mask_of_another_size(work):
    from pixie.errors import ImageError
    from pixie.references.store import load_reference_set
    from pixie.pipeline.estimator import PoseEstimator
    from pixie.geometry.camera import parse_K

    est = PoseEstimator(load_reference_set(work["refs"]), _fast_cfg())
    img = cv2.imread(str(work["photo"]))[..., ::-1].copy()
    with pytest.raises(ImageError, match="mask"):
        est.estimate(img, parse_K(K_TEXT), mask=np.ones((100, 100), bool))


# ------------------------------------------------------------------------------------- reference sets


def test_missing_refs(work, tmp_path):
    assert_error(cli("estimate", "--refs", tmp_path / "no.npz", "--image", work["photo"], "--K", K_TEXT, "--bbox", work["box"]),
                 "not found", "refs build")


@pytest.mark.parametrize("kind", ["garbage", "truncated", "plain_npz", "text"])
def test_corrupt_refs(work, tmp_path, kind):
    p = tmp_path / "r.npz"
    data = work["refs"].read_bytes()
    if kind == "garbage":
        p.write_bytes(os.urandom(5000))
    elif kind == "truncated":
        p.write_bytes(data[: len(data) // 2])
    elif kind == "plain_npz":
        np.savez(p, a=np.zeros(3))
    else:
        p.write_text("hello")
    assert_error(cli("estimate", "--refs", p, "--image", work["photo"], "--K", K_TEXT, "--bbox", work["box"]),
                 str(p))


def _rewrite_meta(src: Path, dst: Path, **changes) -> Path:
    with np.load(src) as z:
        data = {k: z[k] for k in z.files}
    meta = json.loads(data["meta"].tobytes().decode())
    meta.update(changes)
    data["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    with open(dst, "wb") as fh:
        np.savez(fh, **data)
    return dst


def test_stale_refs_format(work, tmp_path):
    p = _rewrite_meta(work["refs"], tmp_path / "old.npz", format_version=0)
    assert_error(cli("estimate", "--refs", p, "--image", work["photo"], "--K", K_TEXT, "--bbox", work["box"]), "format version", "rebuild")


def test_refs_with_broken_config(work, tmp_path):
    p = _rewrite_meta(work["refs"], tmp_path / "cfg.npz", config={"size": "big", "unknown": 1})
    assert_error(cli("estimate", "--refs", p, "--image", work["photo"], "--K", K_TEXT, "--bbox", work["box"]), str(p))


def test_refs_missing_an_array(work, tmp_path):
    with np.load(work["refs"]) as z:
        data = {k: z[k] for k in z.files if k != "poses"}
    np.savez(tmp_path / "partial.npz", **data)
    assert_error(cli("estimate", "--refs", tmp_path / "partial.npz", "--image", work["photo"], "--K", K_TEXT, "--bbox", work["box"]),
                 "missing")


def test_foreign_refs_refused_by_api(work, tmp_path):
    from pixie.errors import ReferenceSetError
    from pixie.geometry.mesh import load_mesh
    from pixie.references.store import load_reference_set

    other = load_mesh(write_ply(tmp_path / "other.ply", TETRA, TETRA_F))
    with pytest.raises(ReferenceSetError, match="another mesh"):
        load_reference_set(work["refs"], mesh=other)


def test_refs_of_another_matcher(work):
    assert_error(estimate(work, "--set", "match.matcher=disk-nn"), "sift-nn", "disk-nn", "refs build")


def test_refs_is_a_mesh(work):
    assert_error(cli("estimate", "--refs", work["mesh"], "--image", work["photo"], "--K", K_TEXT, "--bbox", work["box"]), "part.ply")


# ------------------------------------------------------------------------------------- config: YAML


@pytest.mark.parametrize("text, needles", [
    ("refs: 5\n", ["refs", "mapping"]),
    ("refs:\n  - size\n", ["refs", "mapping"]),
    ("- 1\n- 2\n", ["mapping"]),
    ("refs: {colour: red}\n", ["unknown key", "colour"]),
    ("optics: {size: 3}\n", ["unknown config section", "optics"]),
    ("refs: {size: big}\n", ["refs.size", "big"]),
    ("refs: {size: 0}\n", ["refs.size"]),
    ("refs: {canonical: 3}\n", ["refs.canonical", "true/false"]),
    ("refs: {size: [64\n", ["cannot read config"]),
    ("match: {matcher: [a, b]}\n", ["match.matcher", "text"]),
])
def test_bad_yaml(work, tmp_path, text, needles):
    (tmp_path / "c.yaml").write_text(text)
    assert_error(cli("refs", "build", work["mesh"], "-o", tmp_path / "o.npz", "--config", tmp_path / "c.yaml"),
                 *needles)


def test_yaml_not_utf8(work, tmp_path):
    (tmp_path / "c.yaml").write_bytes(b"refs: {size: \xff\xfe}\n")
    assert_error(cli("refs", "build", work["mesh"], "-o", tmp_path / "o.npz", "--config", tmp_path / "c.yaml"),
                 "c.yaml")


def test_yaml_missing(work, tmp_path):
    assert_error(cli("refs", "build", work["mesh"], "-o", tmp_path / "o.npz", "--config", tmp_path / "no.yaml"),
                 "no.yaml")


# ------------------------------------------------------------------------------------- config: --set


@pytest.mark.parametrize("item, needles", [
    ("refs.size=0", ["refs.size", "0"]),
    ("refs.size=1.5", ["refs.size", "whole number"]),
    ("refs.size=.nan", ["refs.size"]),
    ("refs.size=100000", ["refs.size"]),
    ("refs.n_fibonacci=-3", ["refs.n_fibonacci", "-3"]),
    ("refs.rotations=0", ["refs.rotations"]),
    ("refs.crop_pad=0.5", ["refs.crop_pad"]),
    ("query.crop_pad=-1", ["query.crop_pad", "-1"]),
    ("refs.encodings=[]", ["refs.encodings"]),
    ("refs.encodings=[depth, 3]", ["refs.encodings"]),
    ("refs.feature_rolls=some", ["refs.feature_rolls", "all"]),
    ("match.in_plane=sideways", ["match.in_plane", "reference"]),
    ("match.window=0", ["match.window"]),
    ("match.max_keypoints=0", ["match.max_keypoints"]),
    ("pose.solver=magic", ["pose.solver", "poselib"]),
    ("pose.min_inliers=2", ["pose.min_inliers"]),
    ("pose.confidence=1.5", ["pose.confidence"]),
    ("pose.reprojection_px=0", ["pose.reprojection_px"]),
    ("refine.render_iters=-1", ["refine.render_iters"]),
    ("refs.size", ["section.key=value"]),
    ("size=3", ["section.key"]),
    ("refs.colour=3", ["unknown key", "colour"]),
])
def test_bad_set_values(work, tmp_path, item, needles):
    t0 = time.perf_counter()
    assert_error(cli("refs", "build", work["mesh"], "-o", tmp_path / "o.npz", "--set", item), *needles)
    assert time.perf_counter() - t0 < 5.0  # refused before any rendering (a default build takes minutes)


def test_string_for_a_list_is_a_one_item_list():
    from pixie.config import PixieConfig

    cfg = PixieConfig()
    cfg.set("refs.encodings", "depth")
    assert cfg.refs.encodings == ["depth"]
    cfg.set("refs.encodings", "depth,normal")
    assert cfg.refs.encodings == ["depth", "normal"]


def test_direct_assignment_is_validated_too():
    from pixie.config import PixieConfig
    from pixie.errors import ConfigError

    cfg = PixieConfig()
    with pytest.raises(ConfigError, match="refs.size"):
        cfg.refs.size = 0
    with pytest.raises(ConfigError, match="query.crop_pad"):
        cfg.query.crop_pad = -2.0
    assert cfg.refs.size == 256 and cfg.query.crop_pad == 1.2


def test_bad_cli_numbers(work, tmp_path):
    assert_error(cli("refs", "build", work["mesh"], "-o", tmp_path / "o.npz", "--views", "3"), "--views")
    assert_error(cli("refs", "build", work["mesh"], "-o", tmp_path / "o.npz", "--size", "-5"), "refs.size")
    assert_error(cli("refs", "build", work["mesh"], "-o", tmp_path / "o.npz", "--workers", "0", *SMALL),
                 "--workers")
    code, _, err = cli("refs", "build", work["mesh"], "-o", tmp_path / "o.npz", "--views", "abc")
    assert code == 2 and "invalid int value" in err and "Traceback" not in err


# ------------------------------------------------------------------------------------- results CSVs


def _eval(lmo_dir, tmp_path, text: str | bytes):
    csv = tmp_path / "r.csv"
    (csv.write_bytes if isinstance(text, bytes) else csv.write_text)(text)
    return cli("eval", lmo_dir, "--results", csv, "-o", tmp_path / "ev", "--no-report")


HEADER = "scene_id,im_id,obj_id,score,R,t,time\n"
ROW = "2,3,{o},0.5,1 0 0 0 1 0 0 0 1,0 0 800,1.0\n"


@pytest.mark.parametrize("text, needles", [
    ("", ["no results"]),
    (HEADER, ["no results"]),
    ("\n\n", ["no results"]),
    (HEADER + ROW.format(o=99), ["object", "99"]),
    (HEADER + ROW.format(o=1)[:25] + "\n", ["line 2"]),
    (HEADER + ROW.format(o=1).replace("0.5", "nan"), ["line 2"]),
    (HEADER + "2,3,1,0.5,1 0 0 0 1 0 0 0,0 0 800,1\n", ["line 2"]),
    ("scene,image,object\n" + ROW.format(o=1), ["line 1", "7"]),
    (HEADER + "999,3,1,0.5,1 0 0 0 1 0 0 0 1,0 0 800,1.0\n", ["scene", "999"]),
])
def test_bad_results_csv(lmo_dir, tmp_path, text, needles):
    assert_error(_eval(lmo_dir, tmp_path, text), *needles)
    assert not (tmp_path / "ev" / "scores.json").exists()


def test_results_csv_of_no_target(lmo_dir, tmp_path):
    assert_error(_eval(lmo_dir, tmp_path, HEADER + ROW.format(o=1).replace("2,3,", "2,99999,", 1)), "none of its 1 rows")


def test_eval_n_points(lmo_dir, tmp_path):
    (tmp_path / "r.csv").write_text(HEADER + ROW.format(o=1))
    assert_error(cli("eval", lmo_dir, "--results", tmp_path / "r.csv", "-o", tmp_path / "ev", "--n-points", "0"),
                 "--n-points")


def test_results_csv_not_utf8(lmo_dir, tmp_path):
    assert_error(_eval(lmo_dir, tmp_path, HEADER.encode() + b"2,3,1,0.5,\xff\xfe\n"), "utf-8")


def test_results_csv_missing(lmo_dir, tmp_path):
    assert_error(cli("eval", lmo_dir, "--results", tmp_path / "none.csv", "-o", tmp_path / "ev"), "not found")


def test_eval_dataset_missing(tmp_path):
    (tmp_path / "r.csv").write_text(HEADER + ROW.format(o=1))
    assert_error(cli("eval", tmp_path / "nods", "--results", tmp_path / "r.csv", "-o", tmp_path / "ev"),
                 "dataset folder not found")


@pytest.mark.parametrize("metrics, needle", [("xyz", "unknown metric"), ("", "no metric"), (",,", "no metric")])
def test_eval_bad_metrics(lmo_dir, tmp_path, metrics, needle):
    (tmp_path / "r.csv").write_text(HEADER + ROW.format(o=1))
    assert_error(cli("eval", lmo_dir, "--results", tmp_path / "r.csv", "-o", tmp_path / "ev", "--metrics", metrics),
                 needle)


def test_run_on_a_dataset_without_models(tmp_path):
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "test_targets_bop19.json").write_text('[{"scene_id":1,"im_id":1,"obj_id":1,"inst_count":1}]')
    t0 = time.perf_counter()
    assert_error(cli("run", tmp_path / "ds", "-o", tmp_path / "out"), "model file not found")
    assert time.perf_counter() - t0 < 5.0
    assert_error(cli("run", tmp_path / "nothing", "-o", tmp_path / "out"), "not found")


def test_run_bad_objects(work, lmo_dir, tmp_path):
    assert_error(cli("run", lmo_dir, "-o", tmp_path / "run", "--objects", "1,x"), "--objects")
    assert_error(cli("run", lmo_dir, "-o", tmp_path / "run", "--objects", "77"), "77")
    assert_error(cli("run", lmo_dir, "-o", tmp_path / "run", "--max-targets", "0"), "--max-targets")


# ------------------------------------------------------------------------------------------ signals


def _spawn(*argv) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(SRC), PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    # SIGINT back to its default in the child: a test runner started as `nohup ... &` ignores it, and an ignored
    # signal is inherited (Python then installs no KeyboardInterrupt handler)
    return subprocess.Popen([sys.executable, "-m", "pixie", *map(str, argv)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=_default_signals)


def _reap(proc: subprocess.Popen) -> None:
    """Kill a spawned command's process group if it still runs, so a failed test leaves nothing behind."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)


def _default_signals() -> None:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_DFL)


def _children(pid: int) -> list[int]:
    kids = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                stat = (p / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(p.name))
    return kids


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _wait_started(proc: subprocess.Popen, timeout: float = 30.0) -> str:
    """Wait for the 'N views x R rolls' line that refs build prints before rendering (after the units line)."""
    line = proc.stdout.readline()
    if line.startswith("mesh "):  # the units note comes first
        line = proc.stdout.readline()
    assert "views x" in line, (line, proc.stderr.read() if proc.poll() is not None else "")
    return line


@pytest.mark.parametrize("workers", [1, 2])
def test_ctrl_c_during_refs_build(work, tmp_path, workers):
    out = tmp_path / "big.npz"
    proc = _spawn("refs", "build", work["mesh"], "-o", out, "--views", "3000", "--rotations", "1", "--size", "96",
                  "--matcher", "none", "--workers", workers)
    try:
        _wait_started(proc)
        time.sleep(0.5)
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C reaches the whole foreground group
        _, err = proc.communicate(timeout=30)
    finally:
        _reap(proc)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert [ln for ln in err.splitlines() if ln.startswith("pixie:")] == ["pixie: interrupted"], err
    assert not out.exists() and not list(tmp_path.glob(".big*"))


def test_sigterm_during_refs_build(work, tmp_path):
    out = tmp_path / "big.npz"
    proc = _spawn("refs", "build", work["mesh"], "-o", out, "--views", "3000", "--rotations", "1", "--size", "96",
                  "--matcher", "none", "--workers", "2")
    try:
        _wait_started(proc)
        time.sleep(0.3)
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    finally:
        _reap(proc)
    assert proc.returncode == 143 and "Traceback" not in err, err
    assert [ln for ln in err.splitlines() if ln.startswith("pixie:")] == ["pixie: terminated"], err
    assert not out.exists() and not list(tmp_path.glob(".big*"))


def test_sigkill_of_parent_leaves_no_workers(work, tmp_path):
    proc = _spawn("refs", "build", work["mesh"], "-o", tmp_path / "big.npz", "--views", "3000", "--rotations", "1",
                  "--size", "96", "--matcher", "none", "--workers", "2")
    try:
        _wait_started(proc)
        deadline = time.time() + 20
        while len(_children(proc.pid)) < 2 and time.time() < deadline:
            time.sleep(0.1)
        kids = _children(proc.pid)
        assert len(kids) >= 2
        proc.kill()
        proc.wait(timeout=10)
        deadline = time.time() + 10
        while any(_alive(k) for k in kids) and time.time() < deadline:
            time.sleep(0.1)
        assert not any(_alive(k) for k in kids), "worker processes outlived their parent"
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # its own session: the build and any worker it left
        except ProcessLookupError:
            pass
        proc.wait(timeout=10)


# ------------------------------------------------------------------------------------------ Python API


def test_api_wrong_argument_types(work):
    from pixie.geometry.camera import validate_K
    from pixie.config import PixieConfig
    from pixie.errors import PixieError
    from pixie.geometry.mesh import load_mesh
    from pixie.pipeline.query import load_image
    from pixie.references.set import build_reference_set
    from pixie.references.store import load_reference_set

    for call in (lambda: load_mesh(None), lambda: load_image(3), lambda: load_reference_set(None),
                 lambda: build_reference_set("part.ply"), lambda: validate_K(None), lambda: validate_K("K"),
                 lambda: build_reference_set(load_mesh(work["mesh"]), object()),
                 lambda: PixieConfig.from_dict({"refs": 5}), lambda: PixieConfig.from_dict([1, 2])):
        with pytest.raises(PixieError):
            call()


def test_api_build_accepts_a_whole_config(work):
    from pixie.config import PixieConfig
    from pixie.geometry.mesh import load_mesh
    from pixie.references.set import build_reference_set

    cfg = PixieConfig()
    cfg.set("refs.n_fibonacci", 0)
    cfg.set("refs.rotations", 1)
    cfg.set("refs.size", 32)
    cfg.set("refs.encodings", "depth")
    refs = build_reference_set(load_mesh(work["mesh"]), cfg)
    assert refs.n_views == 6 and refs.size == 32


# ------------------------------------------------------------------------------------- plausibility


def _projected_box(mesh, T, K):
    from pixie.geometry.camera import project, transform_points

    uv = project(K, transform_points(T, mesh.vertices))
    return np.r_[uv.min(0) + 0.5, uv.max(0) + 0.5]


@pytest.fixture(scope="module")
def plaus(work):
    from pixie.geometry.camera import parse_K
    from pixie.geometry.mesh import load_mesh

    mesh = load_mesh(work["mesh"])
    return mesh, work["T"], parse_K(K_TEXT)


def _contradictions(mesh, T, K, box):
    from pixie.pose.plausibility import pose_contradictions

    return pose_contradictions(T, K, box, mesh.hull_vertices, mesh.center, mesh.bounding_radius)


def test_true_pose_is_plausible(plaus):
    mesh, T, K = plaus
    box = _projected_box(mesh, T, K)
    assert _contradictions(mesh, T, K, box) == []
    occluded = box.copy()
    occluded[2] = box[0] + 0.3 * (box[2] - box[0])  # only the left 30 % visible
    assert _contradictions(mesh, T, K, occluded) == []


@pytest.mark.parametrize("scale_z, needle", [(20.0, "too far"), (0.12, "too close")])
def test_pose_at_the_wrong_distance_is_implausible(plaus, scale_z, needle):
    mesh, T, K = plaus
    box = _projected_box(mesh, T, K)
    T2 = T.copy()
    T2[:3, 3] = T[:3, 3] * scale_z  # same direction, 20x farther / 8x closer
    reasons = _contradictions(mesh, T2, K, box)
    assert any(needle in r for r in reasons), reasons


def test_pose_beside_the_box_is_implausible(plaus):
    mesh, T, K = plaus
    box = _projected_box(mesh, T, K)
    T2 = T.copy()
    T2[0, 3] += 0.8 * mesh.diameter  # shifted sideways by most of its size
    assert any("of the box lies inside" in r for r in _contradictions(mesh, T2, K, box))


def test_pose_behind_the_camera_is_implausible(plaus):
    mesh, T, K = plaus
    T2 = T.copy()
    T2[:3, 3] *= -1
    assert any("behind the camera" in r for r in _contradictions(mesh, T2, K, _projected_box(mesh, T, K)))
    T3 = T.copy()
    T3[:3, 3] = -T[:3, :3] @ mesh.center
    assert any("inside the object" in r for r in _contradictions(mesh, T3, K, _projected_box(mesh, T, K)))


# ------------------------------------------------------------------------------------- thread safety


def test_two_threads_share_one_estimator(work):
    """2 threads x 4 estimates with one PoseEstimator give the serial results bit for bit, and the estimator
    leaves the config it was given as it was."""
    import copy
    from concurrent.futures import ThreadPoolExecutor

    from pixie.geometry.camera import parse_K
    from pixie.config import RefsConfig
    from pixie.pipeline.estimator import PoseEstimator
    from pixie.matching import get_matcher
    from pixie.geometry.mesh import load_mesh
    from pixie.references.set import build_reference_set

    cfg = _fast_cfg()
    cfg.set("refine.render_iters", 1)
    cfg.set("match.in_plane", "reference")
    before = copy.deepcopy(cfg.to_dict())
    # features of roll 0 only make the estimator rotate the query: it must not write that into cfg
    refs = build_reference_set(load_mesh(work["mesh"]), RefsConfig(n_fibonacci=4, rotations=2, size=64,
                               encodings=["shade3_edges"], feature_rolls="first"),
                               matcher=get_matcher("sift-nn", max_keypoints=128, window=16.0))
    est = PoseEstimator(refs, cfg)
    assert cfg.to_dict() == before
    img = cv2.imread(str(work["photo"]))[..., ::-1].copy()
    K = parse_K(K_TEXT)
    x, y, w, h = map(int, work["box"].split(","))
    boxes = [(x, y, w, h), (x - 3, y - 2, w + 6, h + 4), (x + 2, y + 1, w - 4, h - 2), (x - 6, y, w + 6, h + 3)]
    serial = [est.estimate(img, K, bbox=b) for b in boxes]
    with ThreadPoolExecutor(2) as pool:
        runs = [pool.submit(lambda: [est.estimate(img, K, bbox=b) for b in boxes]) for _ in range(2)]
        threaded = [r.result() for r in runs]
    for results in threaded:
        for a, b in zip(serial, results):
            assert (a.T_cam_from_obj is None) == (b.T_cam_from_obj is None)
            if a.T_cam_from_obj is not None:
                assert np.array_equal(a.T_cam_from_obj, b.T_cam_from_obj)
            assert (a.score, a.n_inliers, a.view, a.roll, a.failed, a.message) == \
                   (b.score, b.n_inliers, b.view, b.roll, b.failed, b.message)
    assert cfg.to_dict() == before


def test_estimator_flags_a_pose_that_contradicts_its_box(work, plaus):
    from pixie.pipeline.estimator import Hypothesis, PoseEstimator
    from pixie.references.store import load_reference_set

    mesh, T, K = plaus
    est = PoseEstimator(load_reference_set(work["refs"]), _fast_cfg())
    img = cv2.imread(str(work["photo"]))[..., ::-1].copy()
    q = est.prepare(img, K, bbox=[int(v) for v in work["box"].split(",")])
    far = T.copy()
    far[:3, 3] *= 20.0
    good = est.result([Hypothesis(T_cam_from_obj=T, score=5.0, n_inliers=20, n_matches=30, view=0, roll=0, rot_to_ref_deg=0.0, box_iou=1.0)], {}, q)
    bad = est.result([Hypothesis(T_cam_from_obj=far, score=5.0, n_inliers=20, n_matches=30, view=0, roll=0, rot_to_ref_deg=0.0, box_iou=1.0)], {}, q)
    assert not good.failed and good.message == "ok"
    assert bad.failed and bad.message.startswith("implausible") and "too far" in bad.message
    assert bad.T_cam_from_obj is far  # the best guess is still returned
    blank = est.prepare(np.full_like(img, 128), K, bbox=[int(v) for v in work["box"].split(",")])
    flat = est.result([Hypothesis(T_cam_from_obj=T, score=5.0, n_inliers=20, n_matches=30, view=0, roll=0, rot_to_ref_deg=0.0, box_iou=1.0)], {}, blank)
    assert flat.failed and "no contrast" in flat.message


# ------------------------------------------------------------------------------------------ pixie run

TINY_RUN = ["--objects", "1", "--max-targets", "2", "--no-report", "--set", "refs.n_fibonacci=4", "--set",
            "refs.rotations=2", "--set", "refs.size=64", "--set", "refs.encodings=[shade3_edges]", *FAST]


def test_run_resume_detects_cut_lines_and_changed_config(lmo_dir, tmp_path):
    out = tmp_path / "run"
    rc, text, err = cli("run", lmo_dir, "-o", out, *TINY_RUN)
    assert rc == 0, err
    assert "2 targets, 0 cached, 2 to run" in text
    jsonl = out / "per_target.jsonl"
    lines = jsonl.read_text().splitlines()
    assert len(lines) == 2
    for p in (jsonl, out / "results.csv", out / "config.json", out / "scores.json"):
        assert p.stat().st_mode & 0o777 == 0o644 & ~_umask(), p
    # a crash cut the last line; the same config resumes: the cut line is reported and its target redone
    jsonl.write_text(lines[0] + "\n" + lines[1][: len(lines[1]) // 2])
    rc, text, err = cli("run", lmo_dir, "-o", out, *TINY_RUN)
    assert rc == 0, err
    assert "cut or corrupt (line 2)" in text and "2 targets, 1 cached, 1 to run" in text
    done = [json.loads(ln) for ln in jsonl.read_text().splitlines()[:1] + jsonl.read_text().splitlines()[2:]]
    assert sorted(tuple(d["key"]) for d in done) == sorted(tuple(json.loads(ln)["key"]) for ln in lines)
    rows = (out / "results.csv").read_text().splitlines()[1:]
    assert len(rows) >= 1 and {tuple(map(int, r.split(",")[:3])) for r in rows} <= {tuple(json.loads(ln)["key"]) for ln in lines}
    # another config: nothing is reused, and config.json says which config made the results
    rc, text, err = cli("run", lmo_dir, "-o", out, *TINY_RUN, "--set", "query.crop_pad=1.3")
    assert rc == 0, err
    assert "2 targets, 0 cached, 2 to run" in text and "another config" in text
    assert json.loads((out / "config.json").read_text())["query"]["crop_pad"] == 1.3


def test_sigterm_watchdog_ends_a_hanging_clean_exit(tmp_path):
    """A clean exit after SIGTERM that hangs (a pool or lock caught mid-operation) still ends, with 143 and one line."""
    code = (
        "import signal, sys, time\n"
        "from pixie.app import signals as cli\n"
        "cli.TERM_GRACE_S = 1.0\n"
        "signal.signal(signal.SIGTERM, cli.on_sigterm)\n"
        "try:\n"
        "    print('ready', flush=True)  # inside the try: a SIGTERM right after it is caught too\n"
        "    time.sleep(60)\n"
        "except BaseException:\n"
        "    time.sleep(60)  # the clean-up hangs\n"
    )
    env = dict(os.environ, PYTHONPATH=str(SRC), PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, preexec_fn=_default_signals)
    try:
        assert proc.stdout.readline().strip() == "ready"
        t0 = time.time()
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    finally:
        _reap(proc)
    assert proc.returncode == 143 and err.strip() == "pixie: terminated", err
    assert time.time() - t0 < 20


# ------------------------------------------------------------------------- reliability, third round


def _batch_folder(work, tmp_path, copies: int = 2) -> Path:
    """A folder of ``copies`` photos with identical bytes."""
    folder = tmp_path / "photos"
    folder.mkdir()
    for k in range(copies):
        (folder / f"p{k}.png").write_bytes(work["photo"].read_bytes())
    return folder


def test_batch_of_identical_photos_keeps_one_result_each(work, tmp_path):
    folder = _batch_folder(work, tmp_path)
    rc, out, err = cli("estimate", "--refs", work["refs"], "--batch", folder, "--K", K_TEXT, "--bbox", work["box"],
                       "-o", tmp_path / "out", "--no-overlays", *FAST)
    assert rc == 0, err
    assert "2 images, 0 cached, 2 to run" in out
    rows = (tmp_path / "out" / "results.csv").read_text().splitlines()[1:]
    assert sorted(int(r.split(",")[1]) for r in rows) == [0, 1]  # both im_ids, once each
    recs = [json.loads(ln) for ln in (tmp_path / "out" / "results.jsonl").read_text().splitlines()]
    assert [r["name"] for r in recs] == ["p0.png", "p1.png"] and len({r["key"] for r in recs}) == 2


@pytest.mark.parametrize("value", ["-1", "0"])
def test_batch_max_items_must_be_positive(work, tmp_path, value):
    folder = _batch_folder(work, tmp_path, 1)
    assert_error(cli("estimate", "--refs", work["refs"], "--batch", folder, "--K", K_TEXT, "--bbox", work["box"],
                     "-o", tmp_path / "out", "--max-items", value, *FAST), "--max-items", value)
    assert not (tmp_path / "out" / "journal.jsonl").exists()


def test_batch_journal_reports_a_cut_last_line(work, tmp_path):
    folder = _batch_folder(work, tmp_path)
    args = ["estimate", "--refs", work["refs"], "--batch", folder, "--K", K_TEXT, "--bbox", work["box"],
            "-o", tmp_path / "out", "--no-overlays", *FAST]
    assert cli(*args)[0] == 0
    journal = tmp_path / "out" / "journal.jsonl"
    lines = journal.read_text().splitlines()
    journal.write_text(lines[0] + "\n" + lines[1][: len(lines[1]) // 2])  # a kill cut the last line
    rc, out, err = cli(*args)
    assert rc == 0, err
    assert "cut or corrupt (line 2)" in out and "2 images, 1 cached, 1 to run" in out
    assert len((tmp_path / "out" / "results.jsonl").read_text().splitlines()) == 2


def test_every_numeric_config_field_has_a_range():
    import dataclasses

    from pixie.config import RANGES, PixieConfig

    cfg = PixieConfig()
    missing = [f"{s.name}.{f.name}" for s in dataclasses.fields(cfg) if s.name != "preset"
               for f in dataclasses.fields(getattr(cfg, s.name))
               if f.type.split("|")[0].strip() in ("int", "float") and f"{s.name}.{f.name}" not in RANGES]
    assert not missing, f"numeric config fields without a RANGES entry: {missing}"


@pytest.mark.parametrize("item", ["shape.w_edge=-100", "shape.w_match=-1", "align.w_fit=-0.5", "align.min_fit=2",
                                  "match.detection_threshold=5", "shape.region_weight=-3"])
def test_negative_weights_and_out_of_range_thresholds_are_refused(work, tmp_path, item):
    assert_error(cli("refs", "build", work["mesh"], "-o", tmp_path / "o.npz", "--set", item), item.split("=")[0])


@pytest.mark.parametrize("what", ["zero R", "scaled R", "reflection", "nan t", "nan score"])
def test_evaluate_refuses_estimates_that_are_not_poses(synthetic_bop, what):
    from pixie.eval.datasets import BopDataset, PoseEstimate
    from pixie.eval.evaluate import evaluate

    root, _ = synthetic_bop
    g = next(g for g in BopDataset(root).instances(1, 0) if g.obj_id == 1)
    T, score = g.T_cam_from_obj.copy(), 1.0
    if what == "zero R":
        T[:3, :3] = 0
    elif what == "scaled R":
        T[:3, :3] *= 2
    elif what == "reflection":
        T[:3, 0] *= -1
    elif what == "nan t":
        T[0, 3] = np.nan
    else:
        score = float("nan")
    with pytest.raises(ValueError, match="estimate #1 .scene 1, image 0, object 1."):
        evaluate(root, [PoseEstimate(1, 0, 2, 1.0, BopDataset(root).instances(1, 0)[1].T_cam_from_obj),
                        PoseEstimate(1, 0, 1, score, T)], metrics=["mssd"])


def test_unknown_matcher_is_named_not_a_rebuild(work):
    msg = assert_error(estimate(work, "--set", "match.matcher=bogus"), "unknown matcher", "bogus", "sift-nn")
    assert "rebuild" not in msg


def test_refs_with_inconsistent_arrays_name_the_set_and_field(work, tmp_path):
    with np.load(work["refs"]) as z:
        data = {k: z[k] for k in z.files}
    data["depth_q"] = data["depth_q"][:7]  # 10 views of poses, 7 depth maps
    np.savez(tmp_path / "cut.npz", **data)
    assert_error(cli("estimate", "--refs", tmp_path / "cut.npz", "--image", work["photo"], "--K", K_TEXT, "--bbox",
                     work["box"]), "cut.npz", "depth_q", "inconsistent")


def test_load_reference_set_accepts_a_mesh_path(work, tmp_path):
    from pixie.errors import ReferenceSetError
    from pixie.references.store import load_reference_set

    assert load_reference_set(work["refs"], mesh=work["mesh"]).n_views == 10
    assert load_reference_set(work["refs"], mesh=str(work["mesh"])).n_views == 10
    with pytest.raises(ReferenceSetError, match="another mesh"):
        load_reference_set(work["refs"], mesh=write_ply(tmp_path / "t.ply", TETRA, TETRA_F))


def test_console_warnings_reach_the_result_json(work, tmp_path):
    rot = _jpeg_with_orientation(work["photo"], tmp_path / "rot.jpg", 6)
    rc, out, err = estimate(work, "-o", tmp_path / "r.json", "--device", "cuda", "--preset", "paper", image=rot)
    assert rc in (0, 1) and "Traceback" not in err
    res = json.loads((tmp_path / "r.json").read_text())
    printed = [ln[len("pixie: warning: "):] for ln in err.splitlines() if ln.startswith("pixie: warning: ")]
    assert any("EXIF orientation 6" in w for w in res["warnings"])
    cuda = any("CUDA" in w for w in printed)  # only where torch sees no GPU
    assert cuda == any("CUDA" in w for w in res["warnings"])
    assert any("preset paper asks for encodings" in w for w in res["warnings"])  # a set of another preset
    assert res["settings"]["encodings"] == ["shade3_edges"] and res["preset"] == "paper"
    assert sorted(set(printed)) == sorted(set(res["warnings"])) and len(printed) == len(set(printed))


def test_units_hint_names_only_the_other_units(tmp_path):
    import re

    path = write_ply(tmp_path / "part.ply", TETRA, TETRA_F)  # 72 units across: 72 m declared as metres
    rc, out, err = cli("refs", "build", path, "-o", tmp_path / "o.npz", "--units", "m", *SMALL)
    assert rc == 0 and "implausible" in err and "--units mm" in err and not re.search(r"--units m\b", err), err
    huge = write_ply(tmp_path / "huge.ply", [tuple(c * 1000 for c in v) for v in TETRA], TETRA_F)
    rc, out, err = cli("refs", "build", huge, "-o", tmp_path / "o2.npz", "--units", "mm", *SMALL)
    assert rc == 0 and "implausible" in err and "--units mm" not in err and "check the file" in err, err


# ---------------------------------------------------------------------- "pose ok" for impossible poses


def test_box_given_as_corners_past_the_image_edge_warns(work, tmp_path):
    x, y, w, h = map(int, work["box"].split(","))
    corners = f"{x},{y},{x + w + 60},{y + h}"  # x1,y1,x2,y2 read as x,y,w,h: runs far past the right edge
    rc, out, err = estimate(work, "-o", tmp_path / "r.json", box=corners)
    assert rc in (0, 1) and "Traceback" not in err
    res = json.loads((tmp_path / "r.json").read_text())
    assert any("past the right edge" in m and "x1,y1,x2,y2" in m for m in res["warnings"]), res["warnings"]
    assert "past the right edge" in err


def test_whole_image_box_is_not_a_confident_pose(work, tmp_path):
    rc, out, err = estimate(work, "-o", tmp_path / "r.json", box=f"0,0,{W},{H}")
    res = json.loads((tmp_path / "r.json").read_text())
    assert any("covers 100 % of the image" in m for m in res["warnings"]), res["warnings"]
    assert res["failed"] or ("warning" in out and "pose ok (" in out)


def test_mesh_in_cm_read_as_mm_warns_about_its_size(work, tmp_path):
    """The part (~100 mm) in a file in cm, read as mm: a 10 mm object cannot fill the box at any plausible distance."""
    from pixie.config import RefsConfig
    from pixie.geometry.mesh import from_arrays, load_mesh
    from pixie.matching import get_matcher
    from pixie.references.set import build_reference_set
    from pixie.references.store import save_reference_set

    part = load_mesh(work["mesh"])
    small = from_arrays(part.vertices / 10.0, part.faces, name="part_cm")
    refs = build_reference_set(small, RefsConfig(n_fibonacci=4, rotations=2, size=64, encodings=["shade3_edges"]),
                               matcher=get_matcher("sift-nn", max_keypoints=128, window=16.0))
    save_reference_set(refs, tmp_path / "cm.npz")
    rc, out, err = cli("estimate", "--refs", tmp_path / "cm.npz", "--image", work["photo"], f"--K={K_TEXT}",
                       f"--bbox={work['box']}", "-o", tmp_path / "r.json", *FAST)
    res = json.loads((tmp_path / "r.json").read_text())
    assert any("10.2 mm object" in m and "--units" in m for m in res["warnings"]), res["warnings"]
    assert "pixie: warning:" in err


def test_right_box_and_mesh_give_no_pose_warning(work, tmp_path):
    rc, out, err = estimate(work, "-o", tmp_path / "r.json")
    res = json.loads((tmp_path / "r.json").read_text())
    assert not [m for m in res["warnings"] if "box" in m or "object" in m or "inliers" in m], res["warnings"]
