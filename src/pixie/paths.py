"""Output paths checked before any work starts, and files written atomically with normal permissions.

Every command checks its outputs first (:func:`output_file`, :func:`output_dir`), so a bad path costs
nothing; every file is then written to a temporary name beside it and renamed into place
(:func:`write_atomic`), so a crash never leaves half a file and readers never see one.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Callable, IO

from pixie.errors import OutputError


def _umask() -> int:
    """The process umask, read without changing it where the OS allows (Linux), else set and restored."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def output_file(path: str | Path, suffix: str | None = None, force: bool = True, what: str = "output") -> Path:
    """The file an output will be written to, checked before any work is done.

    Parameters
    ----------
    path : str or Path
        As the user gave it.
    suffix : str, optional
        Required extension (``'.npz'``): appended when missing (``part_v1.2`` -> ``part_v1.2.npz``),
        never substituted for another one.
    force : bool
        Allow replacing an existing file; False refuses it (the CLI's default, ``--force`` to replace).
    what : str
        What the file is, for messages.

    Raises
    ------
    OutputError
        The path is a folder or not a regular file (``/dev/null``), exists (without ``force``), or its
        folder cannot be created or written.
    """
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{what} {p} is a folder; give a file name")
    if p.exists() and not p.is_file():
        raise OutputError(f"{what} {p} is not a regular file")
    if suffix and p.suffix.lower() != suffix.lower():
        p = p.with_name(p.name + suffix)
        if p.is_dir():
            raise OutputError(f"{what} {p} is a folder; give a file name")
        if p.exists() and not p.is_file():
            raise OutputError(f"{what} {p} is not a regular file")
    if p.exists() and not force:
        raise OutputError(f"{what} {p} exists; pass --force to replace it")
    output_dir(p.parent, what=f"output folder")
    return p


def output_dir(path: str | Path, what: str = "output folder") -> Path:
    """Create (if needed) a folder that outputs go to and check that it is writable."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutputError(f"cannot create {what} {p}: it exists and is not a folder")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create {what} {p}: {exc.strerror or exc}") from exc
    if not os.access(p, os.W_OK | os.X_OK):
        raise OutputError(f"{what} {p} is not writable")
    return p


def write_atomic(path: str | Path, write: Callable[[IO[bytes]], None] | bytes | str) -> Path:
    """Write a file atomically (temporary file beside it, fsync, rename) with mode 0666 & ~umask (0644).

    Parameters
    ----------
    path : str or Path
        The final name; replaced in one step if it exists.
    write : callable(file object) or bytes or str
        Writes the content to a binary file object, or the content itself (str is UTF-8 encoded).
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            if callable(write):
                write(fh)
            else:
                fh.write(write.encode("utf-8") if isinstance(write, str) else write)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
