"""User-facing warnings, collected in one place so that each one reaches the console and the result JSON alike.

Library code says something unusual with ``warnings.warn`` (EXIF orientation, CUDA asked for but absent,
intrinsics unusual for the image) or lists it in :attr:`pixie.pose.results.PoseResult.warnings` (a pose that its
inputs make doubtful). :func:`collect_warnings` records the first kind while an operation runs, optionally
echoing each once (the command line prints ``pixie: warning: ...``); :meth:`Notes.merge` joins both kinds,
without repeats, for the result's ``warnings``. :func:`settings_warnings` says where a reference set makes the
estimator run with other settings than the ones asked for (and what it runs with).
"""

from __future__ import annotations

import contextlib
import warnings
from typing import Callable, Iterator

__all__ = ["Notes", "collect_warnings", "settings_warnings", "effective_settings"]


class Notes:
    """Distinct warning messages in the order they came; ``echo`` (if any) is called once per new message."""

    def __init__(self, echo: Callable[[str], None] | None = None):
        self.items: list[str] = []
        self.echo = echo

    def add(self, message: str) -> None:
        message = str(message)
        if message not in self.items:
            self.items.append(message)
            if self.echo is not None:
                self.echo(message)

    def extend(self, messages) -> "Notes":
        for m in messages or ():
            self.add(m)
        return self

    def merge(self, messages) -> list[str]:
        """These notes followed by ``messages`` (a result's own warnings), each once; ``messages`` are echoed too."""
        self.extend(messages)
        return list(self.items)


@contextlib.contextmanager
def collect_warnings(echo: Callable[[str], None] | None = None) -> Iterator[Notes]:
    """Record every ``UserWarning`` raised inside the block as a :class:`Notes` entry (others pass through)."""
    notes = Notes(echo)
    with warnings.catch_warnings():
        warnings.simplefilter("always", UserWarning)
        previous = warnings.showwarning

        def show(message, category, filename, lineno, file=None, line=None) -> None:
            if issubclass(category, UserWarning):
                notes.add(str(message))
            else:
                previous(message, category, filename, lineno, file, line)

        warnings.showwarning = show
        yield notes


def effective_settings(est) -> dict:
    """What a :class:`~pixie.pipeline.estimator.PoseEstimator` really runs with where its reference set decides:
    the encodings matched, the in-plane mode, the matcher, and the set's views, rolls and size."""
    refs = est.refs
    return {"encodings": list(est.encodings), "match.in_plane": est.cfg.match.in_plane, "match.matcher": est.matcher.name,
            "refs.views": int(refs.n_views), "refs.rotations": int(refs.n_rolls), "refs.size": int(refs.size)}


def settings_warnings(est, asked) -> list[str]:
    """Where the estimator ``est`` runs with other query settings than the config ``asked`` names (its preset or
    overrides) because its reference set was built otherwise (encodings, in-plane mode): one sentence each. The
    set's own views, rolls and size are its to choose (recorded by :func:`effective_settings`, not warned about)."""
    eff, out = effective_settings(est), []
    refs_cfg = est.refs.config
    name = f"preset {asked.preset}" if asked.preset else "the config"
    if list(asked.refs.encodings) != eff["encodings"]:
        out.append(f"{name} asks for encodings {list(asked.refs.encodings)}, but the reference set holds "
                   f"{list(refs_cfg.encodings)}: matching {eff['encodings']} (rebuild the set with this preset to use them)")
    if asked.match.in_plane != eff["match.in_plane"]:
        out.append(f"{name} asks for match.in_plane={asked.match.in_plane}, but the reference set holds features of "
                   f"roll 0 only: running match.in_plane={eff['match.in_plane']}")
    return out


def annotate(res, est, asked, notes: Notes | None = None):
    """Give a :class:`~pixie.pose.results.PoseResult` of ``est`` its ``settings`` (:func:`effective_settings`) and
    every warning once: ``notes`` collected meanwhile, :func:`settings_warnings` against ``asked``, its own."""
    res.settings = effective_settings(est)
    res.warnings = (notes or Notes()).merge([*settings_warnings(est, asked), *res.warnings])
    return res
