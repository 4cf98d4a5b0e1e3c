"""Output paths checked before any work starts, and files written atomically with normal permissions.

Outputs are written to exactly the name given: no suffix is ever added or changed. Every command checks its
outputs first (:func:`output_file`, :func:`output_dir`), so a bad path costs nothing; every regular file is
then written to a temporary name beside it and renamed into place (:func:`write_atomic`), so a crash never
leaves half a file and readers never see one. A path that exists and is not a regular file (``/dev/null``,
a FIFO, ``/dev/stdout``) is written into directly and never replaced.

Without ``force`` the final step is a hard link of the temporary file to the name, which fails atomically when
another process wrote that name meanwhile (two ``refs build -o same.npz`` at once: the second one refuses);
with ``force`` the last writer wins, and both writes are complete. Temporary names are ``.<name>.<pid>.<random>.tmp``:
one left by a killed process (SIGKILL runs no clean-up) is removed by the next write, load or run in that folder
once its process is gone (:func:`remove_stale_temps`). :func:`not_an_input` refuses an output that is one of the
command's inputs (the same file, also through a link, or the same folder), ``--force`` or not.
"""

from __future__ import annotations

import errno
import io
import os
import re
import tempfile
from pathlib import Path
from typing import IO, Callable

from pixie.errors import OutputError

__all__ = ["not_an_input", "output_dir", "output_file", "pid_alive", "remove_stale_temps", "write_atomic"]


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


def _same(a: Path, b: Path) -> bool:
    """The same file or folder: equal resolved paths, or (both existing) the same inode (a hard link)."""
    if a.resolve() == b.resolve():
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def not_an_input(outputs: list, inputs: list) -> None:
    """Refuse an output path that is one of the command's inputs (``--force`` would overwrite the photo).

    Parameters
    ----------
    outputs : list of paths (None entries are skipped)
        Every file the command writes, and every folder it writes into.
    inputs : list of paths (None entries are skipped)
        Every file or folder the command reads.

    Raises
    ------
    OutputError
        An output is the same file as an input (also through a symbolic or hard link), or the same folder.
        Devices and pipes (``/dev/null``) are never refused.
    """
    ins = [Path(p) for p in inputs if p]
    for o in outputs:
        if o is None or _is_device(Path(o)):
            continue
        for i in ins:
            if not _is_device(i) and _same(Path(o), i):
                what = "folder" if Path(o).is_dir() else "file"
                raise OutputError(f"output {o} is also an input of this command ({what} {i}): give another output")


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


_TEMP = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.[A-Za-z0-9_]+\.tmp$")


def pid_alive(pid: int) -> bool:
    """True when a process ``pid`` exists on this machine (one of another user's counts too)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    try:  # a zombie (killed, not yet reaped) is gone for our purposes
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def remove_stale_temps(folder: str | Path) -> list[Path]:
    """Remove the temporary files (``.<name>.<pid>.<random>.tmp``) that killed writers left in ``folder``.

    Only names of this module's pattern whose process no longer runs are removed; a live writer's file is kept.
    Returns the removed paths (errors are ignored: a folder we cannot list has nothing of ours).
    """
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for e in entries:
        m = _TEMP.match(e.name)
        if m and e.is_file(follow_symlinks=False) and not pid_alive(int(m["pid"])):
            try:
                os.unlink(e.path)
                removed.append(Path(e.path))
            except OSError:
                pass
    return removed


def temp_path(path: Path) -> tuple[int, str]:
    """A new temporary file beside ``path`` named ``.<name>.<pid>.<random>.tmp`` (mode 0600): (fd, name)."""
    return tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp", dir=path.parent)


def _publish(tmp: str, path: Path, force: bool) -> None:
    """Put the finished ``tmp`` at ``path``: replaced with ``force``, else linked (fails if ``path`` appeared)."""
    if force:
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise OutputError(f"{path} exists (written by another process meanwhile); pass --force to replace it") from None
    except OSError as exc:  # a file system without hard links: an exclusive create, then the replace
        if exc.errno not in (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EXDEV, errno.EMLINK, errno.ENOSYS):
            raise
        try:
            os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))
        except FileExistsError:
            raise OutputError(f"{path} exists (written by another process meanwhile); pass --force to replace "
                              "it") from None
        os.replace(tmp, path)
        return
    os.unlink(tmp)


def write_atomic(path: str | Path, write: Callable[[IO[bytes]], None] | bytes | str, force: bool = True) -> Path:
    """Write a file at exactly ``path``, atomically (temporary file beside it, fsync, rename), mode 0666 & ~umask.

    Parameters
    ----------
    path : str or Path
        The final name (never changed); replaced in one step if it exists. Its folder is created. A device
        or pipe is written into directly.
    write : callable(file object) or bytes or str
        Writes the content to a binary file object, or the content itself (str is UTF-8 encoded).
    force : bool
        Replace an existing file (default). False refuses one, also one that another process wrote while
        this one was writing (the check is atomic: a hard link, not a test before the rename).

    Raises
    ------
    OutputError
        ``path`` is a folder, its folder cannot be created or written, or (without ``force``) it exists.
    """
    path = output_file(path, force=force)

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
    remove_stale_temps(path.parent)
    fd, tmp = temp_path(path)
    try:
        with os.fdopen(fd, "wb") as fh:
            _write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600
        _publish(tmp, path, force)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
