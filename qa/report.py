"""The HTML report of one sequence's QA and the index page of a session or release (issue #18,
item 4), and the headless-Chromium check that every image of such a page loads.

Both pages are self-contained static files that open from disk (``file://``): the CSS and the
script are inline, nothing is fetched (no fonts, no CDN), the images / video / MCAP scene are
files beside the page, referenced by *relative* paths (an absolute path is made relative to the
page's folder). Every string is HTML-escaped and every path percent-encoded, so sequence names
with spaces and reasons with ``<`` / ``>`` show as written.

An inline script runs after ``load``: it checks every ``<img>`` (``complete && naturalWidth >
0``) and writes ``document.body.dataset.images`` = ``"ok <n>"`` or ``"broken <name>, <name>"``
and, when one is broken, shows a red banner listing them. It does the same for the ``<video>``
(``dataset.video`` = ``"ok <w>x<h>"``, ``"broken <src>"`` or ``"none"``): Chromium and Firefox
cannot decode the MPEG-4 Part 2 (``mp4v``) that ``formats.video.write_mp4`` writes, so a WebM
beside the MP4 (same stem, ``webm_copy``) is offered as the first ``<source>`` when it exists.

:func:`render_in_chromium` runs Debian's ``chromium`` headless on a page and returns what the
script found (installed by ``scripts/setup.sh --browser``).
"""
from __future__ import annotations

import html
import json
import math
import os
import re
import shutil
import subprocess
import tempfile
import urllib.parse
from dataclasses import dataclass
from html.parser import HTMLParser
from pathlib import Path

from formats.errors import InputError
from qa.constants import SYNC_MIN_Z as _SYNC_MIN_Z

MAX_LIST_ITEMS = 12      # longer lists in the stage reports are cut, with a count
MAX_MATRIX_ROWS = 60     # rows of a dict-of-dicts table (e.g. per marker)
MAX_TABLE_DEPTH = 4      # nested dicts deeper than this are shown as (cut) JSON
CHROMIUM_TIMEOUT_S = 60.0
INSTALL_HINT = ("install it with `bash scripts/setup.sh --browser` (or `make browser`; it runs "
                "`apt-get install chromium` as root)")
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                  "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync")


# ----------------------------------------------------------------------------- small helpers

def esc(x) -> str:
    """HTML-escape any value (quotes included: safe in attributes too)."""
    return html.escape(str(x), quote=True)


def rel_url(path, base_dir: Path) -> str:
    """A relative path as an escaped, percent-encoded URL for ``src`` / ``href`` (spaces, ``#``,
    ``?``, ``:`` in file names survive); an absolute path is made relative to ``base_dir``."""
    p = str(path)
    if os.path.isabs(p):
        p = os.path.relpath(p, base_dir)
    p = p.replace(os.sep, "/")
    return esc(urllib.parse.quote(p, safe="/"))


def fmt_num(v) -> str:
    """A number for people: ints as they are, floats to about 2-3 significant digits."""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    if math.isnan(f):
        return "–"
    if math.isinf(f):
        return "∞" if f > 0 else "−∞"
    a = abs(f)
    digits = 0 if a >= 10 else 1 if a >= 1 else 3
    s = f"{f:.{digits}f}" if a >= 1 or a == 0 else f"{f:.3g}"
    if "." in s and "e" not in s:
        s = s.rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


_UNIT_SUFFIXES = (("_m_s3", "m/s³"), ("_m_s", "m/s"), ("_cm3", "cm³"), ("_mm", "mm"),
                  ("_px", "px"), ("_deg", "°"), ("_s", "s"))


def metric_unit(name: str, units: dict | None = None) -> str:
    """The unit of a metric: from ``units`` when given, else from its name
    (``partner.reproj_body_px.<cam>`` -> px, ``sync_offset_frames.<cam>`` -> frames)."""
    if units and name in units:
        u = str(units[name])
        return {"m/s3": "m/s³", "cm3": "cm³"}.get(u, u)
    parts = name.split(".")
    if parts[0] == "sync_offset_frames":
        return "frames"
    for seg in parts:
        for suf, unit in _UNIT_SUFFIXES:
            if seg.endswith(suf):
                return unit
    return ""


_PERSON = r"(?P<p>wearer|partner|person\d+)"
_GLOSSES = [
    (r"wearer\.marker_median_mm", "median marker residual of the marker wearer"),
    (r"wearer\.marker_max_mm", "worst marker residual of the marker wearer"),
    (_PERSON + r"\.reproj_(?P<g>\w+?)_px\.(?P<cam>.+)",
     "median 2D reprojection error of the {p}'s {g} keypoints in camera {cam}"),
    (_PERSON + r"\.self_penetration_mm", "the {p}'s self-penetration depth"),
    (_PERSON + r"\.ground_penetration_mm", "how deep the {p} is below the ground"),
    (_PERSON + r"\.foot_skate_m_s", "the {p}'s foot sliding speed while on the ground"),
    (_PERSON + r"\.jerk_m_s3", "the {p}'s temporal jerk (largest over the joints)"),
    (_PERSON + r"\.not_valid", "the {p}'s fit is marked not valid"),
    (r"penetration_mm", "deepest interpenetration between the two bodies"),
    (r"penetration_volume_cm3", "penetrating volume between the two bodies"),
    (r"contact_gap_mm", "gap between the annotated contact regions in an annotated contact frame"),
    (r"unexpected_contact_mm", "closest distance between the bodies outside the annotated contact"),
    (r"sync_offset_frames\.(?P<cam>.+)",
     "camera {cam}'s best time shift against the marker wearer"),
]


def reason_gloss(name: str) -> str:
    """What a metric name means, in words ("" when unknown)."""
    for pat, text in _GLOSSES:
        m = re.fullmatch(pat, name)
        if m:
            return text.format(**m.groupdict())
    return ""


def describe_reason(name: str, value=None, threshold=None, unit: str | None = None) -> str:
    """A flag reason in plain words: ``"partner.reproj_body_px.58860488 = 41 px > 15 px"``
    (the comparison is the one that flagged: ``<`` for a closest distance, ``|v|`` for a sync
    offset); a ``not_valid`` reason has no numbers. Not escaped."""
    unit = metric_unit(name) if unit is None else unit
    sp = f" {unit}" if unit else ""
    if name.split(".")[-1] == "not_valid":
        return f"{name}: {reason_gloss(name) or 'the fit is marked not valid'}"
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return name
    text = f"{name} = {fmt_num(value)}{sp}"
    if threshold is None:
        return text
    v, t = float(value), float(threshold)
    if name.startswith("sync_offset_frames"):
        return f"{text} (|{fmt_num(value)}| > {fmt_num(threshold)}{sp})" if abs(v) > t else text
    op = ">" if v > t else "<" if v < t else "="
    return f"{text} {op} {fmt_num(threshold)}{sp}"


def _scalar(v) -> bool:
    return v is None or isinstance(v, (str, int, float, bool))


# ----------------------------------------------------------------------------- generic tables

_KEY_FIGURE = re.compile(r"(^|_)(frames?|valid|median|mean|p9[05]|max|rate|cpu_s|fps|s_per_frame|"
                         r"iterations|source)(_|$)|_(mm|px)$")


_RANK = (r"^frames$", r"^frames_valid$", r"median", r"(_mm|_px)$", r"^(fps|s_per_frame)",
         r"cpu_s$")


def _rank(key) -> int | None:
    """How early a figure comes (lower first); None when the name does not look like one."""
    k = str(key)
    for i, p in enumerate(_RANK):
        if re.search(p, k):
            return i
    return len(_RANK) if _KEY_FIGURE.search(k) else None


def _ordered_items(d: dict) -> list:
    """Key figures first (scalars whose names look like figures: frames, frames valid, medians,
    mm / px figures, speed), then other scalars, then the nested entries."""
    items = list(d.items())
    key = sorted(((k, v) for k, v in items if _scalar(v) and _rank(k) is not None),
                 key=lambda kv: _rank(kv[0]))
    other = [(k, v) for k, v in items if _scalar(v) and _rank(k) is None]
    nested = [(k, v) for k, v in items if not _scalar(v)]
    return key + other + nested


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _more(n_shown: int, n: int) -> str:
    return f' <span class="more">… (+{n - n_shown} more; {n} in all)</span>' if n > n_shown else ""


def value_html(v, depth: int = 0) -> str:
    """Any JSON value as HTML: dicts as tables, lists of scalars inline (cut with a count),
    lists of dicts as a table of rows (cut with a count)."""
    if _scalar(v):
        return esc(fmt_num(v)) if not isinstance(v, str) else esc(v)
    if depth >= MAX_TABLE_DEPTH:
        s = json.dumps(v, default=str)
        return f"<code>{esc(s[:200])}</code>" + (" …" if len(s) > 200 else "")
    if isinstance(v, dict):
        if not v:
            return '<span class="more">(empty)</span>'
        vals = list(v.values())
        if len(vals) >= 2 and all(isinstance(x, dict) and x and all(map(_scalar, x.values()))
                                  for x in vals):
            return _matrix_html(v, depth)
        return table_html(v, depth + 1)
    if isinstance(v, (list, tuple)):
        n = len(v)
        if n == 0:
            return '<span class="more">(none)</span>'
        shown = list(v[:MAX_LIST_ITEMS])
        if all(_scalar(x) for x in shown):
            return esc(", ".join(fmt_num(x) if not isinstance(x, str) else x for x in shown)) + \
                _more(len(shown), n)
        if all(isinstance(x, dict) for x in shown):
            cols: list = []
            for x in shown:
                cols += [k for k in x if k not in cols]
            cols = cols[:10]
            head = "".join(f"<th>{esc(c)}</th>" for c in cols)
            rows = "".join("<tr>" + "".join(f"<td>{value_html(x.get(c, ''), depth + 1)}</td>"
                                            for c in cols) + "</tr>" for x in shown)
            return (f'<table class="kv"><tr>{head}</tr>{rows}</table>' + _more(len(shown), n))
        return "<ol>" + "".join(f"<li>{value_html(x, depth + 1)}</li>" for x in shown) + \
            "</ol>" + _more(len(shown), n)
    return esc(v)


def _matrix_html(d: dict, depth: int) -> str:
    """A dict of flat dicts (e.g. per marker: median, p90, max) as one table, a row per key
    (cut at MAX_MATRIX_ROWS with a count)."""
    cols: list = []
    for x in d.values():
        cols += [k for k in x if k not in cols]
    cols = cols[:12]
    head = "<th></th>" + "".join(f"<th>{esc(c)}</th>" for c in cols)
    items = list(d.items())[:MAX_MATRIX_ROWS]
    rows = "".join(f"<tr><th>{esc(k)}</th>" + "".join(
        f"<td>{value_html(x.get(c, ''), depth + 1)}</td>" for c in cols) + "</tr>"
        for k, x in items)
    return f'<table class="kv"><tr>{head}</tr>{rows}</table>' + _more(len(items), len(d))


def table_html(d: dict, depth: int = 0) -> str:
    """A dict as a two-column table, key figures first."""
    rows = "".join(f"<tr><th>{esc(k)}</th><td>{value_html(v, depth)}</td></tr>"
                   for k, v in _ordered_items(d))
    return f'<table class="kv">{rows}</table>'


# ----------------------------------------------------------------------------- page shell

_CSS = """
*{box-sizing:border-box}
body{font-family:"DejaVu Sans",Helvetica,Arial,sans-serif;margin:0;padding:0 24px 40px;
 color:#1d2733;background:#f6f7f9;font-size:14px;line-height:1.4}
h1{font-size:22px;margin:18px 0 4px}h2{font-size:18px;margin:28px 0 8px;
 border-bottom:2px solid #d5dbe3;padding-bottom:4px}h3{font-size:15px;margin:16px 0 6px}
.sub{color:#5b6b7d;margin:0 0 12px}
.banner{position:sticky;top:0;z-index:9;background:#c62828;color:#fff;padding:10px 14px;
 font-weight:bold;margin:0 -24px 10px;white-space:pre-wrap}
.banner.warn{background:#e6a100;color:#1d2733}
ul.warn li{background:#fff4d6;border-left:4px solid #e6a100;padding:4px 8px;margin:4px 0;list-style:none}
.figs{display:flex;flex-wrap:wrap;gap:12px}
.card{background:#fff;border:1px solid #d5dbe3;border-radius:6px;padding:10px 14px}
.kfig{display:flex;gap:12px;flex-wrap:wrap}.kfig .card{min-width:130px}
.kfig .v{font-size:22px;font-weight:bold}.kfig .l{color:#5b6b7d;font-size:12px}
table.kv{border-collapse:collapse;background:#fff;margin:2px 0}
table.kv th,table.kv td{border:1px solid #d5dbe3;padding:3px 8px;text-align:left;
 vertical-align:top}
table.kv th{background:#eef1f5;font-weight:600}
.more,.gloss{color:#6b7a8c;font-size:12px}
.flag{color:#b71c1c}.okc{color:#2e7d32}
figure{margin:0;background:#fff;border:1px solid #d5dbe3;border-radius:6px;padding:8px;
 flex:0 1 620px}
figure img{max-width:100%;display:block}figcaption{color:#5b6b7d;font-size:12px;margin-top:4px}
.span{background:#fff;border:1px solid #d5dbe3;border-left:5px solid #c62828;
 border-radius:6px;padding:10px 14px;margin:10px 0}
.span.sample{border-left-color:#2e7d32}
.span ul{margin:4px 0 8px 18px;padding:0}
.span .imgs{display:flex;flex-wrap:wrap;gap:8px}
.span .imgs img{max-width:620px;width:100%;border:1px solid #d5dbe3}
details{background:#fff;border:1px solid #d5dbe3;border-radius:6px;margin:8px 0;padding:6px 12px}
summary{cursor:pointer;font-weight:600}summary .more{font-weight:normal}
video{max-width:100%;background:#000}
table.index{border-collapse:collapse;background:#fff;width:100%}
table.index th,table.index td{border-bottom:1px solid #d5dbe3;padding:6px 8px;text-align:left;
 vertical-align:middle}
table.index th{background:#eef1f5}
.bar{background:#e4e8ee;width:160px;height:12px;border-radius:3px;overflow:hidden;
 display:inline-block;vertical-align:middle}
.bar>span{display:block;height:100%;background:#c62828}
.st{padding:1px 8px;border-radius:10px;font-size:12px;color:#fff}
.st-ok{background:#2e7d32}.st-flagged{background:#e65100}.st-failed{background:#6a1b9a}
.thumb{max-height:70px;max-width:120px;display:block}
code{background:#eef1f5;padding:0 3px;border-radius:3px}
"""

_CHECK_JS = r"""
(function () {
  function nm(el) {
    var s = el.getAttribute('src') || '';
    try { return decodeURIComponent(s); } catch (e) { return s; }
  }
  function imagesCheck() {
    var imgs = Array.prototype.slice.call(document.images);
    var bad = imgs.filter(function (im) { return !(im.complete && im.naturalWidth > 0); });
    if (bad.length === 0) {
      document.body.dataset.images = 'ok ' + imgs.length;
      return;
    }
    var names = bad.map(nm);
    document.body.dataset.images = 'broken ' + names.join(', ');
    var b = document.getElementById('qa-broken');
    b.textContent = bad.length + ' of ' + imgs.length + ' images did not load: ' +
      names.join(', ');
    b.hidden = false;
  }
  function videoCheck() {
    var vids = document.getElementsByTagName('video');
    if (vids.length === 0) { document.body.dataset.video = 'none'; return; }
    var v = vids[0];
    var srcs = Array.prototype.slice.call(v.getElementsByTagName('source'));
    function ok() { document.body.dataset.video = 'ok ' + v.videoWidth + 'x' + v.videoHeight; }
    function broken() {
      var names = srcs.map(nm).join(', ');
      document.body.dataset.video = 'broken ' + names;
      var b = document.getElementById('qa-video-broken');
      b.textContent = 'This browser cannot play the video (' + names +
        '); open the file with a video player.';
      b.hidden = false;
    }
    if (v.readyState >= 2) { ok(); return; }
    document.body.dataset.video = 'loading';
    v.addEventListener('loadeddata', ok);
    v.addEventListener('error', broken);
    if (srcs.length) srcs[srcs.length - 1].addEventListener('error', broken);
    if (v.networkState === 3) broken();
  }
  function run() { imagesCheck(); videoCheck(); }
  if (document.readyState === 'complete') run(); else window.addEventListener('load', run);
})();
"""


def _page(title: str, body: str) -> str:
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            f"<title>{esc(title)}</title><style>{_CSS}</style></head><body>"
            '<div id="qa-broken" class="banner" hidden></div>'
            '<div id="qa-video-broken" class="banner warn" hidden></div>'
            f"{body}<script>{_CHECK_JS}</script></body></html>\n")


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


def _img(src: str, base: Path, alt: str = "", cls: str = "") -> str:
    u = rel_url(src, base)
    c = f' class="{cls}"' if cls else ""
    return f'<a href="{u}"><img src="{u}" alt="{esc(alt or src)}"{c}></a>'


# ----------------------------------------------------------------------------- sequence report

_SUMMARY_KNOWN = ("frames", "flagged", "rate", "spans", "people", "reasons", "not_valid",
                  "sync_offset_frames", "sync_z", "sync_not_measurable_why", "thresholds",
                  "units")


def _span_html(i: int, s: dict, base: Path, thresholds: dict, units: dict, file: Path) -> str:
    for k in ("start", "end"):
        if k not in s:
            raise InputError(file, f"spans[{i}].{k}", "missing")
    start, end = int(s["start"]), int(s["end"])
    if end < start:
        raise InputError(file, f"spans[{i}].end", f"{end} is before start {start}")
    sample = bool(s.get("sample"))
    n = end - start + 1
    head = f"Frame {start}" if n == 1 else f"Frames {start}–{end} ({n} frames)"
    if not sample and s.get("peak_frame") is not None:
        head += f", worst at frame {int(s['peak_frame'])}"
    worst = s.get("worst") or {}
    thr = {**thresholds, **(s.get("thresholds") or {})}
    described = list(s.get("described") or [])
    items = []
    for j, r in enumerate(s.get("reasons") or []):
        if thr.get(r) is None and j < len(described) and described[j]:
            text = str(described[j])          # the caller's words when no threshold is known
        else:
            text = describe_reason(r, worst.get(r), thr.get(r), metric_unit(r, units))
        g = reason_gloss(r)
        gl = f' <span class="gloss">— {esc(g)}</span>' if g and not r.endswith("not_valid") else ""
        items.append(f'<li><span class="flag">{esc(text)}</span>{gl}</li>')
    reasons = f"<ul>{''.join(items)}</ul>" if items else \
        ('<p class="more">not flagged</p>' if sample else "")
    imgs = "".join(_img(p, base, f"{head}: {p}") for p in s.get("images") or [])
    cls = "span sample" if sample else "span"
    return (f'<div class="{cls}" id="span-{i}"><h3>{esc(head)}</h3>{reasons}'
            f'<div class="imgs">{imgs}</div></div>')


def _stage_html(stage: str, rep) -> str:
    if not isinstance(rep, dict):
        return (f"<details><summary>{esc(stage)}</summary>{value_html(rep)}</details>")
    cand = [(k, v) for k, v in rep.items() if _is_number(v) and _rank(k) is not None]
    cand += [(f"{k} median", v["median"]) for k, v in rep.items()
             if isinstance(v, dict) and _is_number(v.get("median"))]
    key = sorted(cand, key=lambda kv: _rank(kv[0]))[:4]
    line = ", ".join(f"{k} {fmt_num(v)}" for k, v in key)
    line = f' <span class="more">{esc(line)}</span>' if line else ""
    return f"<details><summary>{esc(stage)}{line}</summary>{table_html(rep)}</details>"


def heldout_html(rep: dict) -> str:
    """The held-out view table (stage ``heldout``'s report): per left-out camera and keypoint
    group, median / p90 px of the fit from the other views and of the triangulation
    baseline, on the same detections."""
    groups = ("body", "hands", "face", "all")

    def cell(st):
        if not st or st.get("median_px") is None:
            return "<td>–</td>"
        return f"<td>{esc(fmt_num(st['median_px']))} / {esc(fmt_num(st['p90_px']))}</td>"

    head = "".join(f"<th>{g}: fit</th><th>{g}: triangulation</th>" for g in groups)
    rows = ""
    for cam, r in {**rep.get("cameras", {}), "all cameras": rep.get("all", {})}.items():
        rows += f"<tr><td>{esc(cam)}</td>" + "".join(
            cell((r.get("fit") or {}).get(g)) + cell((r.get("baseline") or {}).get(g))
            for g in groups) + "</tr>"
    return ("<h3>Held-out view (px, median / p90)</h3><p class=\"gloss\">Each camera left out "
            "in turn: the fit from the other views and the plain triangulation of the other "
            "views, projected into it, against its own detections (every "
            f"{esc(fmt_num(rep.get('stride')))}th frame).</p>"
            f'<table class="kv"><tr><th>left out</th>{head}</tr>{rows}</table>')


WARNING_KEYS = ("warnings", "video_warnings")  # the stage reports' lists of warning lines


def stage_warnings(stage_reports: dict | None) -> list[tuple[str, str]]:
    """``[(stage, line)]``: every warning line the stage reports carry (their
    :data:`WARNING_KEYS` lists), in stage order, each line once per stage."""
    out: list[tuple[str, str]] = []
    for st, rep in (stage_reports or {}).items():
        if not isinstance(rep, dict):
            continue
        for key in WARNING_KEYS:
            lines = rep.get(key)
            if isinstance(lines, str):
                lines = [lines]
            for w in lines or ():
                if (st, str(w)) not in out:
                    out.append((st, str(w)))
    return out


def write_sequence_report(out_dir: Path, *, sequence: str, title: str, summary: dict,
                          spans: list[dict], figures: list[tuple[str, str]], video: str | None,
                          stage_reports: dict[str, dict], links: dict[str, str] | None = None,
                          heldout: dict | None = None) -> Path:
    """Write ``out_dir/report.html``: the QA summary, links (the MCAP scene with a line on
    opening it in Foxglove), the tiled video, the figures, the flagged spans with their reasons in
    plain words and overlay images, a "Sample of the rest" (spans with ``"sample": True``) and
    each stage's report as a collapsible table; the stage reports' warning lines
    (:func:`stage_warnings`) are listed at the top. Paths are relative to ``out_dir``.

    ``summary`` may carry ``thresholds`` {metric: value} and ``units`` {metric: unit} (the
    stage's ``QAMetrics.thresholds`` / ``.units``) so that reasons read ``= 41 px > 15 px``;
    a span may carry its own ``thresholds``, and ``described`` (one text per reason, used
    when no threshold is known for it). Returns the page's path."""
    out_dir = Path(out_dir)
    file = out_dir / "report.html"
    thresholds = dict(summary.get("thresholds") or {})
    units = dict(summary.get("units") or {})
    frames = summary.get("frames")
    flagged = summary.get("flagged")
    rate = summary.get("rate")
    if rate is None and frames:
        rate = (flagged or 0) / frames
    flagged_spans = [s for s in spans if not s.get("sample")]
    sample_spans = [s for s in spans if s.get("sample")]
    people = summary.get("people") or []
    b = [f"<h1>{esc(title)}</h1><p class=\"sub\">sequence <b>{esc(sequence)}</b></p>"]

    def card(v, label):
        return f'<div class="card"><div class="v">{esc(v)}</div><div class="l">{esc(label)}</div></div>'

    b.append('<div class="kfig">' + card(fmt_num(frames) if frames is not None else "–", "frames")
             + card(fmt_num(flagged) if flagged is not None else "–", "frames flagged")
             + card(f"{100 * rate:.1f} %" if rate is not None else "–", "flagged share")
             + card(str(len(flagged_spans)), "flagged spans")
             + card(", ".join(map(str, people)) or "–", "people") + "</div>")

    warned = stage_warnings(stage_reports)
    if warned:
        b.append(f"<h2>Warnings ({len(warned)})</h2><ul class=\"warn\">" + "".join(
            f"<li><b>{esc(st)}</b>: {esc(w)}</li>" for st, w in warned) + "</ul>")

    b.append("<h2>Why frames are flagged</h2>")
    reasons = summary.get("reasons") or {}
    if reasons:
        rows = ""
        for r, n in sorted(reasons.items(), key=lambda kv: (-float(kv[1] or 0), str(kv[0]))):
            t = thresholds.get(r)
            u = metric_unit(r, units)
            ts = "" if t is None else f"{fmt_num(t)} {u}".strip()
            rows += (f"<tr><td>{esc(r)}<div class=\"gloss\">{esc(reason_gloss(r))}</div></td>"
                     f"<td>{esc(fmt_num(n))}</td><td>{esc(ts)}</td></tr>")
        b.append('<table class="kv"><tr><th>reason</th><th>frames</th><th>threshold</th></tr>'
                 f"{rows}</table>")
    else:
        b.append('<p class="okc">No frame is flagged.</p>')
    nv = summary.get("not_valid") or {}
    if nv:
        b.append("<h3>Frames not valid</h3><table class=\"kv\"><tr><th>person</th>"
                 "<th>frames</th></tr>" + "".join(
                     f"<tr><td>{esc(p)}</td><td>{esc(fmt_num(n))}</td></tr>" for p, n in nv.items())
                 + "</table>")
    sync = summary.get("sync_offset_frames") or {}
    why = summary.get("sync_not_measurable_why") or {}
    if sync or why:
        zs = summary.get("sync_z") or {}
        rows = "".join(
            f"<tr><td>{esc(c)}</td><td class=\"{'flag' if o else 'okc'}\">{esc(fmt_num(o))}</td>"
            f"<td>{esc(fmt_num(zs[c])) if c in zs else ''}</td></tr>" for c, o in sync.items())
        rows += "".join(
            f"<tr><td>{esc(c)}</td><td class=\"flag\">not measurable</td><td>{esc(w)}</td></tr>"
            for c, w in why.items() if c not in sync)
        b.append("<h3>Camera time offsets (video frames; 0 = in sync)</h3><table class=\"kv\">"
                 "<tr><th>camera</th><th>offset</th><th>evidence of the best other shift "
                 f"(standard errors; kept from {esc(fmt_num(_SYNC_MIN_Z))}), or why the view "
                 f"cannot tell</th></tr>{rows}"
                 "</table>")
    if heldout:
        b.append(heldout_html(heldout))
    if thresholds:
        b.append("<details><summary>Thresholds</summary>" + table_html(
            {k: f"{fmt_num(v)} {metric_unit(k, units)}".strip() for k, v in thresholds.items()})
            + "</details>")
    other = {k: v for k, v in summary.items() if k not in _SUMMARY_KNOWN}
    if other:
        b.append("<h3>More</h3>" + table_html(other))

    if links:
        items = []
        for label, rel in links.items():
            u = rel_url(rel, out_dir)
            line = f'<li><a href="{u}">{esc(label)}</a> <code>{esc(rel)}</code>'
            if str(rel).lower().endswith(".mcap"):
                line += (' <span class="gloss">— the 3D scene: open it in Foxglove (File &gt; '
                         'Open local file, or drag it onto app.foxglove.dev / Foxglove Studio) '
                         'and scrub through the sequence.</span>')
            items.append(line + "</li>")
        b.append("<h2>Files</h2><ul>" + "".join(items) + "</ul>")

    if video:
        u = rel_url(video, out_dir)
        vp = Path(video) if os.path.isabs(str(video)) else out_dir / video
        webm = vp.with_suffix(".webm")
        srcs = ""
        if webm.exists() and vp.suffix.lower() != ".webm":
            srcs += f'<source src="{rel_url(os.path.relpath(webm, out_dir), out_dir)}" ' \
                    'type="video/webm">'
        mime = "video/webm" if vp.suffix.lower() == ".webm" else "video/mp4"
        srcs += f'<source src="{u}" type="{mime}">'
        b.append(f"<h2>The four views</h2><video controls preload=\"auto\">{srcs}</video>"
                 f'<p class="more"><a href="{u}">{esc(video)}</a></p>')

    if figures:
        b.append("<h2>Figures</h2><div class=\"figs\">" + "".join(
            f"<figure>{_img(rel, out_dir, cap)}<figcaption>{esc(cap)}</figcaption></figure>"
            for cap, rel in figures) + "</div>")

    b.append(f"<h2>Flagged spans ({len(flagged_spans)})</h2>")
    if flagged_spans:
        b += [_span_html(i, s, out_dir, thresholds, units, file) for i, s in enumerate(spans)
              if not s.get("sample")]
    else:
        b.append('<p class="okc">None.</p>')
    if sample_spans:
        n_s = sum(int(s["end"]) - int(s["start"]) + 1 for s in sample_spans)
        b.append(f"<h2>Sample of the rest ({n_s} frame{'s' if n_s != 1 else ''})</h2>")
        b += [_span_html(i, s, out_dir, thresholds, units, file) for i, s in enumerate(spans)
              if s.get("sample")]

    if stage_reports:
        b.append("<h2>Stage reports</h2>")
        b += [_stage_html(st, rep) for st, rep in stage_reports.items()]
    return _write(file, _page(f"{title} — {sequence}", "".join(b)))


# ----------------------------------------------------------------------------- index

@dataclass
class IndexRow:
    sequence: str
    href: str                     # relpath from the index to the sequence's report.html
    frames: int
    flagged: int
    spans: int
    reasons: dict[str, int]
    not_valid: int
    thumbnail: str | None = None  # relpath of an image, optional
    status: str = "ok"            # "ok" | "flagged" | "failed" (a sequence whose qa failed)

    @property
    def share(self) -> float:
        return self.flagged / self.frames if self.frames else 0.0


_STATUSES = ("ok", "flagged", "failed")


def sort_rows(rows: list[IndexRow]) -> list[IndexRow]:
    """Failed sequences first (nothing is known about them), then by flagged share, most first;
    ties by flagged frames, then by name."""
    return sorted(rows, key=lambda r: (r.status != "failed", -r.share, -r.flagged, r.sequence))


def write_index(path: Path, rows: list[IndexRow], title: str, notes: list[str] = ()) -> Path:
    """Write the index page of a session or release at ``path``: one row per sequence, sorted by
    flagged share (most first; failed ones on top), with a bar, the top reasons and a link to the
    sequence's report. ``notes``: lines shown under the title. Returns ``path``."""
    path = Path(path)
    base = path.parent
    for i, r in enumerate(rows):
        if r.status not in _STATUSES:
            raise InputError(path, f"rows[{i}].status", f"{r.status!r} is not one of {_STATUSES}")
        if r.frames < 0 or r.flagged < 0 or r.flagged > max(r.frames, 0):
            raise InputError(path, f"rows[{i}].flagged",
                             f"{r.flagged} flagged of {r.frames} frames ({r.sequence})")
    srt = sort_rows(rows)
    tot_f = sum(r.frames for r in rows)
    tot_x = sum(r.flagged for r in rows)
    n_failed = sum(r.status == "failed" for r in rows)
    b = [f"<h1>{esc(title)}</h1>"]
    b += [f'<p class="sub">{esc(n)}</p>' for n in notes]
    share = f"{100 * tot_x / tot_f:.1f} %" if tot_f else "–"
    b.append(f'<p>{len(rows)} sequences, {tot_f} frames, <b>{tot_x} flagged ({share})</b>'
             + (f', <span class="flag">{n_failed} failed</span>' if n_failed else "") + "</p>")
    trs = []
    for k, r in enumerate(srt, 1):
        u = rel_url(r.href, base)
        thumb = _img(r.thumbnail, base, r.sequence, "thumb") if r.thumbnail else ""
        top = sorted(((n, c) for n, c in r.reasons.items() if c), key=lambda kv: (-kv[1], kv[0]))
        rs = ", ".join(f"{n}: {c}" for n, c in top[:4])
        rs_html = esc(rs) + _more(min(4, len(top)), len(top))
        pct = 100 * r.share
        trs.append(
            f'<tr class="row" data-sequence="{esc(r.sequence)}"><td>{k}</td><td>{thumb}</td>'
            f'<td><a href="{u}">{esc(r.sequence)}</a></td>'
            f'<td><span class="st st-{esc(r.status)}">{esc(r.status)}</span></td>'
            f"<td>{r.frames}</td><td>{r.flagged}</td>"
            f'<td><span class="bar"><span style="width:{min(pct, 100):.1f}%"></span></span> '
            f"{pct:.1f} %</td><td>{r.spans}</td><td>{r.not_valid}</td><td>{rs_html}</td></tr>")
    b.append('<table class="index"><tr><th>#</th><th></th><th>sequence</th><th>status</th>'
             "<th>frames</th><th>flagged</th><th>flagged share</th><th>spans</th>"
             "<th>not valid</th><th>top reasons (frames)</th></tr>" + "".join(trs) + "</table>")
    return _write(path, _page(title, "".join(b)))


# ----------------------------------------------------------------------------- video for browsers

def webm_copy(video: Path, out: Path | None = None) -> Path:
    """Re-encode a video (e.g. the ``mp4v`` MP4 of ``formats.video.write_mp4``, which Chromium
    and Firefox cannot decode) as VP8 WebM beside it (same stem); the report offers it first.
    About 0.1 s per 1280x960 frame on one core."""
    import cv2

    video = Path(video)
    out = Path(out) if out is not None else video.with_suffix(".webm")
    cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        raise InputError(video, "<video>", "cannot open for reading")
    fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
    writer = None
    try:
        j = 0
        while True:
            ok, img = cap.read()
            if not ok:
                break
            if writer is None:
                writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"VP80"), float(fps),
                                         (img.shape[1], img.shape[0]))
                if not writer.isOpened():
                    raise InputError(out, "<video>", "cannot open a VP8 WebM writer")
            writer.write(img)
            j += 1
    finally:
        cap.release()
        if writer is not None:
            writer.release()
    if writer is None:
        raise InputError(video, "frames", "no frames to read")
    return out


# ----------------------------------------------------------------------------- headless chromium

def chromium_path() -> str | None:
    """The Chromium binary: ``$MOCAP_CHROMIUM``, ``/usr/bin/chromium``, or ``chromium`` on PATH."""
    env = os.environ.get("MOCAP_CHROMIUM")
    if env:
        return env if os.access(env, os.X_OK) else None
    if os.access("/usr/bin/chromium", os.X_OK):
        return "/usr/bin/chromium"
    return shutil.which("chromium") or shutil.which("chromium-browser")


class _BodyAttrs(HTMLParser):
    def __init__(self):
        super().__init__()
        self.body: dict[str, str] = {}
        self.banner = ""
        self._in_banner = False

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "body" and not self.body:
            self.body = {k: (v or "") for k, v in attrs}
        if a.get("id") == "qa-broken" and "hidden" not in a:
            self._in_banner = True

    def handle_endtag(self, _tag):
        self._in_banner = False

    def handle_data(self, data):
        if self._in_banner:
            self.banner += data


def _run_chromium(exe: str, args: list[str], timeout: float) -> subprocess.CompletedProcess:
    """One headless run with a fresh profile, in its own process group: on timeout the whole
    group (the browser and its helper processes) is killed."""
    import signal

    with tempfile.TemporaryDirectory(prefix="qa-chromium-") as profile:
        cmd = [exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *args]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                stdin=subprocess.DEVNULL, start_new_session=True)
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired as e:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.communicate()
            raise RuntimeError(f"chromium did not finish within {timeout:.0f} s: {' '.join(cmd)}"
                               ) from e
        return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def render_in_chromium(html: Path, screenshot: Path | None = None, *,
                       timeout: float = CHROMIUM_TIMEOUT_S, window: str = "1280,2000") -> dict:
    """Open ``html`` from disk in headless Chromium, let its scripts run (5 s of virtual time),
    and return ``{"images": "ok <n>" | "broken <names>", "broken": [names], "video": "ok WxH" |
    "broken <src>" | "none" | None, "banner": text of the red banner ("" when hidden), "dom":
    the DOM after the scripts, "screenshot": Path | None}``. With ``screenshot``, a second run
    saves a ``window``-sized PNG there. Raises FileNotFoundError when Chromium is missing
    (naming how to install it) and RuntimeError when it fails or times out."""
    html = Path(html).resolve()
    if not html.is_file():
        raise FileNotFoundError(f"{html}: no such page")
    exe = chromium_path()
    if exe is None:
        raise FileNotFoundError(f"chromium is not installed (/usr/bin/chromium missing); "
                                f"{INSTALL_HINT}")
    url = html.as_uri()
    p = _run_chromium(exe, ["--dump-dom", "--virtual-time-budget=5000", url], timeout)
    if p.returncode != 0 or "<body" not in p.stdout:
        raise RuntimeError(f"chromium --dump-dom {url} failed (exit {p.returncode}): "
                           f"{p.stderr[-800:]}")
    parser = _BodyAttrs()
    parser.feed(p.stdout)
    images = parser.body.get("data-images")
    broken = []
    if images and images.startswith("broken "):
        broken = images[len("broken "):].split(", ")
    shot = None
    if screenshot is not None:
        shot = Path(screenshot).resolve()
        shot.parent.mkdir(parents=True, exist_ok=True)
        shot.unlink(missing_ok=True)
        q = _run_chromium(exe, [f"--screenshot={shot}", f"--window-size={window}",
                                "--hide-scrollbars", "--virtual-time-budget=5000", url], timeout)
        if q.returncode != 0 or not shot.is_file():
            raise RuntimeError(f"chromium --screenshot {url} failed (exit {q.returncode}): "
                               f"{q.stderr[-800:]}")
    return {"images": images, "broken": broken, "video": parser.body.get("data-video"),
            "banner": parser.banner.strip(), "dom": p.stdout, "screenshot": shot}
