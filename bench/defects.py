"""Assembly defects and colour variants: the paper's Tables I and II on the synthetic benchmark.

Usage::

    nice .venv/bin/python bench/defects.py                      # default, affordable on 2 CPU cores
    nice .venv/bin/python bench/defects.py --no-ablations --images 1      # quicker
    nice .venv/bin/python bench/defects.py --set match.matcher=xfeat-nn   # any config override

Steps:

1. Generate (or reuse, when the parameters match) the BOP-format dataset with
   :func:`pixie.synth.scenes.generate_defect_dataset` into ``--data`` (default
   ``out/bench/defects_data``): ``--assemblies`` targets (default 2, LEGO-like), ``--defects``
   defective variants each (2), ``--colours`` colour variants (2), ``--images`` images per scene
   (1). Scenes per assembly = colours (targets) + defects (default: 4 scenes, 4 images per
   assembly). Table I is printed from its summary.
2. For every scene (one physical object) run :class:`pixie.pipeline.estimator.PoseEstimator` with the GT
   ``bbox_visib`` as the crop (the paper gives every method the boxes), with references built from
   (a) the *target* model and (b) the *defective* model actually shown (for target scenes (b) = (a),
   the run is reused). Encoding ablations (depth only / normal only / shade3_edges only) run with the
   target model. References are cheaper than the paper's on this CPU budget:
   ``refs.n_fibonacci=40`` (+6 canonical = 46 views, paper 121), ``refs.feature_rolls=first`` and
   ``match.in_plane=query`` (the query crop is rotated instead of storing 8 rotated reference
   feature sets) and ``refs.size=256`` (reference / query crops of 256 px instead of 512: ~4x
   cheaper; measured on 2 shared cores at 512 px: ~16 min per reference set and ~28 s per image).
   ``--set`` overrides are applied on top (``--paper-refs`` drops these four defaults).
3. Report the columns of Table II: avg / median ADD (cm), ADD < 0.5 / 1 / 5 cm, APS at the
   estimate (model used by the method at the estimate vs the physical model at GT) and AR
   (MSSD, MSPD, VSD via :func:`pixie.eval.evaluate`; the dataset has depth). ADD and AR use the
   *physical* model (what is really in the image) as the evaluation model for every row, so the
   rows are comparable; ``AR_bop`` is the plain BOP evaluation of the dataset files (target model).
   A failed estimate counts as a miss (ADD thresholds, AR) with APS 0 and is left out of the ADD
   mean / median. Robustness: AR per scene kind (target / defective), per defect type and per
   colour variant.

Outputs: ``out/bench/defects/defects.json`` (everything), ``results_<run>.csv`` (BOP'19),
``estimates.jsonl`` (resumable cache of estimates keyed by run configuration and image), and the
section ``## Defects benchmark (bench/defects.py)`` of ``bench/RESULTS.md`` (other sections kept).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from pixie.config import PixieConfig  # noqa: E402
from pixie.errors import PixieError  # noqa: E402
from pixie.pipeline.estimator import PoseEstimator  # noqa: E402
from pixie.eval import ObjectData, evaluate  # noqa: E402
from pixie.eval import pose_error as M  # noqa: E402
from pixie.eval.datasets import BopDataset, PoseEstimate, Target, symmetry_transforms, write_results_csv  # noqa: E402
from pixie.eval.shape_metrics import aps  # noqa: E402
from pixie.geometry.mesh import Mesh, load_mesh  # noqa: E402
from pixie.geometry.render import Renderer  # noqa: E402
from pixie.app.runner import Journal, cached_reference_set, make_matcher, reference_cache_path  # noqa: E402

DEFAULT_DATA = REPO / "out/bench/defects_data"
DEFAULT_OUT = REPO / "out/bench/defects"
RESULTS_MD = REPO / "bench/RESULTS.md"
SECTION = "## Defects benchmark (bench/defects.py)"
CHEAP_REFS = ["refs.n_fibonacci=40", "refs.feature_rolls=first", "match.in_plane=query", "refs.size=256"]
ABLATIONS = {"depth only": ["depth"], "normal only": ["normal"], "shade3_edges only": ["shade3_edges"]}


# ------------------------------------------------------------------------------------------ data


def ensure_dataset(root: Path, params: dict, regenerate: bool, echo=print) -> dict:
    """Generate the dataset unless ``root/table1.json`` records the same parameters."""
    from pixie.synth.scenes import DATASET_FORMAT, generate_defect_dataset

    meta = root / "table1.json"
    if meta.is_file() and not regenerate:
        old = json.loads(meta.read_text())
        same = old.get("format") == DATASET_FORMAT and old.get("seed") == params["seed"] and all(old["params"].get(k) == v for k, v in params.items() if k != "seed")
        if same:
            echo(f"reusing dataset {root}")
            return old
    echo(f"generating dataset {root} {params} ...")
    t0 = time.perf_counter()
    res = generate_defect_dataset(root, **params)
    echo(f"  {res['n_scenes']} scenes, {res['n_images']} images in {time.perf_counter() - t0:.0f} s")
    return res


def physical_model_path(root: Path, v: dict) -> Path:
    return root / v["model_dir"] / f"obj_{v['model_obj_id']:06d}.ply"


# ------------------------------------------------------------------------------------------ estimation


def _hash(obj) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:12]


class Models:
    """Meshes, renderers, reference sets and estimators, cached."""

    def __init__(self, root: Path, refs_dir: Path, echo=print):
        self.root, self.refs_dir, self.echo = root, refs_dir, echo
        self._mesh: dict[Path, Mesh] = {}
        self._ren: dict[Path, object] = {}
        self._refs: dict[tuple, object] = {}
        self._est: dict[tuple, object] = {}
        self._matcher = {}
        self.build_seconds: dict[str, float] = {}

    def mesh(self, path: Path) -> Mesh:
        if path not in self._mesh:
            self._mesh[path] = load_mesh(path)
        return self._mesh[path]

    def renderer(self, path: Path):
        if path not in self._ren:
            self._ren[path] = Renderer(self.mesh(path))
        return self._ren[path]

    def matcher(self, cfg: PixieConfig):
        """The configured matcher (:func:`pixie.app.runner.make_matcher`: detection threshold and all), one per setting."""
        m = cfg.match
        key = (m.matcher, m.max_keypoints, m.detection_threshold, m.window, m.weights_dir, m.device, cfg.refs.size)
        if key not in self._matcher:
            self._matcher[key] = make_matcher(cfg)
        return self._matcher[key]

    def refs(self, path: Path, cfg: PixieConfig):
        """Reference set of a model with *all* encodings of ``cfg.refs`` (ablations pick a subset), cached on disk
        by :func:`pixie.app.runner.cached_reference_set`."""
        mesh = self.mesh(path)
        key = reference_cache_path(mesh, cfg, self.refs_dir)
        if key not in self._refs:
            refs = cached_reference_set(mesh, cfg, self.refs_dir, matcher=self.matcher(cfg),
                                        echo=lambda msg: self.echo(f"  {path.parent.name}/{path.name}: {msg}"))
            self.build_seconds[f"{path.parent.name}/{path.stem}"] = float(getattr(refs, "build_seconds", 0.0) or 0.0)
            self._refs[key] = refs
        return self._refs[key]

    def estimator(self, path: Path, cfg: PixieConfig):
        key = (path, _hash(cfg.to_dict()))
        if key not in self._est:
            if len(self._est) > 6:  # bound memory: drop the oldest
                self._est.pop(next(iter(self._est)))
            self._est[key] = PoseEstimator(self.refs(path, cfg), cfg, matcher=self.matcher(cfg))
        return self._est[key]


def run_key(cfg: PixieConfig, model_path: Path, root: Path, tg: Target, det_threshold: float) -> str:
    """Cache key of one estimate. ``det_threshold`` is the threshold the matcher really uses: estimates cached
    before this script took its matcher from the config (ALIKED at its own 0.2, not the configured 0.0) differ."""
    c = cfg.to_dict()
    c.pop("parts", None)  # the part report never runs on these one-piece PLY models: its settings change no estimate
    return _hash({"cfg": c, "model": str(model_path.relative_to(root)), "t": [tg.scene_id, tg.im_id],
                  "data": json.loads((root / "table1.json").read_text()).get("params"), "det": det_threshold})


def estimate_all(name: str, ds: BopDataset, variants: dict[int, dict], cfg: PixieConfig, model_kind: str,
                 models: Models, cache: Journal, echo=print, reuse: dict | None = None,
                 skip_target_scenes: bool = False, first_images: int | None = None) -> list[dict]:
    """One estimate per target. ``model_kind``: 'target' or 'defective' (the physical model). ``cache`` is the
    resumable journal of estimates (keyed by :func:`run_key`)."""
    rows = []
    root = ds.root
    targets = ds.targets()
    if skip_target_scenes:
        targets = [t for t in targets if variants[t.scene_id]["defect_index"] > 0]
    if first_images is not None:
        targets = [t for t in targets if t.im_id < first_images]
    t_run = time.perf_counter()
    for i, tg in enumerate(targets):
        v = variants[tg.scene_id]
        phys = physical_model_path(root, v)
        model = root / "models" / f"obj_{tg.obj_id:06d}.ply" if model_kind == "target" else phys
        key = run_key(cfg, model, root, tg, models.matcher(cfg).extractor.threshold)
        if key not in cache:
            if reuse is not None and model_kind == "defective" and v["defect_index"] == 0 and (tg.scene_id, tg.im_id) in reuse:
                rec = dict(reuse[(tg.scene_id, tg.im_id)])
                rec["key"] = key
            else:
                (inst,) = ds.instances(tg.scene_id, tg.im_id)
                img = ds.load_rgb(tg.scene_id, tg.im_id)
                K = ds.camera(tg.scene_id, tg.im_id).K
                est = models.estimator(model, cfg)  # builds references on first use: not timed
                t0 = time.perf_counter()
                alt = None
                try:
                    r = est.estimate(img, K, bbox=inst.box_visib)
                    T, score, failed, msg = r.T_cam_from_obj, float(r.score), bool(r.failed), r.message
                    if len(r.hypotheses) > 1:  # the runner-up (best distinct alternative): parts.alt_gap's pose
                        alt = r.hypotheses[1]
                except PixieError as exc:
                    T, score, failed, msg = None, 0.0, True, f"{type(exc).__name__}: {exc}"
                rec = dict(key=key, scene_id=tg.scene_id, im_id=tg.im_id, obj_id=tg.obj_id,
                           T=None if T is None else np.asarray(T).tolist(), score=score, failed=failed,
                           message=msg, time=time.perf_counter() - t0,
                           runner_up_T=None if alt is None else np.asarray(alt.T_cam_from_obj).tolist(),
                           runner_up_score=None if alt is None else float(alt.score))
            cache.append(rec)
        rec = dict(cache.get(key))
        rec["model"] = str(model.relative_to(root))
        rec["physical"] = str(phys.relative_to(root))
        rows.append(rec)
        if (i + 1) % 8 == 0 or i + 1 == len(targets):
            echo(f"  [{name}] {i + 1}/{len(targets)} targets ({time.perf_counter() - t_run:.0f} s)")
    return rows


# ------------------------------------------------------------------------------------------ scoring


def object_data(obj_id: int, mesh: Mesh, n_points: int = 2000):
    pts = np.asarray(mesh.vertices, dtype=np.float64)
    idx = np.random.default_rng(obj_id).choice(len(pts), size=min(n_points, len(pts)), replace=False)
    return ObjectData(obj_id=obj_id, diameter=float(mesh.diameter), symmetric=False, syms=symmetry_transforms({}),
                      pts=pts, add_pts=pts[np.sort(idx)], mesh=mesh)


def score_rows(rows: list[dict], ds: BopDataset, models: Models, variants: dict[int, dict]) -> None:
    """Add ADD (mm, physical model points) and APS (method's model at the estimate vs physical at GT)."""
    for r in rows:
        (inst,) = ds.instances(r["scene_id"], r["im_id"])
        K = ds.camera(r["scene_id"], r["im_id"]).K
        h, w = ds.image_size(r["scene_id"], r["im_id"])
        phys = ds.root / r["physical"]
        if r["T"] is None or r["failed"]:
            r["add_mm"], r["aps"] = None, 0.0
            continue
        T = np.asarray(r["T"])
        pts = models.mesh(phys).sample_points(2000, seed=1)
        r["add_mm"] = float(M.add(T, inst.T_cam_from_obj, pts))
        r["aps"] = float(aps(models.renderer(ds.root / r["model"]), models.renderer(phys), T, inst.T_cam_from_obj, K, h, w))
        r["rot_err_deg"] = float(M.rotation_error_deg(T, inst.T_cam_from_obj))


def ar_physical(rows: list[dict], ds: BopDataset, variants: dict[int, dict], models: Models) -> dict:
    """AR (MSSD, MSPD, VSD) with each scene's physical model as the evaluation model.

    :func:`pixie.eval.evaluate` is called per scene (its object data mapped to the physical mesh);
    AR averages over targets, so the per-scene results combine exactly by target counts.
    Returns {scene_id: {AR, AR_MSSD, AR_MSPD, AR_VSD, n}}.
    """
    ests = [PoseEstimate(r["scene_id"], r["im_id"], r["obj_id"], r["score"], np.asarray(r["T"]), r.get("time", -1.0))
            for r in rows if r["T"] is not None and not r["failed"]]
    out = {}
    all_t = ds.targets()
    done = {(r["scene_id"], r["im_id"]) for r in rows}
    for sid, v in variants.items():
        tgs = [t for t in all_t if t.scene_id == sid and (t.scene_id, t.im_id) in done]  # the targets of this run
        if not tgs:
            continue
        od = object_data(v["obj_id"], models.mesh(physical_model_path(ds.root, v)))
        sc = evaluate(ds, [e for e in ests if e.scene_id == sid], metrics=("mssd", "mspd", "vsd"), targets=tgs,
                      objects={v["obj_id"]: od})
        o = sc.overall
        out[sid] = dict(AR=o.get("AR"), AR_MSSD=o.get("AR_MSSD"), AR_MSPD=o.get("AR_MSPD"), AR_VSD=o.get("AR_VSD"),
                        n=sc.n_targets)
    return out


def _wavg(per_scene: dict, key: str, scenes) -> float | None:
    vals = [(per_scene[s][key], per_scene[s]["n"]) for s in scenes if s in per_scene and per_scene[s][key] is not None]
    n = sum(w for _, w in vals)
    return float(sum(x * w for x, w in vals) / n) if n else None


def table2_row(label: str, model_kind: str, n_views: int, rows: list[dict], ar: dict, ar_bop: float | None) -> dict:
    adds = np.array([r["add_mm"] for r in rows if r.get("add_mm") is not None], dtype=np.float64)
    n = len(rows)
    ok = lambda th: float(np.sum(adds < th) / n) if n else float("nan")  # noqa: E731
    return {
        "method": label, "model": model_kind, "ref_views": n_views, "n": n,
        "n_failed": int(sum(1 for r in rows if r.get("add_mm") is None)),
        "avg_add_cm": float(adds.mean() / 10) if adds.size else None,
        "med_add_cm": float(np.median(adds) / 10) if adds.size else None,
        "add_0.5cm": ok(5.0), "add_1cm": ok(10.0), "add_5cm": ok(50.0),
        "aps": float(np.mean([r["aps"] for r in rows])) if rows else None,
        "AR": _wavg(ar, "AR", ar.keys()), "AR_MSSD": _wavg(ar, "AR_MSSD", ar.keys()),
        "AR_MSPD": _wavg(ar, "AR_MSPD", ar.keys()), "AR_VSD": _wavg(ar, "AR_VSD", ar.keys()),
        "AR_bop": ar_bop,
        "rot_gt150": float(np.mean([(r.get("rot_err_deg") or 0.0) > 150.0 for r in rows])) if rows else None,
        # Median: estimates cached by older versions of this script timed the first image of each model
        # together with its reference build.
        "sec_per_image": float(np.median([r["time"] for r in rows if r.get("time") is not None])) if rows else None,
    }


def _f(x, spec=".3f", pct=False):
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    return f"{100 * x:.1f}%" if pct else format(x, spec)


def format_table2(rows: list[dict]) -> str:
    lines = ["| # | Method | 3D model | # ref. views | avg ADD (cm) | med ADD (cm) | ADD<0.5cm | ADD<1cm | ADD<5cm | APS | AR | AR_bop | rot>150° | failed | med s/img |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for i, r in enumerate(rows, 1):
        lines.append(f"| {i} | {r['method']} | {r['model']} | {r['ref_views']} | {_f(r['avg_add_cm'], '.2f')} | "
                     f"{_f(r['med_add_cm'], '.2f')} | {_f(r['add_0.5cm'], pct=True)} | {_f(r['add_1cm'], pct=True)} | "
                     f"{_f(r['add_5cm'], pct=True)} | {_f(r['aps'])} | {_f(r['AR'])} | {_f(r['AR_bop'])} | "
                     f"{_f(r['rot_gt150'], pct=True)} | "
                     f"{r['n_failed']}/{r['n']} | {_f(r['sec_per_image'], '.1f')} |")
    return "\n".join(lines)


def robustness(rows_by_run: dict[str, list[dict]], ar_by_run: dict[str, dict], variants: dict[int, dict]) -> dict:
    """AR / median ADD per scene kind, per defect type and per colour variant, for each model kind."""
    out = {}
    groups = {
        "target scenes": [s for s, v in variants.items() if v["defect_index"] == 0],
        "defective scenes": [s for s, v in variants.items() if v["defect_index"] > 0],
    }
    for t in sorted({(v.get("defect") or {}).get("type") for v in variants.values() if v["defect_index"] > 0} - {None}):
        groups[f"defect: {t}"] = [s for s, v in variants.items() if (v.get("defect") or {}).get("type") == t]
    for c in sorted({v["colour_variant"] for v in variants.values()}):
        groups[f"colour {c}"] = [s for s, v in variants.items() if v["colour_variant"] == c]
    for c in sorted({v["colour_variant"] for v in variants.values()}):
        groups[f"colour {c} (targets only)"] = [s for s, v in variants.items()
                                                if v["colour_variant"] == c and v["defect_index"] == 0]
    for run, rows in rows_by_run.items():
        res = {}
        for g, scenes in groups.items():
            rs = [r for r in rows if r["scene_id"] in scenes]
            adds = [r["add_mm"] for r in rs if r.get("add_mm") is not None]
            res[g] = dict(n=len(rs), AR=_wavg(ar_by_run[run], "AR", scenes),
                          med_add_cm=float(np.median(adds) / 10) if adds else None,
                          add_1cm=float(np.sum(np.array(adds) < 10.0) / len(rs)) if rs else None,
                          aps=float(np.mean([r["aps"] for r in rs])) if rs else None)
        out[run] = res
    return out


def format_robustness(rob: dict) -> str:
    runs = list(rob)
    groups = list(next(iter(rob.values())))
    head = "| group | n | " + " | ".join(f"AR ({r}) | ADD<1cm ({r}) | APS ({r})" for r in runs) + " |"
    lines = [head, "|" + "---|" * (2 + 3 * len(runs))]
    for g in groups:
        cells = []
        for r in runs:
            d = rob[r][g]
            cells += [_f(d["AR"]), _f(d["add_1cm"], pct=True), _f(d["aps"])]
        lines.append(f"| {g} | {rob[runs[0]][g]['n']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ RESULTS.md


def write_results_md(section_body: str, path: Path = RESULTS_MD) -> None:
    """Replace (or append) this benchmark's section, keeping every other section as it is."""
    text = path.read_text() if path.is_file() else "# Benchmark results\n"
    block = f"{SECTION}\n\n{section_body.strip()}\n"
    if SECTION in text:
        start = text.index(SECTION)
        nxt = text.find("\n## ", start + len(SECTION))
        end = len(text) if nxt < 0 else nxt + 1
        text = text[:start] + block + ("\n" + text[end:] if nxt >= 0 else "")
    else:
        text = text.rstrip("\n") + "\n\n" + block
    path.write_text(text)


# ------------------------------------------------------------------------------------------ main


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--assemblies", type=int, default=2)
    ap.add_argument("--defects", type=int, default=2)
    ap.add_argument("--colours", type=int, default=2)
    ap.add_argument("--images", type=int, default=1, help="images per scene")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--full-product", action="store_true", help="every defective variant in every colour variant")
    ap.add_argument("--preset", default=None, help="estimate with this preset (e.g. default, paper) instead of the "
                    "dataclass defaults + the cheap references " + " ".join(CHEAP_REFS))
    ap.add_argument("--regenerate", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--paper-refs", action="store_true", help="do not apply the cheap defaults " + " ".join(CHEAP_REFS))
    ap.add_argument("--no-ablations", action="store_true")
    ap.add_argument("--first-images", type=int, default=None, metavar="N",
                    help="estimate only the first N images of every scene (a subset, e.g. for the slow paper preset)")
    ap.add_argument("--rows", default="target,defective", help="which model rows to run (a 'defective' run alone "
                    "skips the target scenes, whose estimates the target row makes: merge the journals, then re-run "
                    "both rows from the cache)")
    ap.add_argument("--no-results-md", action="store_true")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--extra-table1", type=Path, action="append", default=[], metavar="DATASET",
                    help="also report the Table I of another generated dataset (e.g. a paper-scale one made with "
                         "python -m pixie.synth.scenes OUT --assemblies 4 --defects 6 --colours 3 --images 2)")
    args = ap.parse_args(argv)

    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    try:
        import torch

        torch.set_num_threads(args.threads)
    except Exception:
        pass
    from pixie.synth.scenes import format_table1

    t_start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    params = dict(n_assemblies=args.assemblies, n_defects=args.defects, n_colour_variants=args.colours,
                  images_per_variant=args.images, seed=args.seed, full_product=args.full_product)
    gen = ensure_dataset(args.data, params, args.regenerate)
    print("\nTable I analogue (APS at P_gt, IoU3D; in parentheses: defective models only)")
    t1 = format_table1(gen["table1"])
    print(t1)

    ds = BopDataset(args.data)
    variants = {v["scene_id"]: v for v in json.loads((args.data / "variants.json").read_text())}
    overrides = ([] if (args.paper_refs or args.preset) else list(CHEAP_REFS)) + list(args.set)
    base = (PixieConfig.from_preset(args.preset) if args.preset else PixieConfig()).apply_overrides(overrides)
    n_views = int(base.refs.n_fibonacci) + (6 if base.refs.canonical else 0)
    models = Models(args.data, args.out / "refs")
    cache = Journal(args.out / "estimates.jsonl", key=lambda rec: rec["key"])

    rows_wanted = [r.strip() for r in args.rows.split(",") if r.strip()]
    runs: list[tuple[str, str, PixieConfig]] = [("PIXIE", kind, base) for kind in ("target", "defective")
                                                if kind in rows_wanted]
    if not args.no_ablations:
        for label, encs in ABLATIONS.items():
            if not all(e in base.refs.encodings for e in encs):
                continue
            c = PixieConfig.from_dict(base.to_dict())
            # Estimator-side subset; references keep every encoding (same cache), see Models.refs.
            runs.append((f"PIXIE - {label}", "target", c))
    rows_by_run, ar_by_run, table2 = {}, {}, []
    reuse = None
    for label, kind, cfg in runs:
        name = f"{label} [{kind}]"
        print(f"\nrunning {name} ...")
        est_cfg = cfg
        if label.startswith("PIXIE - "):
            est_cfg = PixieConfig.from_dict(cfg.to_dict())
            est_cfg.refs.encodings = ABLATIONS[label[len("PIXIE - "):]]
        rows = _run_with_full_refs(name, ds, variants, cfg, est_cfg, kind, models, cache, reuse,
                                   skip_target_scenes=kind == "defective" and "target" not in rows_wanted,
                                   first_images=args.first_images)
        if label == "PIXIE" and kind == "target":
            reuse = {(r["scene_id"], r["im_id"]): r for r in rows}
        score_rows(rows, ds, models, variants)
        ar = ar_physical(rows, ds, variants, models)
        ar_bop = None
        if kind == "target":
            ests = [PoseEstimate(r["scene_id"], r["im_id"], r["obj_id"], r["score"], np.asarray(r["T"]), r["time"])
                    for r in rows if r["T"] is not None and not r["failed"]]
            done = {(r["scene_id"], r["im_id"]) for r in rows}
            ar_bop = evaluate(ds, ests, metrics=("mssd", "mspd", "vsd"),
                              targets=[t for t in ds.targets() if (t.scene_id, t.im_id) in done]).overall.get("AR")
        safe = name.replace(" ", "_").replace("[", "").replace("]", "").replace("/", "-")
        write_results_csv(args.out / f"results_{safe}.csv",
                          [PoseEstimate(r["scene_id"], r["im_id"], r["obj_id"], r["score"], np.asarray(r["T"]), r["time"])
                           for r in rows if r["T"] is not None and not r["failed"]])
        rows_by_run[name], ar_by_run[name] = rows, ar
        table2.append(table2_row(label, kind, n_views, rows, ar, ar_bop))
        print(format_table2(table2[-1:]))

    print("\nTable II analogue")
    t2 = format_table2(table2)
    print(t2)
    main_runs = {k: v for k, v in rows_by_run.items() if k in ("PIXIE [target]", "PIXIE [defective]")}
    rob = robustness(main_runs, ar_by_run, variants)
    t3 = format_robustness(rob)
    print("\nRobustness (AR with the physical model as evaluation model)")
    print(t3)
    total = time.perf_counter() - t_start
    result = dict(table1=gen["table1"], table2=table2, robustness=rob, overrides=overrides, n_views=n_views,
                  dataset=str(args.data), dataset_params=params, iou3d=gen.get("iou3d"),
                  variants=list(variants.values()), time_s=total,
                  estimates={k: [{kk: r.get(kk) for kk in ("scene_id", "im_id", "add_mm", "aps", "failed", "time",
                                                           "rot_err_deg", "model", "physical")} for r in v]
                             for k, v in rows_by_run.items()})
    (args.out / "defects.json").write_text(json.dumps(result, indent=1, default=str))
    print(f"\nwrote {args.out / 'defects.json'} ({total:.0f} s)")
    if not args.no_results_md:
        cmd = "nice .venv/bin/python bench/defects.py" + "".join(f" --set {s}" for s in args.set) + \
            ("" if args.images == 1 else f" --images {args.images}") + \
            ("" if args.assemblies == 2 else f" --assemblies {args.assemblies}") + \
            (" --no-ablations" if args.no_ablations else "") + (" --paper-refs" if args.paper_refs else "") + \
            (f" --preset {args.preset}" if args.preset else "") + (" --full-product" if args.full_product else "") + \
            (f" --defects {args.defects}" if args.defects != 2 else "") + \
            (f" --colours {args.colours}" if args.colours != 2 else "")
        n_img = gen["n_images"]
        ref_s = float(sum(models.build_seconds.values()))
        est_s = float(sum(r["time"] or 0.0 for k, rows in rows_by_run.items() for r in rows
                          if not (k == "PIXIE [defective]" and variants[r["scene_id"]]["defect_index"] == 0)))
        cold = ref_s + est_s
        extra = ""
        for d in args.extra_table1:
            x = json.loads((d / "table1.json").read_text())
            p = x["params"]
            extra += (f"Table I of a paper-scale set `{d.relative_to(REPO) if d.is_absolute() and REPO in d.parents else d}` "
                      f"(`python -m pixie.synth.scenes {d.name} --assemblies {p['n_assemblies']} --defects {p['n_defects']} "
                      f"--colours {p['n_colour_variants']} --images {p['images_per_variant']} --seed {x['seed']}`; "
                      f"generated in {x['time_s'] / 60:.0f} min):\n\n{format_table1(x['table1'])}\n\n")
        body = f"""Synthetic stand-in for the paper's custom LEGO dataset (Sec. IV-C): procedural assemblies,
defective variants (missing / shifted / rotated / wrong / extra part), colour variants, clutter, shadows,
camera degradations; 640x480, fx~fy~600, with depth. Generated by `pixie.synth.scenes.generate_defect_dataset`
(seed {args.seed}; {gen['n_scenes']} scenes, {n_img} images). Command: `{cmd}` (cold cost on 2 shared CPU cores:
{cold / 60:.0f} min = {ref_s / 60:.0f} min for {len(models.build_seconds)} reference sets + {est_s / 60:.0f} min of estimates;
estimates and references are cached under `out/bench/defects/`, so a re-run only re-scores).
Estimator settings: `{' '.join(overrides) or 'paper defaults'}` ({n_views} reference views; the paper uses 121),
GT `bbox_visib` crops. ADD and AR use the physical model (target or defective) actually in the image;
AR_bop = plain BOP evaluation of the files (target model); rot>150° = share of estimates turned by more
than 150° (the near-symmetric base plates invite 180° flips); failed = no pose (a miss).

**Table I analogue** (APS at P_gt and IoU3D; in parentheses: defective models only)

{t1}

{extra}**Table II analogue**

{t2}

**Robustness** (AR / ADD<1cm / APS per scene group; model used for estimation in brackets)

{t3}
"""
        write_results_md(body)
        print(f"updated {RESULTS_MD} ({SECTION})")
    return 0


def _run_with_full_refs(name, ds, variants, ref_cfg, est_cfg, kind, models, cache, reuse, skip_target_scenes=False,
                        first_images=None):
    """Estimates with references built from ``ref_cfg`` (all encodings) and an estimator on ``est_cfg``."""
    orig = models.refs

    def refs_full(path, _cfg, _orig=orig):
        return _orig(path, ref_cfg)

    models.refs = refs_full
    try:
        return estimate_all(name, ds, variants, est_cfg, kind, models, cache, reuse=reuse,
                            skip_target_scenes=skip_target_scenes, first_images=first_images)
    finally:
        models.refs = orig


if __name__ == "__main__":
    raise SystemExit(main())
