"""The package's layering (ARCHITECTURE.md), checked by parsing every module's imports.

* the import graph of ``pixie`` modules has no cycle;
* no module imports a module of a higher layer (``LAYERS``; the package root ``pixie/__init__.py`` is the
  public facade and may import anything);
* imports inside functions are only used for the optional or heavy third-party packages of
  ``LAZY_THIRD_PARTY`` (never for ``pixie`` modules: a function-local import would hide the layering);
* no module is longer than ``MAX_LINES`` unless its docstring states why.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "pixie"

# Lowest first. A module may import modules of its own or a lower layer. Packages are listed by prefix.
LAYERS: list[tuple[str, ...]] = [
    ("pixie._version", "pixie.errors", "pixie.paths"),
    ("pixie.config", "pixie.weights", "pixie.geometry"),
    ("pixie.camera", "pixie.mesh"),
    ("pixie.render", "pixie.views", "pixie.encode", "pixie.features", "pixie.query",
     "pixie.plausibility"),
    ("pixie.references",),
    ("pixie.matching",),
    ("pixie.pose",),
    # cues beside refinement: edge/contour templates, region refinement (pixie.contours, pixie.edges, pixie.region)
    ("pixie.refine", "pixie.contours", "pixie.edges", "pixie.region", "pixie.cues", "pixie.shape", "pixie.edge_photo", "pixie.edge_align"),
    ("pixie.results", "pixie.estimator"),
    ("pixie.viz",),
    ("pixie.eval",),
    ("pixie.synth",),
    ("pixie.train",),
    ("pixie.cluster",),
    ("pixie.runner", "pixie.batch"),
    ("pixie.api", "pixie.demo"),
    ("pixie.cli",),
]

# Third-party packages that may be imported inside functions: optional extras or heavy imports that only
# some code paths need.
LAZY_THIRD_PARTY = {
    "kornia",  # matching backends: a heavy import; a kornia without a network only disables that backend
    "poselib",  # pose.solver=poselib (PoseLib is optional for a source checkout)
    "matplotlib",  # report histograms only
    "manifold3d",  # synth extra: boolean mesh operations of the procedural parts
    "tqdm",  # progress bars of the command line only
    "trimesh",  # mesh file loading and repair: a slow import (~1 s) that inference from a stored set skips
    "scipy",  # KD-trees (ADD-S, mesh sampling) only
    "embreex",  # the ray tracer: imported when a renderer is built
    "torch",  # pixie.weights reads checkpoints with torch, but resolving a weight path must not import it
    "multiprocessing",  # reference rendering with workers > 1 only
    "concurrent",
    "ray",  # the `ray` extra: --ray runs only
}

MAX_LINES = 500


def _module_name(path: Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(SRC.rglob("*.py"))}


MODULES = _modules()


def _resolve(name: str) -> str:
    """The module an imported dotted name refers to (``pixie.eval.errors.add`` -> ``pixie.eval.errors``)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name


def _imports(path: Path) -> tuple[list[tuple[str, int]], list[tuple[str, int]]]:
    """(pixie modules imported at module level, (top-level package, line) of imports inside functions)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    top, local = [], []

    def names(node) -> list[str]:
        if isinstance(node, ast.Import):
            return [a.name for a in node.names]
        if node.level:  # relative import
            base = _module_name(path).split(".")
            base = base[: len(base) - node.level + (1 if path.name == "__init__.py" else 0)]
            mod = ".".join(base + ([node.module] if node.module else []))
        else:
            mod = node.module or ""
        return [f"{mod}.{a.name}" for a in node.names] if mod.startswith("pixie") else [mod]

    def visit(node, in_function: bool, type_checking: bool = False) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                continue  # annotations only
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                for n in names(child):
                    if in_function:
                        local.append((n, child.lineno))
                    elif n.startswith("pixie"):
                        top.append((_resolve(n), child.lineno))
            visit(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    visit(tree, False)
    return top, local


def _layer(mod: str) -> int:
    for i, group in enumerate(LAYERS):
        if any(mod == g or mod.startswith(g + ".") for g in group):
            return i
    raise AssertionError(f"{mod} is in no layer: add it to LAYERS (and to ARCHITECTURE.md)")


def _graph() -> dict[str, set[str]]:
    return {m: {t for t, _ in _imports(p)[0] if t != m and t != "pixie"} | (
        {"pixie"} if any(t == "pixie" for t, _ in _imports(p)[0]) else set()) for m, p in MODULES.items()}


def test_every_module_has_a_layer():
    for m in MODULES:
        if m != "pixie":
            _layer(m)


def test_no_upward_imports():
    bad = []
    for m, p in MODULES.items():
        if m == "pixie":
            continue  # the public facade
        for target, line in _imports(p)[0]:
            if target == "pixie":
                bad.append(f"{p.relative_to(SRC.parent)}:{line} imports the package root (import the module instead)")
            elif _layer(target) > _layer(m):
                bad.append(f"{p.relative_to(SRC.parent)}:{line} {m} (layer {_layer(m)}) imports {target} "
                           f"(layer {_layer(target)})")
    assert not bad, "upward imports:\n" + "\n".join(bad)


def test_import_graph_has_no_cycle():
    graph = _graph()
    state: dict[str, int] = {}
    cycles = []

    def dfs(node: str, stack: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                cycles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]) if nxt in stack else f"{node}->{nxt}")
            elif nxt not in state:
                dfs(nxt, stack + [nxt])
        state[node] = 2

    for m in sorted(graph):
        if m not in state:
            dfs(m, [m])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_cycle_check_finds_a_cycle(monkeypatch):
    """The checker itself: a two-module loop is reported."""
    fake = {"a": {"b"}, "b": {"a"}}
    monkeypatch.setattr(__import__(__name__), "_graph", lambda: fake)
    with pytest.raises(AssertionError, match="a -> b -> a"):
        test_import_graph_has_no_cycle()


def test_function_local_imports_only_for_optional_heavy_packages():
    bad = []
    for m, p in MODULES.items():
        for name, line in _imports(p)[1]:
            if name.split(".")[0] not in LAZY_THIRD_PARTY:
                bad.append(f"{p.relative_to(SRC.parent)}:{line} imports {name} inside a function")
    assert not bad, "function-local imports (move them to the top of the module):\n" + "\n".join(bad)


def test_module_size():
    long = []
    for m, p in MODULES.items():
        n = len(p.read_text(encoding="utf-8").splitlines())
        doc = ast.get_docstring(ast.parse(p.read_text(encoding="utf-8"))) or ""
        if n > MAX_LINES and "longer than" not in doc.lower():
            long.append(f"{p.relative_to(SRC.parent)}: {n} lines and no reason in its docstring")
    assert not long, "\n".join(long)


def test_public_api():
    import pixie

    for name in ("load_mesh", "build_reference_set", "load_reference_set", "PoseEstimator", "PixieConfig",
                 "load_image", "PixieError", "estimate_pose"):
        assert name in pixie.__all__ and hasattr(pixie, name), name
