"""Writing output files: exactly at the path given, whole or not at all.

A regular file is written to a temporary file beside it and renamed over it (a killed write leaves the old
file or nothing, never half a file). A path that exists and is not a regular file (``/dev/null``, a FIFO,
``/dev/stdout``) is written into directly and never replaced. No suffix is ever added or changed.
"""

from __future__ import annotations

import io
import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

from pixie.errors import PixieError

__all__ = ["check_output", "write_atomic", "write_with"]


def check_output(path: str | os.PathLike[str], error: type[PixieError] = PixieError) -> Path:
    """``path`` as given; its folder is created and must be writable; a folder is refused."""
    path = Path(path)
    if path.is_dir():
        raise error(f"output {path} is a folder")
    if path.exists() and not path.is_file():
        return path  # a device or pipe: written into directly
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise error(f"cannot create output folder {parent}: {exc}") from exc
    if not os.access(parent, os.W_OK):
        raise error(f"output folder {parent} is not writable")
    return path


def write_with(path: str | os.PathLike[str], writer: Callable[[BinaryIO], None],
               error: type[PixieError] = PixieError) -> Path:
    """Call ``writer(binary_file)`` to write ``path`` atomically (or directly into a non-regular file)."""
    path = check_output(path, error)
    if path.exists() and not path.is_file():
        buf = io.BytesIO()  # writers may seek (zip files); devices and pipes cannot
        writer(buf)
        with open(path, "wb") as fh:
            fh.write(buf.getvalue())
        return path
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            writer(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_atomic(path: str | os.PathLike[str], data: bytes | str, error: type[PixieError] = PixieError) -> Path:
    """Write ``data`` (str as UTF-8) to ``path`` atomically; see :func:`write_with`."""
    blob = data.encode("utf-8") if isinstance(data, str) else data
    return write_with(path, lambda fh: fh.write(blob), error)
