"""What the LM-O studies share: paths, the preset a study starts from, target selection, the per-object cache.

Bench scripts import it as ``import common`` (a script's own folder is on ``sys.path``); it puts ``src/`` on the
path before importing pixie, so the studies run from a source checkout without installing it.

* :func:`make_config` starts from ``PixieConfig.from_preset(preset)`` (``--preset``, default ``default``), then
  the ``--set`` overrides; :func:`add_preset_arg` adds the option, :func:`config_for_hash` the run-hash view;
* :func:`select_targets`, :func:`gt_instance`: which targets a study runs, and each one's ground truth;
* :class:`ObjectCache`: meshes, eval data, renderers and reference sets per object (``out/bench/refs``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from pixie.app.runner import cached_reference_set, reference_cache_path  # noqa: E402
from pixie.config import DEFAULT_PRESET, PixieConfig, preset_names  # noqa: E402
from pixie.eval import load_object_data, pose_errors  # noqa: E402,F401  (pose_errors: re-exported for the studies)
from pixie.eval.datasets import BopDataset, Target  # noqa: E402
from pixie.geometry.mesh import load_mesh  # noqa: E402
from pixie.geometry.render import Renderer  # noqa: E402

DEFAULT_DATASET = REPO.parent / "shared/data/lmo_dev/lmo"
DEFAULT_OUT = REPO / "out/bench/lmo_pipeline"
REFS_CACHE = REPO / "out/bench/refs"


def add_preset_arg(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--preset", default=DEFAULT_PRESET, choices=preset_names(),
                    help=f"configuration the study starts from, before --set (default {DEFAULT_PRESET})")


def make_config(overrides: list[str], preset: str = DEFAULT_PRESET) -> PixieConfig:
    """``PixieConfig.from_preset(preset)`` with the ``section.key=value`` overrides applied (``cfg.preset`` names it)."""
    return PixieConfig.from_preset(preset).apply_overrides(overrides)


def config_for_hash(cfg: PixieConfig) -> dict:
    """``cfg.to_dict()`` with ``match.device=auto`` resolved to the device it runs on: a run hash names what ran,
    so the ``default`` preset (device auto) on a CPU machine hashes as the dataclass defaults (device cpu) did."""
    d = cfg.to_dict()
    if d.get("match", {}).get("device") == "auto":
        import torch

        d["match"]["device"] = "cuda" if torch.cuda.is_available() else "cpu"
    return d


def parse_config_arg(text: str) -> tuple[str, list[str]]:
    """``NAME:a.b=1,c.d=x`` -> ("NAME", ["a.b=1", "c.d=x"]). Lists inside [] keep their commas."""
    name, _, rest = text.partition(":")
    items, depth, cur = [], 0, ""
    for ch in rest:
        depth += ch == "["
        depth -= ch == "]"
        if ch == "," and depth == 0:
            items.append(cur)
            cur = ""
        else:
            cur += ch
    if cur:
        items.append(cur)
    return name, [i.strip() for i in items if i.strip()]


def write_json(path: Path | None, obj) -> None:
    """A bench's JSON output (its folder made first); nothing when ``path`` is None."""
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(obj, indent=1))


def short_hash(obj) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:12]


def select_targets(ds: BopDataset, max_targets: int | None, objects: list[int] | None = None) -> list[Target]:
    """All targets, or ``max_targets`` spread evenly over the objects (evenly spaced within each object)."""
    tg = [t for t in ds.targets() if objects is None or t.obj_id in objects]
    if not max_targets or max_targets >= len(tg):
        return tg
    by_obj: dict[int, list[Target]] = {}
    for t in tg:
        by_obj.setdefault(t.obj_id, []).append(t)
    per = max(1, math.ceil(max_targets / len(by_obj)))
    out = []
    for oid in sorted(by_obj):
        lst = by_obj[oid]
        idx = np.unique(np.linspace(0, len(lst) - 1, min(per, len(lst))).round().astype(int))
        out += [lst[i] for i in idx]
    return sorted(out, key=lambda t: (t.scene_id, t.im_id, t.obj_id))


def gt_instance(ds: BopDataset, t: Target):
    """The most visible GT instance of the target's object (LM-O has one per object)."""
    insts = [g for g in ds.instances(t.scene_id, t.im_id) if g.obj_id == t.obj_id]
    return max(insts, key=lambda g: g.visib_fract or 0.0)


class ObjectCache:
    """Per object: model mesh (mm), eval data (diameter, ADD points, symmetry), reference sets per config.

    Reference sets come from :func:`pixie.app.runner.cached_reference_set` (one cache in ``out/bench/refs``, shared
    with other bench processes); ``build_seconds`` and ``refs_bytes`` record what they cost.
    """

    def __init__(self, ds: BopDataset):
        self.ds = ds
        self._mesh, self._eval, self._refs, self._renderer = {}, {}, {}, {}
        self.build_seconds: dict[tuple[str, int], float] = {}
        self.refs_bytes: dict[tuple[str, int], int] = {}

    def mesh(self, oid: int):
        if oid not in self._mesh:
            self._mesh[oid] = load_mesh(self.ds.model_path(oid), units="mm")
        return self._mesh[oid]

    def eval_data(self, oid: int):
        if oid not in self._eval:
            self._eval[oid] = load_object_data(self.ds, oid, n_points=2000)
        return self._eval[oid]

    def renderer(self, oid: int, smooth: bool = True):
        if (oid, smooth) not in self._renderer:
            self._renderer[(oid, smooth)] = Renderer(self.mesh(oid), smooth_normals=smooth)
        return self._renderer[(oid, smooth)]

    def refs(self, cfg: PixieConfig, oid: int, matcher, log=print):
        path = reference_cache_path(self.mesh(oid), cfg, REFS_CACHE)
        key = path.stem
        if (key, oid) in self._refs:
            return self._refs[(key, oid)]
        refs = cached_reference_set(self.mesh(oid), cfg, REFS_CACHE, matcher=matcher,
                                    echo=lambda msg: log(f"  obj {oid}: {msg}"))
        self.build_seconds[(refs_key(cfg), oid)] = refs.build_seconds
        self.refs_bytes[(refs_key(cfg), oid)] = path.stat().st_size
        self._refs = {k: v for k, v in self._refs.items() if k[0] == key}  # keep one config's sets in memory
        self._refs[(key, oid)] = refs
        return refs


def refs_key(cfg: PixieConfig) -> str:
    """What the reference sets of a configuration depend on (the summary's key; the cache adds the mesh)."""
    m = cfg.match
    return short_hash({"refs": cfg.refs.__dict__, "matcher": m.matcher, "max_kp": m.max_keypoints, "w": m.weights_dir,
                  "det": m.detection_threshold})
