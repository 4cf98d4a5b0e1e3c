"""One assembly in several photos: the part report judged over all of them (``pixie inspect --batch`` with an
``assembly`` column or ``--one-assembly``).

One photo's evidence about a part is noisy: the part is half hidden, painted like what is behind it, or one of its
edges falls on clutter. A defect is there in every photo of the assembly; one photo's noise is not. So each part's
score (:func:`pixie.cues.parts.part_score`, as one photo's report computes it) is averaged over the photos that see
it, and the part is flagged when the mean is below ``config.parts.flag_below``, the threshold of one photo's report.

>>> reports = [judge_parts(part_support(...), **judge_kw) for each photo]
>>> parts = combine_views(reports, **judge_kw)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pixie.config import PartsConfig
from pixie.cues.parts import PartSupport, only_resizes, part_score, photo_medians
from pixie.pose.results import SUSPECT_VERDICTS

__all__ = ["AssemblyPart", "views_kwargs", "part_scores", "trusted_views", "mean_gain", "mean_spill", "combine_views"]


def views_kwargs(pc: PartsConfig) -> dict:
    """:func:`combine_views`' keywords that ``config.parts`` sets (with ``report_kwargs(pc)[1]``, the judge's)."""
    return dict(views_move_gain=pc.views_move_gain if pc.moves or pc.evidence else float("inf"),
                views_resize_gain=pc.views_resize_gain if pc.resizes or pc.evidence else float("inf"),
                views_resize_same=pc.views_resize_same, views_resize_factors=tuple(pc.views_resize_factors),
                views_spill=pc.views_spill if pc.spill else float("inf"), spill_cap=pc.spill_cap)


def part_scores(parts: list[PartSupport], *, flag_below: float = 0.6, colour_weight: float = 0.0,
                revealed_weight: float = 0.0, shift_weight: float = 0.0, supported_above: float = 1.0,
                min_points: int = 12, min_visible: float = 0.2, **_) -> list[float | None]:
    """Each part's :func:`part_score` in one photo as :func:`judge_parts` uses it (same keywords; the others are
    ignored): None for a part it would judge ``not visible``, and at least ``flag_below`` for a part whose relative
    edge support is at least ``supported_above`` (a view that would never flag it)."""
    med, med_colour = photo_medians(parts, min_points, min_visible)
    out: list[float | None] = []
    for p in parts:
        if p.n_points < min_points or p.visible < min_visible or med <= 0:
            out.append(None)
            continue
        s = part_score(p, colour_weight, med_colour, revealed_weight, med, min_points, shift_weight)
        out.append(max(s, flag_below) if p.support / med >= supported_above else s)
    return out


@dataclass(kw_only=True)
class AssemblyPart:
    """One part's verdict over several photos of one assembly (:func:`combine_views`)."""

    index: int
    name: str
    verdict: str  # as a part's in one photo: present / missing / displaced / wrong / not visible
    score: float  # the mean of its scores over the photos that judge it (nan when none does)
    n_views: int  # the photos that judge it (it is visible enough in them)
    view_verdicts: list[str]  # its verdict in each photo, in the order given
    move_gain: float = 0.0  # the mean over those photos of its best 3D move's gain (0 where none was tried)
    move: str = ""  # the move of the photo where it gained most ('' when none was tried)
    size_gain: float = 0.0  # the same for its best resize
    size: str = ""
    spill: float = float("nan")  # the mean over the photos that measure it of its paint spill (capped), NaN: none

    def as_dict(self) -> dict:
        return {"index": self.index, "name": self.name, "verdict": self.verdict,
                "score": None if not np.isfinite(self.score) else round(self.score, 4), "n_views": self.n_views,
                "view_verdicts": list(self.view_verdicts), "move_gain": round(self.move_gain, 4), "move": self.move,
                "size_gain": round(self.size_gain, 4), "size": self.size,
                "paint_spill": round(self.spill, 4) if np.isfinite(self.spill) else None}


def trusted_views(fits: list[float | None], min_fit: float) -> list[int]:
    """The photos of an assembly whose verdicts count (indices into ``fits``): those whose pose's aligned fit
    (``fits``, the results' ``fit``; None: not scored, kept) is at least ``min_fit``; every photo when none is (the
    assembly is then judged on what there is)."""
    keep = [i for i, f in enumerate(fits) if f is None or not np.isfinite(f) or f >= min_fit]
    return keep or list(range(len(fits)))


def mean_gain(seen: list[PartSupport], what: str, same_hypothesis: bool = False,
              factors=None) -> tuple[float, str]:
    """One part's 3D-move (``what`` 'move') or resize ('size') evidence over the photos that judge it (``seen``): the
    mean gain and the move in words.

    ``same_hypothesis`` False: each photo's best move, averaged (0 where none was tried); the move named is that of
    the photo where it gained most. True: each move's own gain averaged over the photos (0 in a photo where it was
    not judged: it changed nothing in view), and the best such mean: one physical change that every photo must
    support, where the best of each photo may be a different change (photos whose records keep no per-move gains
    count with their best move under its name). ``factors`` (resizes only): only the resizes by these length factors
    count, in records that keep every resize's gain (:func:`pixie.cues.parts.only_resizes`; None: all).
    """
    if factors is not None and what == "size":
        seen = [only_resizes(p, factors) for p in seen]
    named = [(getattr(p, what), getattr(p, f"{what}_gain")) for p in seen]  # each photo's best: (name, gain)
    if not same_hypothesis:
        top = max(named, key=lambda ng: ng[1] if ng[0] else -np.inf)[0]
        return float(np.mean([g if n else 0.0 for n, g in named])), top
    per = [getattr(p, f"{what}_gains") or ({n: g} if n else {}) for p, (n, g) in zip(seen, named)]
    names = sorted({n for g in per for n in g})
    if not names:
        return 0.0, ""
    means = [float(np.mean([g.get(n, 0.0) for g in per])) for n in names]
    i = int(np.argmax(means))
    return means[i], names[i]


def mean_spill(reports: list[list[PartSupport]], k: int, cap: float = 0.5) -> float:
    """Part ``k``'s paint spill (:func:`pixie.cues.part_paint.paint_spill`) over the photos that measure it, each
    photo's capped at ``cap`` (one photo, e.g. at a slightly wrong pose, cannot flag a part alone when another photo
    sees it), averaged; NaN when no photo measures it."""
    vals = [min(r[k].spill, cap) for r in reports if np.isfinite(r[k].spill)]
    return float(np.mean(vals)) if vals else float("nan")


def combine_views(reports: list[list[PartSupport]], *, views_move_gain: float = float("inf"),
                  views_resize_gain: float = float("inf"), views_resize_same: bool = False, views_resize_factors=None,
                  views_spill: float = float("inf"), spill_cap: float = 0.5, **judge_kw) -> list[AssemblyPart]:
    """The part report of one assembly seen in several photos: each part's :func:`part_scores` averaged over the
    photos that judge it, flagged when the mean is below ``flag_below`` (``judge_kw``: :func:`judge_parts`'s keywords,
    ``report_kwargs(config.parts)[1]``).

    With the 3D-move / resize evidence in the records (``config.parts.moves`` / ``resizes`` / ``evidence``), a part
    whose best resize gains on average (over the photos that judge it, 0 where none was tried) at least
    ``views_resize_gain`` is ``wrong``, else one whose best move gains on average at least ``views_move_gain`` is
    ``displaced`` (``config.parts.views_resize_gain`` / ``views_move_gain``): a brick one stud off or a part of another
    size keeps most of its contour supported in every photo, and only the moved or resized part's contour tells.
    Only the resizes by ``views_resize_factors`` count (None: every one recorded); with ``views_resize_same`` one
    resize's gain is averaged over the photos (the same physical change), else each photo's best.

    One photo's evidence about a part is noisy: it is half hidden, painted like what is behind it, or one of its
    edges falls on clutter. Over photos from other viewpoints the noise averages out and a defect, which is there
    in every photo, does not. A flagged part takes the kind (missing / displaced / wrong) that most of the photos
    that flag it give, ties to the photo with the lowest score; 'missing' when no single photo flags it. A part no
    photo judges is 'not visible'. ``reports``: each photo's :func:`part_support` records of the same mesh (verdicts
    as :func:`judge_parts` set them, or unset).

    A part still 'present' whose paint spill (:func:`mean_spill`, each photo's capped at ``spill_cap``; over every
    photo given that measures it) is at least ``views_spill`` is ``wrong``: a larger part than the CAD's keeps the
    CAD part's contour and shows its paint around it.
    """
    if not reports:
        return []
    n = len(reports[0])
    if any(len(r) != n for r in reports):
        raise ValueError("combine_views: every photo's report must list the same parts")
    flag_below = judge_kw.get("flag_below", 0.6)
    scores = [part_scores(r, **judge_kw) for r in reports]
    out = []
    for k in range(n):
        judged = [(s[k], r[k]) for s, r in zip(scores, reports) if s[k] is not None]  # the photos that judge it
        views = [r[k].verdict for r in reports]
        spill = mean_spill(reports, k, spill_cap)
        if not judged:
            out.append(AssemblyPart(index=k, name=reports[0][k].name, verdict="not visible", score=float("nan"),
                                    n_views=0, view_verdicts=views, spill=spill))
            continue
        mean = float(np.mean([s for s, _ in judged]))
        seen = [p for _, p in judged]
        move_gain, move = mean_gain(seen, "move", same_hypothesis=False)
        size_gain, size = mean_gain(seen, "size", same_hypothesis=views_resize_same, factors=views_resize_factors)
        verdict = "present"
        if size_gain >= views_resize_gain:
            verdict = "wrong"
        elif move_gain >= views_move_gain:
            verdict = "displaced"
        elif mean < flag_below:
            by_score = [p.verdict for _, p in sorted(judged, key=lambda sp: (sp[0], sp[1].verdict))]
            kinds = [v for v in by_score if v in SUSPECT_VERDICTS]
            verdict = max(kinds, key=lambda v: (kinds.count(v), -kinds.index(v))) if kinds else "missing"
        if verdict == "present" and np.isfinite(spill) and spill >= views_spill:
            verdict = "wrong"
        out.append(AssemblyPart(index=k, name=reports[0][k].name, verdict=verdict, score=mean, n_views=len(judged),
                                view_verdicts=views, move_gain=move_gain, move=move,
                                size_gain=size_gain, size=size, spill=spill))
    return out
