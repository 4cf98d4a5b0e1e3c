"""Fine-tuned cross-modality matcher: data cache, training, shipping, LM-O oracle comparison.

Usage::

    # 1. synthetic pairs -> cached ALIKED features (resumable; run several in parallel on seed ranges)
    nice .venv/bin/python bench/finetune_matcher.py gen --seeds 50000:50300 --out out/ft/cache/train
    nice .venv/bin/python bench/finetune_matcher.py gen --seeds 900000:900030 --out out/ft/cache/val
    # 2. train the adapter (resumable checkpoints in out/ft/run/)
    nice .venv/bin/python bench/finetune_matcher.py train --steps 400 --eval-every 100 --hidden 64 --wd 1e-2 --run out/ft/run_h64
    # 3. copy the adapter into the package with its model card numbers
    nice .venv/bin/python bench/finetune_matcher.py ship --run out/ft/run_h64 --best
    # 4. oracle comparison on real LM-O crops (evaluation only), off-the-shelf vs fine-tuned, same targets
    #    (ALIKED features are cached on disk by image, so every variant shares keypoints and costs one extraction)
    nice .venv/bin/python bench/finetune_matcher.py oracle --max-targets 80 \
        --matchers aliked-nn,aliked-topk,aliked-grid6,aliked-ft-nogrid,aliked-ft-grid6,aliked-ft-topk

No benchmark object is ever used for training: the data are procedural parts (pixie.synth.parts).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
OUT = REPO / "out" / "ft"


def _seeds(text: str) -> list[int]:
    a, b = text.split(":")
    return list(range(int(a), int(b)))


def cmd_gen(args) -> int:
    import torch

    from pixie.synth.pairs import PairConfig
    from pixie.train.finetune import build_cache

    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    seeds = _seeds(args.seeds)
    paths = build_cache(seeds, args.out, PairConfig(size=args.size), encodings_per_pair=args.encodings, grid=args.grid)
    dt = time.perf_counter() - t0
    print(json.dumps({"pairs": len(seeds), "files": len(paths), "seconds": round(dt, 1),
                      "pairs_per_s": round(len(seeds) / dt, 3)}))
    return 0


def cmd_train(args) -> int:
    import torch

    from pixie.train.finetune import TrainConfig, evaluate, load_cache, train

    torch.set_num_threads(args.threads)
    tr = sorted(Path(args.train).glob("pair_*.npz"))
    va = sorted(Path(args.val).glob("pair_*.npz"))
    if args.max_train:
        tr = tr[: args.max_train]
    train_data, val_data = load_cache(tr), load_cache(va)
    print(f"train pairs {len(train_data)} (valid query anchors {sum(int(d['q_valid'].sum()) for d in train_data)}), "
          f"val pairs {len(val_data)}", flush=True)
    base = evaluate(None, val_data)
    print("  off-the-shelf val: " + json.dumps({k: round(v, 4) for k, v in base.items()}), flush=True)
    cfg = TrainConfig(steps=args.steps, hidden=args.hidden, layers=args.layers, lr=args.lr, batch_pairs=args.batch,
                      eval_every=args.eval_every, ckpt_every=args.eval_every, threads=args.threads,
                      weight_decay=args.wd)
    model, hist = train(train_data, val_data, cfg, run_dir=args.run, log=lambda m: print(m, flush=True))
    summary = {"train_pairs": len(train_data), "val_pairs": len(val_data), "config": cfg.__dict__,
               "val_off_the_shelf": base, "history": hist,
               "train_files": [p.name for p in tr], "val_files": [p.name for p in va]}
    (Path(args.run) / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    return 0


def cmd_ship(args) -> int:
    from pixie.matching.adapter import DescriptorAdapter, shipped_adapter_path
    from pixie.train.finetune import load_checkpoint, save_adapter

    ck = load_checkpoint(Path(args.run) / ("best.pt" if args.best else "last.pt"))
    c = ck["config"]
    model = DescriptorAdapter(128, c["hidden"], c["layers"])
    model.load_state_dict(ck["model"])
    summ = json.loads((Path(args.run) / "summary.json").read_text())
    meta = {"steps": ck["step"], "checkpoint": "best (lowest val loss)" if args.best else "last", "train_pairs": summ["train_pairs"], "val_pairs": summ["val_pairs"],
            "val_final": ck["history"][-1] if ck["history"] else None, "val_off_the_shelf": summ["val_off_the_shelf"],
            "base": "aliked-n16 (Shiaoming/ALIKED weights), descriptors of kornia's ALIKED"}
    path = save_adapter(model, args.to or shipped_adapter_path(), meta)
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB)")
    return 0


class CachedAliked:
    """ALIKED-n16 extractor with an on-disk cache of raw features (keyed by image + mask bytes); an optional
    adapter is applied on top, so off-the-shelf and fine-tuned descriptors share the same keypoints and
    the fine-tuned run costs no second backbone pass."""

    def __init__(self, cache_dir: Path, adapter=None, max_keypoints: int = 1024, grid: int = 0,
                 detection_threshold: float | None = None):
        import torch

        from pixie.matching.aliked import AlikedExtractor

        self.cache_dir = Path(cache_dir)
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        self._inner = None
        self._mk = max_keypoints
        self.adapter = adapter
        self.grid = int(grid)
        self.device = torch.device("cpu")
        self.dim = 128
        self.threshold = detection_threshold
        self._factory = lambda: AlikedExtractor(self.device, max_keypoints=self._mk, allow_download=False,
                                                detection_threshold=detection_threshold)

    def __call__(self, image, mask=None):
        import hashlib

        import numpy as np

        from pixie.matching import Features

        h = hashlib.sha1(np.ascontiguousarray(image).tobytes())
        h.update(b"none" if mask is None else np.packbits(np.asarray(mask, bool)).tobytes())
        h.update(str(image.shape).encode() + str(self._mk).encode())
        if self.grid and mask is not None:
            h.update(f"grid{self.grid}".encode())
        if self.threshold is not None:
            h.update(f"thr{self.threshold}".encode())
        path = self.cache_dir / f"{h.hexdigest()}.npz"
        if path.is_file():
            with np.load(path) as z:
                f = Features.from_arrays(z)
        else:
            self._inner = self._inner or self._factory()
            if self.grid and mask is not None:
                from pixie.matching.adapter import aliked_extract
                from pixie.geometry.rotations import check_image

                img = check_image(image)
                kp, desc, sc, _ = aliked_extract(self._inner.net, img, np.asarray(mask, bool), self.grid)
                f = Features(kp, desc, sc, img.shape[:2])
            else:
                f = self._inner(image, mask)
            tmp = path.with_suffix(".tmp.npz")
            np.savez(tmp, **f.to_arrays())
            tmp.replace(path)
        f.descriptors = f.descriptors.astype(np.float32)
        if self.adapter is not None:
            f.descriptors = self.adapter.apply_np(f.descriptors)
        else:  # float16 storage: renormalise
            f.descriptors /= np.maximum(np.linalg.norm(f.descriptors, axis=1, keepdims=True), 1e-12)
        return f


def oracle_matchers(names: list[str], window: float, cache_dir: Path, adapter_path=None):
    import torch

    from pixie.matching.adapter import load_adapter
    from pixie.matching import LightGlueAssigner, Matcher, MutualNNAssigner, build_lightglue
    from pixie.weights import load_state_dict

    dev = torch.device("cpu")
    out = {}
    for n in names:
        if n == "aliked-nn":
            out[n] = Matcher(n, CachedAliked(cache_dir), MutualNNAssigner(dev, window=window))
        elif n == "aliked-nn-nowin":
            out[n] = Matcher(n, CachedAliked(cache_dir), MutualNNAssigner(dev))
        elif n == "aliked-lg":
            model = build_lightglue("aliked", load_state_dict("aliked_lightglue"), dev)
            out[n] = Matcher(n, CachedAliked(cache_dir), LightGlueAssigner(model, dev))
        elif n == "aliked-ft-nogrid":  # the adapter alone (no reference grid)
            out[n] = Matcher(n, CachedAliked(cache_dir, adapter=load_adapter(adapter_path)),
                             MutualNNAssigner(dev, window=window))
        elif n == "aliked-ft-grid":  # adapter + 6 px reference grid, ALIKED threshold 0.2 (first shipped default)
            out[n] = Matcher(n, CachedAliked(cache_dir, adapter=load_adapter(adapter_path), grid=6),
                             MutualNNAssigner(dev, window=window))
        elif n in ("aliked-topk", "aliked-ft-topk", "aliked-ft-nn"):  # threshold 0: the 1024 strongest maxima
            # aliked-ft-nn = what get_matcher("aliked-ft-nn") builds (adapter + top-k, no grid)
            ad = load_adapter(adapter_path) if n.startswith("aliked-ft") else None
            out[n] = Matcher(n, CachedAliked(cache_dir, adapter=ad, detection_threshold=0.0),  # same cache as topk
                             MutualNNAssigner(dev, window=window))
        elif n.startswith("aliked-grid") or n.startswith("aliked-ft-grid"):  # e.g. aliked-grid6, aliked-ft-grid6
            g = int(n.rsplit("grid", 1)[1])
            ad = load_adapter(adapter_path) if n.startswith("aliked-ft") else None
            out[n] = Matcher(n, CachedAliked(cache_dir, adapter=ad, grid=g), MutualNNAssigner(dev, window=window))
        else:
            raise SystemExit(f"unknown oracle matcher {n}")
    return out


def cmd_oracle(args) -> int:
    import numpy as np
    import torch

    import common as C  # bench/common.py (this script's folder is on sys.path)
    import lmo_pipeline as LP

    from pixie.eval.datasets import BopDataset

    torch.set_num_threads(args.threads)
    ds = BopDataset(C.DEFAULT_DATASET)
    targets = C.select_targets(ds, args.max_targets)
    cfg = C.make_config(args.set, args.preset)
    window = cfg.match.window * cfg.refs.size
    objects = C.ObjectCache(ds)
    mats = oracle_matchers(args.matchers.split(","), window, OUT / "oracle_feature_cache", args.adapter)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, m in mats.items():
        t0 = time.perf_counter()
        r = LP.run_oracle(ds, targets, cfg, matcher=m, objects=objects)
        r["name"] = name
        r["encodings"] = list(cfg.refs.encodings)
        per_enc = {}
        for e in cfg.refs.encodings:
            per_enc[e] = {"matches": float(np.mean([t["per_encoding"][e][0] for t in r["targets"]])),
                          "correct": float(np.mean([t["per_encoding"][e][1] for t in r["targets"]]))}
        r["per_encoding_mean"] = per_enc
        per_obj = {}
        for t in r["targets"]:
            o = per_obj.setdefault(t["obj_id"], [0, 0])
            o[0] += int(t["add_ok"])
            o[1] += 1
        r["per_object_add"] = {k: f"{a}/{b}" for k, (a, b) in sorted(per_obj.items())}
        (args.out / f"oracle_{name}.json").write_text(json.dumps(r, indent=1, default=float))
        rows.append(r)
        print(f"[{name}] {len(targets)} targets in {time.perf_counter() - t0:.0f} s: matches {r['mean_matches']:.1f} "
              f"correct {r['mean_correct']:.1f} (median {r['median_correct']:.0f}) inliers {r['mean_inliers']:.1f} "
              f"ADD<0.1d {r['add_0.1d']:.3f}  per-encoding {json.dumps(per_enc)}", flush=True)
    print("\n| matcher | targets | matches | correct (mean / median) | PnP inliers | ADD(-S)<0.1d | med. rot err | per object ADD |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['name']} | {r['n_targets']} | {r['mean_matches']:.1f} | {r['mean_correct']:.1f} / {r['median_correct']:.0f} | "
              f"{r['mean_inliers']:.1f} | {r['add_0.1d']:.3f} | {r['median_rot_err']} | {r['per_object_add']} |")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("gen", help="make synthetic pairs and cache their ALIKED features")
    g.add_argument("--seeds", required=True, help="a:b (range of pair seeds)")
    g.add_argument("--out", type=Path, required=True)
    g.add_argument("--size", type=int, default=512)
    g.add_argument("--encodings", type=int, default=1, help="reference encodings per pair")
    g.add_argument("--threads", type=int, default=1)
    g.add_argument("--grid", type=int, default=6, help="reference grid stride (0: detections only)")
    t = sub.add_parser("train", help="train the descriptor adapter on the cache")
    t.add_argument("--train", type=Path, default=OUT / "cache" / "train")
    t.add_argument("--val", type=Path, default=OUT / "cache" / "val")
    t.add_argument("--run", type=Path, default=OUT / "run")
    t.add_argument("--steps", type=int, default=2000)
    t.add_argument("--hidden", type=int, default=256)
    t.add_argument("--layers", type=int, default=2)
    t.add_argument("--lr", type=float, default=1e-3)
    t.add_argument("--wd", type=float, default=1e-4)
    t.add_argument("--batch", type=int, default=4)
    t.add_argument("--eval-every", type=int, default=200)
    t.add_argument("--max-train", type=int, default=None)
    t.add_argument("--threads", type=int, default=1)
    sh = sub.add_parser("ship", help="copy the trained adapter into src/pixie/data/weights")
    sh.add_argument("--run", type=Path, default=OUT / "run")
    sh.add_argument("--to", type=Path, default=None)
    sh.add_argument("--best", action="store_true", help="ship the checkpoint of the lowest validation loss")
    o = sub.add_parser("oracle", help="LM-O oracle comparison (bench/lmo_pipeline.run_oracle), same targets")
    o.add_argument("--max-targets", type=int, default=40)
    o.add_argument("--matchers", default="aliked-nn,aliked-topk,aliked-grid6,aliked-ft-nogrid,aliked-ft-grid6,aliked-ft-topk",
                   help="aliked-nn, aliked-nn-nowin, aliked-lg, aliked-topk (threshold 0), aliked-gridN (off-the-shelf "
                        "+ N px reference grid), aliked-ft-nogrid, aliked-ft-gridN, aliked-ft-topk (= aliked-ft-nn, "
                        "the registered backend's defaults)")
    o.add_argument("--adapter", type=Path, default=None, help="adapter file (default: the shipped one)")
    o.add_argument("--set", action="append", default=[], help="section.key=value (as lmo_pipeline)")
    o.add_argument("--out", type=Path, default=OUT / "oracle")
    o.add_argument("--threads", type=int, default=1)
    o.add_argument("--preset", default="default", help="configuration the comparison starts from (default default)")
    args = ap.parse_args(argv)
    return {"gen": cmd_gen, "train": cmd_train, "ship": cmd_ship, "oracle": cmd_oracle}[args.cmd](args)


if __name__ == "__main__":
    raise SystemExit(main())
