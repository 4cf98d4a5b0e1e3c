"""Study: where the aligned pipeline loses its targets, and render-and-compare terms for choosing among the aligned
candidates (issue 22, session 12).

Usage::

    PYTHONPATH=src:bench .venv/bin/python bench/lmo_rerank_study.py --max-targets 96 [--set align.key=value ...]
        [--name NAME] [--no-rc] [--report-only out/bench/lmo_rerank/<key>_s3.pkl]

Stage 1 is :mod:`lmo_align_study`'s cache (the pipeline up to the shape stage). Stage 2 runs the alignment stage
(the preset + ``--set``) once per target and records every candidate (pose, terms, correctness); stage 3 adds
candidate terms from a render of each candidate compared with the photo: matches between the photo crop and the
render that land within 2-8 px of each other (``rc_*``), and how well a spherical-harmonic shading of the rendered
normals explains the photo's colours (``sh*``, :mod:`shade_probe`). Each stage is cached under ``out/bench/lmo_rerank``.

The report: chosen / any candidate right; the misses split into no candidate within 15° (retrieval), chosen within
15° but wrong (depth: how many the GT depth alone would fix), chosen far while another is right (selection); then,
per term, the hits on the fitting half (even positions) and the report half (odd) when the term (divided by its
per-target maximum) is added with weight w to the shipped ranking score ``fused + w_fit * fit``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pickle
import time
from pathlib import Path

import numpy as np

import common as L  # noqa: E402
import lmo_align_study as S  # noqa: E402
from shade_probe import crop_setup, shade_terms  # noqa: E402

from pixie.app.runner import make_matcher  # noqa: E402
from pixie.config import PixieConfig  # noqa: E402
from pixie.pipeline.query import check_bbox  # noqa: E402
from pixie.references.encode import encode  # noqa: E402

REPO = L.REPO


def stage2(ds, objects, cached, cfg, base, cache: Path) -> list[dict]:
    if cache.is_file():
        return pickle.loads(cache.read_bytes())
    out, ests = [], {}
    for i, rec in enumerate(cached):
        sid, iid, oid = rec["target"]
        hyps, _ = S.align_cached(ds, objects, rec, cfg, base, ests)
        od = objects.eval_data(oid)
        g = L.gt_instance(ds, rec["t"])
        cands = []
        for rank, h in enumerate(hyps):
            if "fit" not in h.terms:
                continue
            e = L.pose_errors(od, h.T_cam_from_obj, g.T_cam_from_obj)
            cands.append({"rank": rank, "T": h.T_cam_from_obj, "source": h.source, "score": h.score, "fused": h.fused,
                          "fit": h.fit, "match_score": h.match_score, "terms": dict(h.terms),
                          "add_ok": bool(e["add_ok"]), "rot_err": float(e["rot_err"])})
        out.append({"target": rec["target"], "box": rec["box"], "cands": cands})
        if (i + 1) % 12 == 0:
            print(f"  stage 2: {i + 1}/{len(cached)}", flush=True)
    cache.write_bytes(pickle.dumps(out))
    return out


def render_compare(matcher, renderer, crop, Kc, Ts, enc="shade3_edges"):
    """Per pose: matches between the photo crop (camera ``Kc``, :func:`shade_probe.crop_setup`) and the pose's render
    that land where the pose says."""
    size = crop.image.shape[0]
    fq = matcher.extract(crop.image)
    rows = []
    for T in Ts:
        r = renderer.render(T, Kc, size, size)
        m = r.mask
        if m.sum() < 20:
            rows.append({})
            continue
        im = encode(enc, r.depth, r.normals, m)
        fr = matcher.extract(im, mask=m)
        mt = matcher.match(fq, fr)
        d = np.linalg.norm(fq.keypoints[mt.idx_q] - fr.keypoints[mt.idx_r], axis=1)
        s = mt.scores
        row = {"rc_n": float(len(d)), "rc_nr": float(len(fr.keypoints))}
        for px in (2, 3, 5, 8):
            ok = d <= px
            row[f"rc_c{px}"] = float(ok.sum())
            row[f"rc_s{px}"] = float(s[ok].sum())
        row["rc_frac5"] = row["rc_c5"] / max(len(d), 1)
        # every photo keypoint in the silhouette: its best descriptor similarity among render keypoints within 4 px
        kq = fq.keypoints
        inm = m[np.clip(np.rint(kq[:, 1]).astype(int), 0, size - 1), np.clip(np.rint(kq[:, 0]).astype(int), 0, size - 1)]
        if inm.sum() and len(fr.keypoints):
            D = np.linalg.norm(kq[inm][:, None, :] - fr.keypoints[None, :, :], axis=2)
            sim = fq.descriptors[inm] @ fr.descriptors.T
            loc = np.where(D <= 4.0, sim, -1.0).max(axis=1)
            row["rc_local"] = float(np.clip(loc, 0, None).mean())
            row["rc_local_sum"] = float(np.clip(loc, 0, None).sum())
        rows.append(row)
    return rows


def stage3(ds, objects, recs, base, cache: Path) -> list[dict]:
    if cache.is_file():
        return pickle.loads(cache.read_bytes())
    matcher = make_matcher(base)
    t0 = time.perf_counter()
    for i, rec in enumerate(recs):
        sid, iid, oid = rec["target"]
        img = ds.load_rgb(sid, iid)
        K = ds.camera(sid, iid).K
        box = check_bbox(rec["box"], img.shape[:2])
        crop, Kc, allowed = crop_setup(img, K, box)
        rows = render_compare(matcher, objects.renderer(oid), crop, Kc, [c["T"] for c in rec["cands"]])
        for c, r in zip(rec["cands"], rows):
            c["terms"].update(r)
            c["terms"].update(shade_terms(objects.renderer(oid), crop, Kc, allowed, c["T"]))
        if (i + 1) % 12 == 0:
            print(f"  stage 3: {i + 1}/{len(recs)} ({(time.perf_counter() - t0) / (i + 1):.2f} s/target)", flush=True)
    cache.write_bytes(pickle.dumps(recs))
    return recs


def report(ds, objects, recs) -> None:
    """Print the loss breakdown and the per-term selection table (see the module docstring)."""
    recs = [r for r in recs if r["cands"]]
    n = len(recs)
    top = sum(r["cands"][0]["add_ok"] for r in recs)
    anyr = sum(any(c["add_ok"] for c in r["cands"]) for r in recs)
    print(f"{n} targets: chosen right {top}, any candidate right {anyr}")
    cat = {"no candidate within 15°": 0, "chosen within 15°, wrong; another right": 0,
           "chosen within 15°, wrong; none right": 0, "chosen > 15° while another is right": 0, "other": 0}
    depth_fixed = 0
    for r in recs:
        ch = r["cands"][0]
        if ch["add_ok"]:
            continue
        sid, iid, oid = r["target"]
        if ch["rot_err"] < 15:
            cat["chosen within 15°, wrong; another right" if any(c["add_ok"] for c in r["cands"])
                else "chosen within 15°, wrong; none right"] += 1
            insts = [gi for gi in ds.instances(sid, iid) if gi.obj_id == oid]
            g = max(insts, key=lambda gi: gi.visib_fract or 0.0).T_cam_from_obj  # as common.gt_instance
            ctr = objects.mesh(oid).center
            T = np.array(ch["T"])
            c_est, c_gt = T[:3, :3] @ ctr + T[:3, 3], g[:3, :3] @ ctr + g[:3, 3]
            Tz = T.copy()
            Tz[:3, 3] = c_est * (c_gt[2] / c_est[2]) - T[:3, :3] @ ctr  # the GT depth along the estimate's ray
            depth_fixed += bool(L.pose_errors(objects.eval_data(oid), Tz, g)["add_ok"])
        elif not any(c["rot_err"] < 15 for c in r["cands"]):
            cat["no candidate within 15°"] += 1
        elif any(c["add_ok"] for c in r["cands"]):
            cat["chosen > 15° while another is right"] += 1
        else:
            cat["other"] += 1
    print("misses: " + "; ".join(f"{k} {v}" for k, v in cat.items()) + f"; GT depth alone fixes {depth_fixed} of the "
          "chosen-within-15° misses (symmetric objects count under 'no candidate within 15°' when ADD-S is missed)")

    def pick(r, k, w):
        v = np.array([float(c["terms"].get(k, 0.0) or 0.0) for c in r["cands"]]) if k else np.zeros(len(r["cands"]))
        if v.max() > 0:
            v = v / v.max()
        return int(np.argmax([c["fused"] + c["fit"] + w * x for c, x in zip(r["cands"], v)]))

    even, odd = recs[0::2], recs[1::2]
    ws = (0.25, 0.5, 1.0, 2.0, 4.0)
    print("| term | " + " | ".join(f"w {w}: fit / report" for w in ws) + " |")
    print("|---|" + "---|" * len(ws))
    base = f"{sum(r['cands'][pick(r, None, 0)]['add_ok'] for r in even)} / {sum(r['cands'][pick(r, None, 0)]['add_ok'] for r in odd)}"
    print(f"| (shipped: fused + fit) | {base} |" + " |" * (len(ws) - 1))
    for k in ("rc_c3", "rc_c5", "rc_c8", "rc_s5", "rc_local", "sh4_r2", "sh9_r2"):
        if k not in recs[0]["cands"][0]["terms"]:
            continue
        cells = [f"{sum(r['cands'][pick(r, k, w)]['add_ok'] for r in even)} / {sum(r['cands'][pick(r, k, w)]['add_ok'] for r in odd)}"
                 for w in ws]
        print(f"| {k} | " + " | ".join(cells) + " |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--max-targets", type=int, default=96)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--set", action="append", default=[], dest="sets", help="stage-2 config overrides")
    ap.add_argument("--name", default="default", help="name of the stage-2 variant (its cache file)")
    ap.add_argument("--no-rc", action="store_true", help="skip the render-compare terms")
    ap.add_argument("--report-only", type=Path, default=None, help="report a stage-2 or stage-3 cache file")
    args = ap.parse_args(argv)
    ds = L.BopDataset(args.dataset)
    objects = L.ObjectCache(ds)
    if args.report_only is not None:
        report(ds, objects, pickle.loads(args.report_only.read_bytes()))
        return 0
    targets = L.select_targets(ds, args.max_targets)
    base = PixieConfig.from_preset(args.preset).apply_overrides(["align.enabled=false"])
    key = hashlib.sha256(json.dumps([S.TAG, args.preset, base.digest(), [(t.scene_id, t.im_id, t.obj_id) for t in targets]],
                                    default=str).encode()).hexdigest()[:12]
    cached = S.stage1(ds, objects, targets, base, REPO / "out/bench/lmo_align_study" / f"{key}.pkl")
    cfg = PixieConfig.from_preset(args.preset).apply_overrides(args.sets)
    d = REPO / "out/bench/lmo_rerank"
    d.mkdir(parents=True, exist_ok=True)
    sfx = "" if args.name == "default" else f"_{args.name}"
    recs = stage2(ds, objects, cached, cfg, base, d / f"{key}{sfx}_s2.pkl")
    if not args.no_rc:
        recs = stage3(ds, objects, recs, base, d / f"{key}{sfx}_s3.pkl")
    report(ds, objects, recs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
