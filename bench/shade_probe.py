"""Probe (issue 22, session 12): does a Lambertian shading fit tell a pose from the same pose turned by a few degrees?

Usage::

    PYTHONPATH=src .venv/bin/python bench/shade_probe.py [N_TARGETS]

Per LM-O dev target (GT ``bbox_visib`` crop), the photo's colours inside the silhouette rendered at the GT pose, and at
the GT pose turned 3 / 6 / 10 / 20° about random axes through the object centre, are fitted robustly as a degree-1 (4
terms) or degree-2 (9 terms) spherical-harmonic function of the rendered normals; prints how often the GT pose
explains the shading better (R² and RMS). ``bench/lmo_rerank_study.py`` uses the same terms per aligned candidate.
"""
import pickle
import sys

import cv2
import numpy as np

sys.path.insert(0, "bench")
import common as L  # noqa: E402
from pixie.geometry.camera import crop_intrinsics  # noqa: E402
from pixie.pipeline.query import check_bbox, square_crop  # noqa: E402
from pixie.synth.e2e import turned_pose  # noqa: E402


def sh_basis(n):
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    return np.stack([np.ones_like(x), x, y, z, x * y, x * z, y * z, x * x - y * y, 3 * z * z - 1], 1)


def shading_fit(img, normals, mask, iters=3, order=9):
    """Robust per-channel SH fit of colours on normals; returns (r2, rms, n)."""
    n = normals[mask].astype(np.float64)
    c = img[mask].astype(np.float64) / 255.0
    if len(c) < 50:
        return 0.0, 1.0, len(c)
    B = sh_basis(n)[:, :order]
    w = np.ones(len(c))
    for _ in range(iters):
        Bw = B * w[:, None]
        X = np.linalg.lstsq(Bw.T @ B + 1e-6 * np.eye(B.shape[1]), Bw.T @ c, rcond=None)[0]
        r = np.linalg.norm(c - B @ X, axis=1)
        s = 1.4826 * np.median(r) + 1e-6
        w = (1 - np.minimum((r / (3 * s)) ** 2, 1)) ** 2
    tot = np.linalg.norm(c - np.average(c, axis=0, weights=w), axis=1)
    r2 = 1 - np.sum(w * r ** 2) / max(np.sum(w * tot ** 2), 1e-9)
    return float(r2), float(np.sqrt(np.average(r ** 2, weights=w))), len(c)


def crop_setup(img, K, box, size=256, pad=1.2):
    crop = square_crop(img, box, pad, size)
    Kc = crop_intrinsics(K, crop.A)
    Ai = np.linalg.inv(np.vstack([crop.A, [0, 0, 1]]))
    c0 = Ai @ np.array([box[0], box[1], 1.0])
    c1 = Ai @ np.array([box[2], box[3], 1.0])
    allowed = np.zeros((size, size), bool)
    allowed[max(int(c0[1]), 0):int(np.ceil(c1[1])), max(int(c0[0]), 0):int(np.ceil(c1[0]))] = True
    return crop, Kc, allowed


def shade_terms(renderer, crop, Kc, allowed, T, size=256):
    r = renderer.render(T, Kc, size, size)
    m = cv2.erode(r.mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    m &= allowed
    out = {}
    for order in (4, 9):
        r2, rms, n = shading_fit(crop.image, r.normals, m, order=order)
        out[f"sh{order}_r2"], out[f"sh{order}_rms"] = r2, rms
    out["sh_n"] = float(m.sum())
    return out


if __name__ == "__main__":
    ds = L.BopDataset(L.DEFAULT_DATASET)
    objects = L.ObjectCache(ds)
    rows = []
    for t in L.select_targets(ds, int(sys.argv[1]) if len(sys.argv) > 1 else 48):
        g = L.gt_instance(ds, t)
        img = ds.load_rgb(t.scene_id, t.im_id)
        K = ds.camera(t.scene_id, t.im_id).K
        box = check_bbox(g.box_visib, img.shape[:2])
        crop, Kc, allowed = crop_setup(img, K, box)
        ren = objects.renderer(t.obj_id)
        ctr = objects.mesh(t.obj_id).center
        rng = np.random.default_rng([t.im_id, t.obj_id])
        row = {"obj": t.obj_id, "gt": shade_terms(ren, crop, Kc, allowed, g.T_cam_from_obj)}
        for deg in (3, 6, 10, 20):
            row[deg] = [shade_terms(ren, crop, Kc, allowed, turned_pose(g.T_cam_from_obj, K, ctr, deg, 0.0, 0.0, rng)) for _ in range(4)]
        rows.append(row)
    pickle.dump(rows, open("out/bench/shade_probe.pkl", "wb"))
    for k in ("sh4_r2", "sh9_r2", "sh4_rms", "sh9_rms"):
        sgn = 1 if "r2" in k else -1
        for deg in (3, 6, 10, 20):
            wins = [np.mean([sgn * (r["gt"][k] - p[k]) > 0 for p in r[deg]]) for r in rows]
            print(k, deg, "GT beats perturbed:", round(float(np.mean(wins)), 3))
        for o in sorted({r["obj"] for r in rows}):
            print("   obj", o, [round(float(np.mean([np.mean([sgn * (r["gt"][k] - p[k]) > 0 for p in r[d]]) for r in rows if r["obj"] == o])), 2) for d in (3, 6, 10, 20)])
