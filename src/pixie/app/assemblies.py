"""Assemblies in a batch: the photos of one physical assembly judged together (:mod:`pixie.cues.part_views`).

A batch row names its assembly in the manifest's ``assembly`` column (or a folder batch is one assembly with
``--one-assembly``); :func:`assembly_reports` combines the part reports of its photos, :func:`assembly_html` is the
batch page's table of them (assemblies with suspect parts first).
"""

from __future__ import annotations

import html

from pixie.config import PixieConfig
from pixie.cues.part_views import combine_views, trusted_views, views_kwargs
from pixie.cues.parts import PartSupport, report_kwargs
from pixie.pose.results import SUSPECT_VERDICTS

__all__ = ["ASSEMBLY_NOTE", "assembly_reports", "assembly_html"]


ASSEMBLY_NOTE = ("photos with the same 'assembly' judged together: each part's score (pixie.cues.parts.part_score, "
                 "as in one photo's report) averaged over the photos that see it (visible enough to judge), flagged "
                 "below config.parts.flag_below; move_gain = its best 3D move's gain averaged over them (0 where "
                 "none was tried), size_gain = the gain of one resize (views_resize_factors: a part shorter along "
                 "one axis) averaged over them: 'displaced' from config.parts.views_move_gain, 'wrong' from "
                 "views_resize_gain; paint_spill = its paint around it where the model shows another paint "
                 "(pixie.cues.part_paint), capped at config.parts.spill_cap per photo and averaged over the photos "
                 "that measure it: 'wrong' from views_spill; n_views = those photos, view_verdicts = its verdict in "
                 "each photo judged; "
                 "left_out = the photos whose pose's aligned fit is below config.parts.views_min_fit (a report at a "
                 "wrong pose is noise), not judged")


def assembly_reports(records: list[dict], config: PixieConfig) -> list[dict]:
    """One combined part report per assembly: the records (batch results) with the same ``assembly`` and object
    whose estimate has a part report, judged together (:func:`pixie.cues.part_views.combine_views` with
    ``config.parts``' thresholds); failed estimates are left out (their pose, and so their evidence, is not
    trusted). Assemblies with suspect parts come first."""
    groups: dict[tuple, list[dict]] = {}
    for r in records:
        res = r.get("result") or {}
        if r.get("assembly") and res.get("parts") and not res.get("failed"):
            groups.setdefault((r["assembly"], r.get("obj_id", 1), r.get("refs")), []).append(r)
    judge = report_kwargs(config.parts)[1]
    out = []
    for (name, obj_id, _), rs in groups.items():
        reports = [[PartSupport.from_dict(p) for p in r["result"]["parts"]] for r in rs]
        if len({len(x) for x in reports}) != 1:
            continue  # not the same parts: not one model (a changed reference set)
        keep = trusted_views([r["result"].get("fit") for r in rs], config.parts.views_min_fit)
        parts = combine_views([reports[i] for i in keep], **views_kwargs(config.parts), **judge)
        out.append({"assembly": name, "obj_id": obj_id, "n_photos": len(rs), "photos": [r["name"] for r in rs],
                    "left_out": [rs[i]["name"] for i in range(len(rs)) if i not in keep],
                    "rows": [r["row"] for r in rs],
                    "suspect": [p.name for p in parts if p.verdict in SUSPECT_VERDICTS],
                    "parts": [p.as_dict() for p in parts]})
    return sorted(out, key=lambda a: (-len(a["suspect"]), str(a["assembly"])))


def assembly_html(assemblies: list[dict]) -> str:
    """The page's table of assemblies judged over several photos (suspect first)."""
    if not assemblies:
        return ""
    rows = []
    for a in assemblies:
        sus = [p for p in a["parts"] if p["verdict"] in SUSPECT_VERDICTS]
        what = ("<b>suspect parts:</b> " + ", ".join(
            f"{html.escape(p['name'])} ({p['verdict']}, mean score {p['score']:.2f} over {p['n_views']} photos"
            + (f"; moved {html.escape(p['move'])}, mean gain {p['move_gain']:.2f}" if p["verdict"] == "displaced"
               and p.get("move") else "")
            + (f"; {html.escape(p['size'])}, mean gain {p['size_gain']:.2f}" if p["verdict"] == "wrong"
               and p.get("size") else "")
            + (f"; its paint shows around it (mean spill {p['paint_spill']:.2f})" if p["verdict"] == "wrong"
               and p.get("paint_spill") is not None else "") + ")"
            for p in sus)) if sus else "no suspect part"
        if a.get("left_out"):
            what += "<br>left out (pose not supported by the photo's edges): " + ", ".join(
                html.escape(n) for n in a["left_out"])
        hidden = [p["name"] for p in a["parts"] if p["verdict"] == "not visible"]
        if hidden:
            what += "<br>not visible in any photo: " + ", ".join(html.escape(h) for h in hidden)
        rows.append(f"<tr><td>{html.escape(str(a['assembly']))}</td><td>{a['n_photos']}</td><td>{what}</td>"
                    f"<td>{html.escape(', '.join(a['photos']))}</td></tr>")
    return ("<h2>Assemblies (their photos judged together)</h2><p>Each part's score is averaged over the photos that "
            "see it; a part is suspect when the mean is below the threshold of one photo's report.</p>"
            "<table><tr><th>assembly</th><th>photos</th><th>part report</th><th>which photos</th></tr>"
            + "\n".join(rows) + "</table><h2>Photos</h2>")
