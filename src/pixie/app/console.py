"""What the ``pixie`` command prints besides results: progress bars (closed before an interruption is reported),
the mesh's units line, and warnings as single ``pixie: warning: ...`` lines on stderr.
"""

from __future__ import annotations

import sys
import warnings

from pixie.app.signals import TERM, Terminated
from pixie.geometry.mesh import load_mesh, units_note

__all__ = ["close_bars", "load_mesh_announced", "say_warning", "show_warning", "tqdm_progress"]


def say_warning(message: str) -> None:
    """One ``pixie: warning: ...`` line on stderr."""
    print(f"pixie: warning: {message}", file=sys.stderr, flush=True)


def show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` of the command line: one line each, without the source line."""
    say_warning(str(message))


def load_mesh_announced(path: str, units: str):
    """load_mesh, announcing the units in one line; a size warning is raised again after that line (the command's
    warning collector, :func:`pixie.app.notes.collect_warnings`, or :func:`show_warning` prints it). With
    ``--units auto`` (the user named no units) a size implausible even after auto-detection is an error."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = load_mesh(path, units=units, implausible="error" if units == "auto" else "warn")
    print(units_note(mesh))
    for w in caught:
        warnings.warn(str(w.message), UserWarning, stacklevel=2)
    return mesh


OPEN_BARS: list = []  # progress bars still drawing, closed before an interruption is reported


def close_bars() -> None:
    """Close the open progress bars, so that a message printed next stands on its own line."""
    while OPEN_BARS:
        OPEN_BARS.pop().close()


def tqdm_progress(total_label: str):
    from tqdm import tqdm

    bar = {"b": None}

    def cb(done: int, total: int) -> None:
        if TERM:
            raise Terminated()
        if bar["b"] is None:
            bar["b"] = tqdm(total=total, unit=total_label, dynamic_ncols=True)
            OPEN_BARS.append(bar["b"])
        bar["b"].update(done - bar["b"].n)
        if done >= total:
            bar["b"].close()
            OPEN_BARS.remove(bar["b"])

    return cb


