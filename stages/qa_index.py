"""Stage ``qa_index`` (per session): the page a reviewer opens first.

Reads every sequence's ``qa`` artifact through ``artifacts.QAResult`` and writes

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


def rows_of(results: dict) -> list[dict]:
    """One row per sequence from its ``artifacts.QAResult`` (the thumbnail: its first span's
    overlay, else its plot; the files the QA result lists, checked on load)."""
    rows = []
    for unit, qa in results.items():
        s = qa.summary
        thumb = qa.files.thumbnail()
        rows.append({"sequence": unit,
                     "href": rel_href(unit, "qa", qa.files.report or "report.html"),
                     "frames": s.frames, "flagged": s.flagged_frames, "spans": s.spans,
                     "reasons": dict(s.per_reason), "not_valid": int(sum(s.not_valid.values())),
                     "thumbnail": None if thumb is None else rel_href(unit, "qa", thumb),
                     "status": "flagged" if s.flagged_frames else "ok",
                     "sync_offset_frames": s.out_of_sync})
    return rows


def run(ctx: StageContext) -> None:
    from artifacts import QAResult
    from qa.report import IndexRow, write_index

    rows = rows_of({u: QAResult.load(a) for u, a in ctx.inputs["qa"].items()})
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
