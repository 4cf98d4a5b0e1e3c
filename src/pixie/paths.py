"""Output paths checked before any work starts, and files written atomically with normal permissions.

Outputs are written to exactly the name given: no suffix is ever added or changed. Every command checks its
outputs first (:func:`output_file`, :func:`output_dir`), so a bad path costs nothing; every regular file is
then written to a temporary name beside it and renamed into place (:func:`write_atomic`), so a crash never
leaves half a file and readers never see one. A path that exists and is not a regular file (``/dev/null``,
a FIFO, ``/dev/stdout``) is written into directly and never replaced.
"""

from __future__ import annotations

import io
import os
import tempfile
from pathlib import Path
from typing import IO, Callable

from pixie.errors import OutputError

__all__ = ["not_an_input", "output_dir", "output_file", "write_atomic"]


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


def _is_device(p: Path) -> bool:
    """True for an existing path that is neither a folder nor a regular file (a device, a pipe)."""
    return p.exists() and not p.is_file() and not p.is_dir()


def output_file(path: str | Path, force: bool = True, what: str = "output") -> Path:
    """The file an output will be written to, exactly as given, checked before any work is done.

    Parameters
    ----------
    path : str or Path
        As the user gave it; never renamed (``part_v1.2`` stays ``part_v1.2``).
    force : bool
        Allow replacing an existing regular file; False refuses it (the CLI's default, ``--force`` to
        replace). A device or pipe (``/dev/null``) is written into, not replaced, so it needs no ``force``.
    what : str
        What the file is, for messages.

    Raises
    ------
    OutputError
        The path is a folder, exists (without ``force``), or its folder cannot be created or written.
    """
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{what} {p} is a folder; give a file name")
    if _is_device(p):
        return p
    if p.exists() and not force:
        raise OutputError(f"{what} {p} exists; pass --force to replace it")
    output_dir(p.parent, what="output folder")
    return p


def not_an_input(outputs: list, inputs: list) -> None:
    """Refuse an output path that is one of the command's inputs (``--force`` would overwrite the photo).

    Raises
    ------
    OutputError
        An entry of ``outputs`` (None entries are skipped) resolves to the same file as one of ``inputs``.
    """
    ins = {Path(p).resolve() for p in inputs if p}
    for o in outputs:
        if o is not None and Path(o).resolve() in ins:
            raise OutputError(f"output {o} is also an input of this command")


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
    """Write a file at exactly ``path``, atomically (temporary file beside it, fsync, rename), mode 0666 & ~umask.

    Parameters
    ----------
    path : str or Path
        The final name (never changed); replaced in one step if it exists. Its folder is created. A device
        or pipe is written into directly.
    write : callable(file object) or bytes or str
        Writes the content to a binary file object, or the content itself (str is UTF-8 encoded).

    Raises
    ------
    OutputError
        ``path`` is a folder or its folder cannot be created or written.
    """
    path = output_file(path)

    def _write(fh: IO[bytes]) -> None:
        if callable(write):
            write(fh)
        else:
            fh.write(write.encode("utf-8") if isinstance(write, str) else write)

    if _is_device(path):
        buf = io.BytesIO()  # writers may seek (zip files); devices and pipes cannot
        _write(buf)
        with open(path, "wb") as fh:
            fh.write(buf.getvalue())
        return path
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            _write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
