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

from pixie.cues.parts import PartSupport, part_score, photo_medians
from pixie.pose.results import SUSPECT_VERDICTS

__all__ = ["AssemblyPart", "part_scores", "combine_views"]


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

    def as_dict(self) -> dict:
        return {"index": self.index, "name": self.name, "verdict": self.verdict,
                "score": None if not np.isfinite(self.score) else round(self.score, 4), "n_views": self.n_views,
                "view_verdicts": list(self.view_verdicts)}


def combine_views(reports: list[list[PartSupport]], **judge_kw) -> list[AssemblyPart]:
    """The part report of one assembly seen in several photos: each part's :func:`part_scores` averaged over the
    photos that judge it, flagged when the mean is below ``flag_below`` (``judge_kw``: :func:`judge_parts`'s keywords,
    ``report_kwargs(config.parts)[1]``).

    One photo's evidence about a part is noisy: it is half hidden, painted like what is behind it, or one of its
    edges falls on clutter. Over photos from other viewpoints the noise averages out and a defect, which is there
    in every photo, does not. A flagged part takes the kind (missing / displaced / wrong) that most of the photos
    that flag it give, ties to the photo with the lowest score; 'missing' when no single photo flags it. A part no
    photo judges is 'not visible'. ``reports``: each photo's :func:`part_support` records of the same mesh (verdicts
    as :func:`judge_parts` set them, or unset). The verdict rests on the score: the 3D-move and resize evidence
    (off by default) only names the kind, through the photos' verdicts.
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
        mine = [(s[k], r[k].verdict) for s, r in zip(scores, reports) if s[k] is not None]
        views = [r[k].verdict for r in reports]
        if not mine:
            out.append(AssemblyPart(index=k, name=reports[0][k].name, verdict="not visible", score=float("nan"),
                                    n_views=0, view_verdicts=views))
            continue
        mean = float(np.mean([s for s, _ in mine]))
        verdict = "present"
        if mean < flag_below:
            kinds = [v for _, v in sorted(mine) if v in SUSPECT_VERDICTS]
            verdict = max(kinds, key=lambda v: (kinds.count(v), -kinds.index(v))) if kinds else "missing"
        out.append(AssemblyPart(index=k, name=reports[0][k].name, verdict=verdict, score=mean, n_views=len(mine),
                                view_verdicts=views))
    return out
