"""Stage ``release`` (per session): the session's release folder, from every sequence's export.

Merges the files each ``export`` artifact lists (``artifacts.SequenceExport``) into one
CHI3D-layout tree (files copied; a path two exports both write is an error; each group's
``interaction_contact_signature.json`` and ``text_annotations.json`` merged by action), then
writes

- ``datasheet.json`` and ``datasheet.md``: subjects, sequences, frames per sequence, contact
  events, interaction classes (action names without the take number), which person-frames
  are not valid and why (counts per reason and person, and the frames as ranges; of them the
  person-frames withheld because their QA flags say the fit is wrong, ``qa:<reason>``, per
  sequence and in total: ``withheld``), the fitting
  figures per sequence (each export's ``artifacts.SequenceFigures``), and the QA summary (each
  sequence's ``artifacts.QAResult``: frames flagged, spans and reasons, cameras out of sync;
  :func:`qa_summary`);
- ``MANIFEST.sha256``: every file of the folder (``sha256sum -c MANIFEST.sha256`` passes in it);
- ``verification.json`` (``artifacts.Release``, which ``evaluate`` reads): the re-read pass
  (:func:`verify_release`): every file through its reader (``formats.chi3d``,
  ``formats.anny_json``, ``formats.release``, ``calib.io.read_chi3d_cameras``, the videos' frame count against their ``joints3d_25``), the
  persons and frames of an action's files agreeing, each copied file's hash equal to the
  export's, and the manifest verified. Any problem raises an InputError naming the file (the
  engine then leaves no artifact).
"""
from __future__ import annotations

import json
import re
import shutil
from collections import defaultdict
from pathlib import Path

import numpy as np

from pipeline.spec import Stage, StageContext

READS = ("session.name", "session.subjects", "session.sequences")

CONTACT_FILE = "interaction_contact_signature.json"
OWN = ("datasheet.json", "datasheet.md", "verification.json")


def interaction_class(action: str) -> str:
    """``"Grab 4"`` -> ``"Grab"`` (the action name without its take number)."""
    return re.sub(r"\s+\d+$", "", action).strip() or action


def frame_ranges(frames) -> list[list[int]]:
    """Increasing frame indices -> ``[[first, last], ...]`` runs of consecutive frames."""
    f = [int(x) for x in frames]
    out: list[list[int]] = []
    for x in f:
        if out and x == out[-1][1] + 1:
            out[-1][1] = x
        else:
            out.append([x, x])
    return out


# -------------------------------------------------------------------------------------- merge
def merge_exports(exports: dict, root: Path) -> dict[str, str]:
    """Copy every export's files (``{unit: artifacts.SequenceExport}``: the files it lists)
    into ``root``, merging the per-group contact and text files by action. Returns
    ``{relative path: sha256 of the source}`` of the copied files (the merged ones are written
    anew)."""
    from formats.chi3d import read_contact_signatures, write_contact_signatures
    from formats.errors import InputError
    from formats.release import read_text_annotations, sha256_file, write_text_annotations

    copied: dict[str, str] = {}
    origin: dict[str, str] = {}
    contact: dict[str, dict] = defaultdict(dict)
    text: dict[str, dict] = defaultdict(dict)
    for unit, exp in exports.items():
        group = exp.group
        merged = {exp.contact_file: CONTACT_FILE, exp.text_file: "text_annotations.json"}
        for rel in sorted(exp.files):
            src = exp.path(rel)
            if rel in merged:
                name = merged[rel]
                reader = read_contact_signatures if name == CONTACT_FILE else read_text_annotations
                into = contact if name == CONTACT_FILE else text
                for action, v in reader(src).items():
                    if action in into[group]:
                        raise InputError(src, action, f"action given by two exports "
                                         f"({origin.get(f'{group}/{name}:{action}')} and {unit})")
                    into[group][action] = v
                    origin[f"{group}/{name}:{action}"] = unit
                continue
            if rel in copied:
                raise InputError(src, "<path>", f"{rel} is written by two exports "
                                 f"({origin[rel]} and {unit})")
            dst = root / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
            copied[rel] = sha256_file(src)
            origin[rel] = unit
    for group, sigs in contact.items():
        write_contact_signatures(root / group / CONTACT_FILE, dict(sorted(sigs.items())))
    for group, t in text.items():
        write_text_annotations(root / group / "text_annotations.json", dict(sorted(t.items())))
    return copied


# ---------------------------------------------------------------------------------- datasheet
def qa_summary(results: dict) -> dict:
    """The release's QA summary from every sequence's ``artifacts.QAResult``: per sequence the
    frames flagged, their share, the spans (frames and reasons) and sequence-level findings
    (a camera out of sync), and the totals."""
    seqs = {}
    for unit, qa in sorted(results.items()):
        s = qa.summary
        seqs[unit] = {"frames": s.frames, "flagged": s.flagged_frames, "rate": s.flagged_rate,
                      "reasons": dict(s.per_reason),
                      "spans": [list(sp) for sp in qa.span_list()],
                      "sync_offset_frames": s.out_of_sync}
    frames = sum(v["frames"] for v in seqs.values())
    flagged = sum(v["flagged"] for v in seqs.values())
    return {"sequences": seqs, "frames": frames, "flagged": flagged,
            "rate": flagged / max(frames, 1),
            "what": "frames whose QA metrics (stage qa: marker residuals, reprojection, "
                    "interpenetration, ground, skating, contact, jerk, validity) pass a recipe "
                    "threshold; a flagged frame is the one to look at, and one flagged for a "
                    "reason that says the fit is wrong (stage export's withhold) is published not "
                    "valid (reason qa:<reason>)"}


def datasheet(session: str, subjects: list[str], sequences: dict, exports: dict,
              qa: dict | None = None) -> dict:
    """The datasheet as JSON (see the module doc) from the recipe's session view and each
    export (``{unit: artifacts.SequenceExport}``: its facts, figures and validity file);
    ``qa``: the :func:`qa_summary` (None: no QA ran)."""
    from formats.release import read_valid
    from formats.release import withheld_counts as read_withheld

    seqs: dict[str, dict] = {}
    classes: dict[str, list[str]] = defaultdict(list)
    by_reason: dict[str, int] = defaultdict(int)
    withheld: dict[str, int] = defaultdict(int)
    contact_events = 0
    for unit, exp in exports.items():
        group, action = exp.group, exp.action
        v = read_valid(exp.path(exp.valid_file))
        not_valid = {}
        for p, subj in enumerate(exp.persons):
            per: dict[str, list] = {}
            for r in sorted(set(v["reason"][p]) - {"fitted"}):
                per[r] = frame_ranges(v["frames"][v["reason"][p] == r])
                by_reason[r] += int((v["reason"][p] == r).sum())
            not_valid[subj] = per
        held = read_withheld(v["reason"])
        for r, n in held.items():
            withheld[r] += n
        # joints3d_25 joints of valid frames that no marker or view observed (joints_valid)
        jv = v.get("joints_valid")
        unobserved = {subj: 0 if jv is None else int((v["valid"][p][:, None] & ~jv[p]).sum())
                      for p, subj in enumerate(exp.persons)}
        c = exp.contact
        has_contact = bool(c is not None and c.event)
        contact_events += has_contact
        cls = interaction_class(action)
        classes[cls].append(unit)
        rec = sequences.get(unit, {})
        seqs[unit] = {
            "group": group, "action": action, "interaction_class": cls,
            "persons": list(exp.persons), "frames": exp.frames,
            "first_frame": exp.first_frame, "last_frame": exp.last_frame,
            "has_video": bool(rec.get("has_video", bool(exp.cameras))),
            "text": rec.get("text") or None,
            "person_frames_not_valid": exp.person_frames_not_valid,
            "not_valid_by_reason": [dict(x) for x in exp.not_valid_by_reason],
            "not_valid_frames": not_valid,
            "withhold": None if exp.withhold is None else list(exp.withhold),
            "withheld": held,
            "joint_frames_not_observed": unobserved,
            "contact": None if c is None else {
                "event": has_contact, "pairs": dict(c.pairs), "fr_id": c.fr_id,
                "start_fr": c.start_fr, "end_fr": c.end_fr},
            "absent": dict(exp.absent),
            "figures": exp.figures.datasheet(),
        }
    missing = sorted(set(sequences) - set(exports))
    return {
        "session": session, "subjects": list(subjects),
        "sequences": dict(sorted(seqs.items())),
        "sequences_not_exported": missing,
        "interaction_classes": {k: sorted(v) for k, v in sorted(classes.items())},
        "contact_events": contact_events,
        "totals": {
            "sequences": len(seqs),
            "frames": int(sum(s["frames"] for s in seqs.values())),
            "person_frames": int(sum(s["frames"] * len(s["persons"]) for s in seqs.values())),
            "person_frames_not_valid": int(sum(s["person_frames_not_valid"]
                                               for s in seqs.values())),
            "not_valid_by_reason": dict(sorted(by_reason.items())),
            "withheld": dict(sorted(withheld.items())),
            "joint_frames_not_observed": int(sum(sum(s["joint_frames_not_observed"].values())
                                                 for s in seqs.values())),
        },
        "validity": "a person-frame is ground truth only when fitted from its own evidence "
                    "(reason 'fitted') and its QA flags do not say the fit is wrong (withheld: "
                    "reason 'qa:<QA reason>'); the others are written (the arrays are dense) and "
                    "marked false in valid/<action>.json with their reason",
        "qa": qa,
    }


def _mm(d, key="median"):
    if not isinstance(d, dict):
        return "-"
    v = d.get(key, d.get(f"{key}_mm"))
    return "-" if v is None else f"{v:.1f}"


def datasheet_md(sheet: dict) -> str:
    t = sheet["totals"]
    lines = [f"# Datasheet: {sheet['session']}", "",
             f"- subjects: {', '.join(sheet['subjects'])}",
             f"- sequences: {t['sequences']}, frames: {t['frames']}, person-frames: "
             f"{t['person_frames']}, of them not valid: {t['person_frames_not_valid']}",
             f"- contact events: {sheet['contact_events']}",
             "- interaction classes: " + ", ".join(f"{k} ({len(v)})" for k, v in
                                                   sheet["interaction_classes"].items()),
             "- not valid, by reason: " + (", ".join(f"{r} {n}" for r, n in
                                                     t["not_valid_by_reason"].items()) or "none"),
             "- of them withheld for QA flags (the fit called them valid, QA says the fit is "
             "wrong): " + (", ".join(f"{r} {n}" for r, n in t.get("withheld", {}).items())
                           or "none"),
             f"- joints3d_25 joint-frames of valid frames that no marker or view observed (not "
             f"ground truth, valid/<action>.json joints_valid): "
             f"{t.get('joint_frames_not_observed', 0)}",
             ""]
    if sheet["sequences_not_exported"]:
        lines += [f"- sequences of the recipe not released (an upstream stage failed): "
                  f"{', '.join(sheet['sequences_not_exported'])}", ""]
    lines += ["## Sequences", "",
              "| sequence | class | persons | frames | not valid | withheld for QA flags | contact (fr_id, video frame) | marker residual "
              "median mm | partner reprojection median px | SMPL-X v2s median mm |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for q, s in sheet["sequences"].items():
        f = s["figures"]
        conv = (f.get("convert") or {}).get("per_person") or []
        v2s = "/".join(f"{p.get('v2s_median_mm'):.1f}" if p.get("v2s_median_mm") is not None
                       else "-" for p in conv) or "-"
        c = s["contact"]
        ct = "-" if not c else f"{'yes' if c['event'] else 'no'} ({c['fr_id']})"
        lines.append(f"| {q} | {s['interaction_class']} | {', '.join(s['persons'])} | "
                     f"{s['frames']} | {s['person_frames_not_valid']} | "
                     f"{sum((s.get('withheld') or {}).values())} | {ct} | "
                     f"{_mm((f.get('marker_fit') or {}).get('residual_mm'))} | "
                     f"{_mm((f.get('partner_fit') or {}).get('reprojection_px'))} | {v2s} |")
    lines += ["", "## Frames that are not valid", "",
              "Frame indices as the fits number them (video frames; capture frames on a "
              "marker-only sequence), per person and reason:", ""]
    any_nv = False
    for q, s in sheet["sequences"].items():
        for subj, per in s["not_valid_frames"].items():
            for r, runs in per.items():
                any_nv = True
                lines.append(f"- {q}, {subj}: {r}: " + ", ".join(
                    f"{a}" if a == b else f"{a}-{b}" for a, b in runs))
    if not any_nv:
        lines.append("- none")
    lines += ["", sheet["validity"], ""]
    qa = sheet.get("qa")
    if qa:
        lines += ["## Quality checks (stage qa)", "",
                  f"{qa['flagged']} of {qa['frames']} frames flagged ({100 * qa['rate']:.1f} %): "
                  f"{qa['what']}.", "",
                  "| sequence | frames | flagged | spans (video frames: reasons) |", "|---|---|---|---|"]
        for q, s in qa["sequences"].items():
            spans = "; ".join(f"{a}-{b}: {', '.join(r)}" for a, b, r in s["spans"][:6])
            more = f" (+{len(s['spans']) - 6} more)" if len(s["spans"]) > 6 else ""
            sync = ("; camera out of sync: " + ", ".join(f"{c} {v:+d}" for c, v in
                                                          s["sync_offset_frames"].items())
                    if s["sync_offset_frames"] else "")
            lines.append(f"| {q} | {s['frames']} | {s['flagged']} | {spans or '-'}{more}{sync} |")
        lines.append("")
    return "\n".join(lines)


# ------------------------------------------------------------------------------ re-read pass
def verify_release(root: Path, copied: dict[str, str] | None = None) -> dict:
    """Re-read every file of the release folder ``root`` through its reader and verify the
    manifest. ``copied``: ``{relative path: sha256}`` the files must still have (the exports').
    Returns ``{"ok", "files": {path: what was checked}, "problems": [...]}``."""
    from calib.io import read_chi3d_cameras
    from formats import anny_json, chi3d
    from formats import release as R
    from formats.errors import InputError
    from formats.video import video_info

    root = Path(root)
    problems: list[str] = []
    checked: dict[str, str] = {}
    files = sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
    # (group, action) -> {what: (P, F)}
    shapes: dict[tuple[str, str], dict[str, tuple]] = defaultdict(dict)
    videos: list[tuple[str, str, str]] = []
    cam_actions: set[tuple[str, str]] = set()
    contact: dict[str, dict] = {}
    text: dict[str, dict] = {}

    def attempt(rel, what, fn, *args):
        try:
            out = fn(*args)
            checked[rel] = what
            return out
        except InputError as e:
            problems.append(str(e))
        except (OSError, ValueError, KeyError, TypeError) as e:
            problems.append(f"{root / rel}: {what}: {type(e).__name__}: {e}")
        return None

    for rel in files:
        parts = rel.split("/")
        p = root / rel
        if rel in (R.MANIFEST_FILE, "verification.json"):
            continue
        if rel == "datasheet.json":
            attempt(rel, "json", lambda q: json.loads(q.read_text()), p)
            continue
        if rel == "datasheet.md":
            attempt(rel, "utf-8 text", lambda q: q.read_text(encoding="utf-8"), p)
            continue
        g = parts[0]
        if len(parts) == 2 and parts[1] == CONTACT_FILE:
            contact[g] = attempt(rel, "formats.chi3d.read_contact_signatures",
                                 chi3d.read_contact_signatures, p) or {}
        elif len(parts) == 2 and parts[1] == R.TEXT_FILE:
            text[g] = attempt(rel, "formats.release.read_text_annotations",
                              R.read_text_annotations, p) or {}
        elif (len(parts) == 3 and parts[2].endswith(".json")
              and parts[1] not in ("camera_parameters", "videos")):
            action = parts[2][:-5]
            kind = parts[1]
            if kind == "smplx":
                a = attempt(rel, "formats.chi3d.read_smplx", chi3d.read_smplx, p)
                sh = None if a is None else a["transl"].shape[:2]
            elif kind == "joints3d_25":
                a = attempt(rel, "formats.chi3d.read_joints3d_25", chi3d.read_joints3d_25, p)
                sh = None if a is None else a.shape[:2]
            elif kind == R.VALID_DIR:
                a = attempt(rel, "formats.release.read_valid", R.read_valid, p)
                sh = None if a is None else a["valid"].shape
            else:  # the fitted model's own parameters (anny/<action>.json)
                a = attempt(rel, "formats.anny_json.read_anny", anny_json.read_anny, p)
                sh = None if a is None else np.asarray(a["transl"]).shape[:2]
            if sh is not None:
                shapes[(g, action)][rel] = tuple(int(x) for x in sh)
        elif len(parts) == 4 and parts[1] == "camera_parameters" and parts[3].endswith(".json"):
            cam_actions.add((g, parts[3][:-5]))
        elif len(parts) == 4 and parts[1] == "videos" and parts[3].endswith(".mp4"):
            videos.append((rel, g, parts[3][:-4]))
        else:
            problems.append(f"{p}: no reader for this file (not part of the release layout)")
    for g, action in sorted(cam_actions):
        cams = attempt(f"{g}/camera_parameters/*/{action}.json", "calib.io.read_chi3d_cameras",
                       read_chi3d_cameras, root / g, action)
        if cams is not None:
            for c in cams:
                checked[f"{g}/camera_parameters/{c}/{action}.json"] = "calib.io.read_chi3d_cameras"
            checked.pop(f"{g}/camera_parameters/*/{action}.json", None)
    for (g, action), sh in sorted(shapes.items()):
        ref = f"{g}/joints3d_25/{action}.json"
        want = sh.get(ref)
        if want is None:
            problems.append(f"{root / ref}: missing or unreadable, beside {sorted(sh)}")
            continue
        for rel, s in sh.items():
            if s != want:
                problems.append(f"{root / rel}: (persons, frames) {s} != {ref}'s {want}")
    for rel, g, action in videos:
        want = shapes.get((g, action), {}).get(f"{g}/joints3d_25/{action}.json")
        info = attempt(rel, "formats.video.video_info", video_info, root / rel)
        if info is not None and want is not None and info.n_frames != want[1]:
            problems.append(f"{root / rel}: {info.n_frames} video frames, its joints3d_25 has "
                            f"{want[1]}")
        elif info is not None and want is None:
            problems.append(f"{root / rel}: no joints3d_25/{action}.json beside the video")
        if info is not None:
            checked[rel] = f"formats.video.video_info ({info.n_frames} frames)"
    for g, sigs in contact.items():
        for action, s in sigs.items():
            want = shapes.get((g, action), {}).get(f"{g}/joints3d_25/{action}.json")
            if want is None:
                problems.append(f"{root / g / CONTACT_FILE}: {action}: no joints3d_25 for the "
                                "action")
            elif not s.fr_id < want[1] or (s.end_fr is not None and not s.end_fr < want[1]):
                problems.append(f"{root / g / CONTACT_FILE}: {action}.fr_id/end_fr: frame "
                                f"{s.end_fr or s.fr_id} outside the action's {want[1]} frames")
    for g, t in text.items():
        for action in t:
            if (g, action) not in shapes:
                problems.append(f"{root / g / R.TEXT_FILE}: {action}: no files of the action")
    for rel, h in (copied or {}).items():
        p = root / rel
        if not p.is_file():
            problems.append(f"{p}: missing (copied from the export)")
        elif R.sha256_file(p) != h:
            problems.append(f"{p}: differs from the export's file (sha256)")
    if (root / R.MANIFEST_FILE).is_file():
        try:
            problems += [q for q in R.verify_manifest(root)
                         if not q.startswith(f"{root / 'verification.json'}:")]
            checked[R.MANIFEST_FILE] = "formats.release.verify_manifest"
        except InputError as e:
            problems.append(str(e))
    else:
        problems.append(f"{root / R.MANIFEST_FILE}: missing")
    return {"ok": not problems, "files": checked, "problems": problems,
            "files_checked": len(checked)}


# -------------------------------------------------------------------------------------- stage
def run(ctx: StageContext) -> None:
    from artifacts import QAResult, Release, SequenceExport
    from formats import release as R
    from formats.errors import InputError

    rv = ctx.recipe
    exports = ctx.inputs.get("export") or {}
    if not isinstance(exports, dict):
        exports = {ctx.unit: exports}
    if not exports:
        raise InputError(ctx.recipe_path or "<recipe>", "sequences", "no sequence was exported")
    exports = {u: SequenceExport.load(a) for u, a in exports.items()}
    root = Path(ctx.out.dir).resolve()
    copied = merge_exports(exports, root)
    qa_arts = ctx.inputs.get("qa") or {}
    if not isinstance(qa_arts, dict):
        qa_arts = {ctx.unit: qa_arts}
    qa = qa_summary({u: QAResult.load(a) for u, a in qa_arts.items()}) if qa_arts else None
    sheet = datasheet(rv.session.name, list(rv.session.subjects),
                      rv.session.sequences.as_dict(), exports, qa)
    ctx.out.save_json("datasheet", sheet)
    ctx.out.path("datasheet.md").write_text(datasheet_md(sheet), encoding="utf-8")
    R.write_manifest(root)
    result = verify_release(root, copied)
    Release.of(result).save(ctx.out)
    # the manifest lists every file, verification.json included
    with open(root / R.MANIFEST_FILE, "a") as f:
        f.write(f"{R.sha256_file(root / 'verification.json')}  verification.json\n")
    late = R.verify_manifest(root)
    if not result["ok"] or late:
        problems = result["problems"] + late
        first = problems[0]
        file, _, rest = first.partition(": ")
        raise InputError(file, "<release>", f"{rest} ({len(problems)} problems in the re-read "
                         f"pass: {'; '.join(problems[:5])})")
    ctx.log(f"release: {len(exports)} sequences, {result['files_checked']} files re-read, "
            f"{sheet['totals']['person_frames_not_valid']} person-frames not valid (withheld for QA "
            f"flags: {sum(sheet['totals']['withheld'].values())}); manifest verified")


STAGE = Stage(name="release", func=run, per="session", upstream=("export", "qa"), reads=READS,
              version="1",
              doc="the release folder: every sequence's export, SHA-256 manifest, datasheet, "
                  "re-read")
