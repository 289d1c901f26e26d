"""Stage ``qa_index`` (per session): the page a reviewer opens first.

Reads every sequence's ``qa`` artifact (its ``report.json``) and writes

- ``index.html`` (``qa.report.write_index``): the sequences sorted by their share of flagged
  frames, most first, each with its flagged frames, spans, reasons, frames not valid, a
  thumbnail (its first span's overlay, else its plot) and a link to its ``report.html``. The
  links are relative (``../../<group>/<action>/qa/report.html``): the store keeps every
  artifact at ``<outputs>/<session>/<unit>/<stage>/``, so the page opens from disk as long as
  the session folder stays together;
- ``summary.json``: the same rows, and the session's totals (frames, flagged frames, the
  flagged share, the sequences with a camera out of sync).
"""
from __future__ import annotations

from pathlib import Path

from pipeline.spec import Stage, StageContext

READS = ("session.name",)


def rel_href(unit: str, stage: str, file: str) -> str:
    """The relative path from ``<session>/session/qa_index/`` to
    ``<session>/<unit>/<stage>/<file>`` (``qa.report`` percent-encodes it in the page:
    sequence names have spaces)."""
    return "../../" + "/".join(unit.split("/") + [stage, file])


def rows_of(reports: dict[str, dict], exists) -> list[dict]:
    """One row per sequence from its qa ``report.json`` (``exists(unit, relpath)`` says whether
    a file of the unit's qa artifact is there, for the thumbnail)."""
    rows = []
    for unit, rep in reports.items():
        s = rep["summary"]
        thumb = None
        spans = rep.get("overlay_frames", {}).get("spans") or []
        for f in spans[:1]:
            if exists(unit, f"overlays/overlay_{int(f):06d}.png"):
                thumb = rel_href(unit, "qa", f"overlays/overlay_{int(f):06d}.png")
        if thumb is None and exists(unit, "qa.png"):
            thumb = rel_href(unit, "qa", "qa.png")
        rows.append({"sequence": unit, "href": rel_href(unit, "qa", "report.html"),
                     "frames": int(s["frames"]), "flagged": int(s["flagged"]),
                     "spans": int(s["spans"]), "reasons": dict(s.get("reasons", {})),
                     "not_valid": int(sum(s.get("not_valid", {}).values())),
                     "thumbnail": thumb, "status": "flagged" if s["flagged"] else "ok",
                     "sync_offset_frames": {c: v for c, v in
                                            (s.get("sync_offset_frames") or {}).items() if v}})
    return rows


def run(ctx: StageContext) -> None:
    from qa.report import IndexRow, write_index

    arts = ctx.inputs["qa"]
    reports = {u: a.json("report") for u, a in arts.items()}

    def exists(unit: str, rel: str) -> bool:
        return Path(arts[unit].path(rel)).exists()

    rows = rows_of(reports, exists)
    frames = sum(r["frames"] for r in rows)
    flagged = sum(r["flagged"] for r in rows)
    out_of_sync = {r["sequence"]: r["sync_offset_frames"] for r in rows if r["sync_offset_frames"]}
    notes = [f"{len(rows)} sequences, {flagged} of {frames} frames flagged "
             f"({100.0 * flagged / max(frames, 1):.1f} %)."]
    if out_of_sync:
        notes.append("Cameras out of sync: " + "; ".join(
            f"{u}: " + ", ".join(f"{c} {v:+d} frames" for c, v in d.items())
            for u, d in out_of_sync.items()))
    fields = ("sequence", "href", "frames", "flagged", "spans", "reasons", "not_valid",
              "thumbnail", "status")
    write_index(Path(ctx.out.path("index.html")),
                [IndexRow(**{k: r[k] for k in fields}) for r in rows],
                title=f"QA of session {ctx.recipe.session.name}", notes=notes)
    ctx.out.save_json("summary", {"session": ctx.recipe.session.name, "sequences": len(rows),
                                  "frames": frames, "flagged": flagged,
                                  "rate": flagged / max(frames, 1), "out_of_sync": out_of_sync,
                                  "rows": rows})
    ctx.log(f"QA index: {flagged}/{frames} frames flagged over {len(rows)} sequences")


STAGE = Stage(name="qa_index", func=run, per="session", upstream=("qa",), reads=READS,
              version="1",
              doc="the session's QA index page: sequences sorted by how much is flagged")
