"""Fine-tuning a descriptor adapter for photo <-> geometry-render matching (CPU-sized).

What is trained
    :class:`DescriptorAdapter`: a small residual MLP applied to the (frozen) ALIKED-n16 descriptors,
    ``d' = normalize(d + W2 gelu(W1 d))`` with ``W2`` zero-initialised (the untrained adapter is the
    identity). One adapter is shared by the photo side and the geometry side (pixie extracts both through
    the same ``matcher.extract``, which does not know which side an image is).

Data
    :func:`build_cache` runs ALIKED once per synthetic pair (:func:`pixie.synth.pairs.make_pair`) and keeps,
    per pair: query keypoints/descriptors (no mask, 1024 max, as the oracle extracts a query crop), their
    ground-truth reference positions and validity, reference keypoints/descriptors (inside the mask), the
    reference descriptors *at* the GT positions of the query keypoints and the query descriptors at the GT
    positions of the reference keypoints (descriptor head evaluated at arbitrary points). Training then only
    touches these small arrays.

Loss
    Windowed symmetric InfoNCE: for each valid query keypoint i, the positive is the reference descriptor at
    its GT position; negatives are the detected reference keypoints within ``window`` px of that GT position
    (those closer than ``pos_px`` are left out); and the same from the reference side. This is the local
    discrimination a windowed mutual-NN matcher needs.

Checkpoints are resumable (model + optimizer + step + RNG), written atomically and split so each file stays
under ``max_file_mb``.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from pixie.features import Features
from pixie.geometry.rotations import check_image
from pixie.matching.adapter import DescriptorAdapter, aliked_extract, load_adapter, shipped_adapter_path
from pixie.matching.aliked import AlikedExtractor
from pixie.synth.pairs import make_pair

__all__ = [
    "DescriptorAdapter",
    "AlikedDense",
    "extract_pair",
    "build_cache",
    "TrainConfig",
    "train",
    "evaluate",
    "load_cache",
    "save_checkpoint",
    "load_checkpoint",
    "save_adapter",
    "load_adapter",
    "shipped_adapter_path",
]


# ----------------------------------------------------------------------------------------------------- model


class AlikedDense:
    """ALIKED-n16 (pixie's weights) giving detections and descriptors at arbitrary pixel positions."""

    def __init__(self, model: str = "aliked-n16", max_keypoints: int = 1024):
        self.ext = AlikedExtractor(torch.device("cpu"), model=model, max_keypoints=max_keypoints, allow_download=False)
        self.net = self.ext.net

    def __call__(self, rgb: np.ndarray, mask: np.ndarray | None = None, extra_xy: np.ndarray | None = None,
                 grid: int = 0):
        """Features (detections [+ grid inside the mask]) and descriptors at ``extra_xy`` (or a describer
        function on the same feature map with ``extra_xy="describer"``); one backbone pass."""
        img = check_image(rgb)
        kp, desc, sc, extra = aliked_extract(self.net, img, mask, grid, extra_xy)
        return Features(kp, desc, sc, img.shape[:2]), extra


# ------------------------------------------------------------------------------------------------------ data


def extract_pair(pair, dense: AlikedDense, encoding: str, grid: int = 6) -> dict[str, np.ndarray]:
    """The training arrays of one pair for one reference encoding (see the module docstring)."""
    ref = pair.refs[encoding]
    # GT positions of every reference pixel's point in the query are known before detection, but the
    # reference keypoints are not: detect on the reference first, then one pass over the query does both.
    rf, ref_describe = dense(ref, mask=pair.ref_mask, extra_xy="describer", grid=grid)
    r_uv, r_valid = pair.correspond_ref(rf.keypoints)
    qf, h_desc = dense(pair.query, extra_xy=r_uv[r_valid])
    q_uv, q_valid = pair.correspond(qf.keypoints)
    g_desc = ref_describe(q_uv[q_valid])
    G = np.zeros((len(qf), qf.dim), np.float16)
    G[q_valid] = g_desc
    Hq = np.zeros((len(rf), rf.dim), np.float16)
    Hq[r_valid] = h_desc
    return {
        "q_kp": qf.keypoints, "q_desc": qf.descriptors.astype(np.float16), "q_uv": q_uv, "q_valid": q_valid,
        "r_kp": rf.keypoints, "r_desc": rf.descriptors.astype(np.float16), "r_uv": r_uv, "r_valid": r_valid,
        "g_desc": G, "h_desc": Hq,
        "meta": np.frombuffer(json.dumps({"seed": pair.seed, "encoding": encoding, "part": pair.mesh.name,
                                          "visib": pair.visib_fract, "size": int(pair.query.shape[0]), "grid": grid}).encode(),
                              np.uint8),
    }


def build_cache(seeds, out_dir: str | Path, pair_cfg=None, encodings_per_pair: int = 1, grid: int = 6,
                enc_probs: dict[str, float] | None = None, log=print) -> list[Path]:
    """Make pairs for ``seeds`` and write one ``pair_<seed>_<enc>.npz`` each (existing files are kept)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    probs = enc_probs or {"shade3_edges": 0.5, "depth": 0.25, "normal": 0.25}
    names, p = list(probs), np.array(list(probs.values()), float)
    dense = None
    written = []
    t0 = time.perf_counter()
    for k, seed in enumerate(seeds):
        rng = np.random.default_rng([int(seed), 99])
        encs = list(rng.choice(names, size=min(encodings_per_pair, len(names)), replace=False, p=p / p.sum()))
        paths = [out_dir / f"pair_{int(seed):07d}_{e}.npz" for e in encs]
        if all(q.is_file() for q in paths):
            written += paths
            continue
        dense = dense or AlikedDense()
        pair = make_pair(int(seed), pair_cfg)
        for e, path in zip(encs, paths):
            arrays = extract_pair(pair, dense, e, grid)
            tmp = path.with_suffix(".tmp.npz")
            np.savez(tmp, **arrays)
            os.replace(tmp, path)
            written.append(path)
        if log and (k + 1) % 10 == 0:
            log(f"  cache {k + 1}/{len(seeds)}  {(time.perf_counter() - t0) / (k + 1):.2f} s/pair")
    return written


def load_cache(paths) -> list[dict[str, np.ndarray]]:
    out = []
    for p in paths:
        with np.load(p) as z:
            d = {k: z[k] for k in z.files}
        d["meta"] = json.loads(d["meta"].tobytes().decode())
        out.append(d)
    return out


# ------------------------------------------------------------------------------------------------------ loss


def _t(a, dtype=torch.float32):
    return torch.from_numpy(np.asarray(a)).to(dtype)


def _side_loss(anchor: torch.Tensor, anchor_gt: torch.Tensor, pos: torch.Tensor, cand: torch.Tensor,
               cand_xy: torch.Tensor, window: float, pos_px: float, temp: torch.Tensor) -> torch.Tensor:
    """InfoNCE of anchors (A, D) against [their positive (A, D) | candidates (C, D) within the window]."""
    if len(anchor) == 0:
        return anchor.sum() * 0.0
    s_pos = (anchor * pos).sum(-1, keepdim=True)
    s_cand = anchor @ cand.t()
    dist = torch.cdist(anchor_gt, cand_xy) if len(cand) else torch.zeros(len(anchor), 0)
    keep = (dist < window) & (dist > pos_px)
    s_cand = (s_cand / temp).masked_fill(~keep, float("-inf"))  # mask after the division: no inf * 0 gradient
    logits = torch.cat([s_pos / temp, s_cand], 1)
    return -(logits.log_softmax(1)[:, 0]).mean()


def pair_loss(model: nn.Module, d: dict, temp: torch.Tensor, window: float = 64.0, pos_px: float = 3.0,
              max_anchors: int = 256, rng: np.random.Generator | None = None) -> torch.Tensor:
    """Symmetric windowed InfoNCE of one cached pair."""
    rng = rng or np.random.default_rng(0)
    q = model(_t(d["q_desc"]))
    r = model(_t(d["r_desc"]))
    qi = np.flatnonzero(d["q_valid"])
    ri = np.flatnonzero(d["r_valid"])
    if len(qi) > max_anchors:
        qi = np.sort(rng.choice(qi, max_anchors, replace=False))
    if len(ri) > max_anchors:
        ri = np.sort(rng.choice(ri, max_anchors, replace=False))
    g = model(_t(d["g_desc"][qi]))
    h = model(_t(d["h_desc"][ri]))
    l1 = _side_loss(q[qi], _t(d["q_uv"][qi]), g, r, _t(d["r_kp"]), window, pos_px, temp)
    l2 = _side_loss(r[ri], _t(d["r_uv"][ri]), h, q, _t(d["q_kp"]), window, pos_px, temp)
    return 0.5 * (l1 + l2)


# ------------------------------------------------------------------------------------------------ evaluation


def _mnn(qd: np.ndarray, rd: np.ndarray, qk: np.ndarray, rk: np.ndarray, window: float | None):
    if len(qd) == 0 or len(rd) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    s = qd @ rd.T
    if window is not None:
        s = np.where(np.linalg.norm(qk[:, None] - rk[None], axis=-1) < window, s, -np.inf)
    a = s.argmax(1)
    b = s.argmax(0)
    i = np.arange(len(qd))
    ok = (b[a] == i) & np.isfinite(s[i, a])
    return i[ok], a[ok]


@torch.inference_mode()
def evaluate(model: nn.Module | None, data: list[dict], window_frac: float = 0.125, px: float = 3.0,
             aligned_window: bool = True) -> dict:
    """Windowed mutual-NN matching precision / recall at ``px`` on cached pairs.

    The window is centred on each query keypoint's GT reference position when ``aligned_window`` (it
    simulates the aligned reference of the pipeline; synthetic references are rolled), else on its position.
    precision = correct / matches; recall = correct / matchable (query keypoints with a valid GT whose
    GT position has a detected reference keypoint within ``px``).
    """
    tot_m = tot_c = tot_able = 0
    for d in data:
        qd = d["q_desc"].astype(np.float32)
        rd = d["r_desc"].astype(np.float32)
        if model is not None:
            qd = model(_t(qd)).numpy()
            rd = model(_t(rd)).numpy()
        S = float(d["meta"].get("size", 512))
        win = window_frac * S
        qk = np.where(d["q_valid"][:, None], d["q_uv"], d["q_kp"]) if aligned_window else d["q_kp"]
        ii, jj = _mnn(qd, rd, qk, d["r_kp"], win)
        err = np.linalg.norm(d["q_uv"][ii] - d["r_kp"][jj], axis=1)
        correct = d["q_valid"][ii] & (err < px)
        if len(d["r_kp"]):
            dmin = np.linalg.norm(d["q_uv"][:, None] - d["r_kp"][None], axis=-1).min(1)
            able = d["q_valid"] & (dmin < px)
        else:
            able = np.zeros(len(qd), bool)
        tot_m += len(ii)
        tot_c += int(correct.sum())
        tot_able += int(able.sum())
    return {"matches_per_pair": tot_m / max(len(data), 1), "correct_per_pair": tot_c / max(len(data), 1),
            "precision": tot_c / max(tot_m, 1), "recall": tot_c / max(tot_able, 1), "pairs": len(data)}


# -------------------------------------------------------------------------------------------------- training


@dataclass
class TrainConfig:
    hidden: int = 256
    layers: int = 2
    lr: float = 1e-3
    weight_decay: float = 1e-4
    steps: int = 2000
    batch_pairs: int = 4
    window: float = 64.0
    pos_px: float = 3.0
    max_anchors: int = 256
    init_temp: float = 0.05
    eval_every: int = 200
    ckpt_every: int = 200
    seed: int = 0
    threads: int = 1


def save_checkpoint(path: str | Path, state: dict, max_file_mb: float = 15.0) -> list[Path]:
    """Write ``state`` (any torch-serialisable dict) as ``path`` (+ ``path.partN``) files each < ``max_file_mb``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    torch.save(state, buf)
    data = buf.getvalue()
    chunk = int(max_file_mb * 1024 * 1024)
    parts = [data[i:i + chunk] for i in range(0, len(data), chunk)] or [b""]
    names = [path] + [path.with_name(f"{path.name}.part{k}") for k in range(1, len(parts))]
    for name, blob in zip(names, parts):
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{name.name}.")
        with os.fdopen(fd, "wb") as fh:
            fh.write(blob)
        os.replace(tmp, name)
    (path.with_name(path.name + ".json")).write_text(json.dumps({"parts": len(parts), "bytes": len(data)}))
    return names


def load_checkpoint(path: str | Path) -> dict:
    """Inverse of :func:`save_checkpoint`."""
    path = Path(path)
    info = json.loads(path.with_name(path.name + ".json").read_text())
    blob = b"".join((path if k == 0 else path.with_name(f"{path.name}.part{k}")).read_bytes() for k in range(info["parts"]))
    return torch.load(io.BytesIO(blob), map_location="cpu", weights_only=False)


def train(train_data: list[dict], val_data: list[dict], cfg: TrainConfig, run_dir: str | Path | None = None,
          log=print, resume: bool = True) -> tuple[DescriptorAdapter, list[dict]]:
    """Train an adapter; returns it and the history (step, loss, val metrics). Resumes from ``run_dir/last.pt``."""
    torch.set_num_threads(max(1, int(cfg.threads)))
    torch.manual_seed(cfg.seed)
    model = DescriptorAdapter(128, cfg.hidden, cfg.layers)
    log_temp = nn.Parameter(torch.tensor(float(np.log(cfg.init_temp))))
    opt = torch.optim.AdamW(list(model.parameters()) + [log_temp], lr=cfg.lr, weight_decay=cfg.weight_decay)
    rng = np.random.default_rng(cfg.seed)
    step, history = 0, []
    run_dir = Path(run_dir) if run_dir else None
    if run_dir and resume and (run_dir / "last.pt.json").is_file():
        ck = load_checkpoint(run_dir / "last.pt")
        model.load_state_dict(ck["model"])
        log_temp.data.copy_(ck["log_temp"])
        opt.load_state_dict(ck["optimizer"])
        step, history = int(ck["step"]), list(ck["history"])
        rng.bit_generator.state = ck["rng"]
        log(f"  resumed at step {step}")
    sched_lr = lambda s: cfg.lr * min(1.0, (s + 1) / 50) * (0.5 * (1 + np.cos(np.pi * min(s / max(cfg.steps, 1), 1.0))))  # noqa: E731
    t0 = time.perf_counter()
    run_loss = []
    while step < cfg.steps:
        for gparam in opt.param_groups:
            gparam["lr"] = sched_lr(step)
        idx = rng.choice(len(train_data), min(cfg.batch_pairs, len(train_data)), replace=False)
        loss = sum(pair_loss(model, train_data[i], log_temp.exp(), cfg.window, cfg.pos_px, cfg.max_anchors, rng)
                   for i in idx) / len(idx)
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        run_loss.append(float(loss.detach()))
        if step % cfg.eval_every == 0 or step == cfg.steps or step == 1:
            model.eval()
            v = evaluate(model, val_data) if val_data else {}
            with torch.no_grad():
                vl = float(np.mean([float(pair_loss(model, d, log_temp.exp(), cfg.window, cfg.pos_px, cfg.max_anchors,
                                                    np.random.default_rng(0))) for d in val_data])) if val_data else None
            model.train()
            rec = {"step": step, "train_loss": float(np.mean(run_loss)), "val_loss": vl, "temp": float(log_temp.detach().exp()),
                   **{f"val_{k}": x for k, x in v.items()}, "seconds": time.perf_counter() - t0}
            history.append(rec)
            run_loss = []
            best = min((h["val_loss"] for h in history[:-1] if h.get("val_loss") is not None), default=None)
            if run_dir and vl is not None and (best is None or vl < best):  # early-stopping snapshot
                save_checkpoint(run_dir / "best.pt", {"model": model.state_dict(), "log_temp": log_temp.detach().clone(),
                                                      "step": step, "history": list(history), "config": asdict(cfg)})
            log("  " + json.dumps({k: (round(x, 4) if isinstance(x, float) else x) for k, x in rec.items()}))
        if run_dir and (step % cfg.ckpt_every == 0 or step == cfg.steps):
            save_checkpoint(run_dir / "last.pt", {"model": model.state_dict(), "log_temp": log_temp.detach().clone(),
                                                  "optimizer": opt.state_dict(), "step": step, "history": history,
                                                  "rng": rng.bit_generator.state, "config": asdict(cfg)})
    return model, history


def save_adapter(model: DescriptorAdapter, path: str | Path, meta: dict | None = None) -> Path:
    """Ship an adapter: its weights (float32) + config + metadata, one small file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"config": model.config(), "state_dict": {k: v.detach().float().clone() for k, v in model.state_dict().items()},
                "meta": meta or {}}, path)
    return path
