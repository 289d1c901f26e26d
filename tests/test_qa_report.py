"""qa.report: the sequence report and the session index, checked as pages (pure Python) and
rendered in headless Chromium (every image loads, a screenshot that is not blank, the index's
order and links, a deleted image reported by the page itself).

Chromium: skipped when /usr/bin/chromium is missing, unless MOCAP_REQUIRE_BROWSER is set (the
Makefile's test target sets it after `scripts/setup.sh --browser`): then a missing browser fails.
"""
from __future__ import annotations

import os
import re
import shutil
import urllib.parse
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from formats.errors import InputError
from qa.report import (
    IndexRow,
    describe_reason,
    render_in_chromium,
    sort_rows,
    webm_copy,
    write_index,
    write_sequence_report,
)

SEQ = 'Push 1 <b>&"x"'                       # spaces, tags, ampersand and quotes
EVIL = "<script>alert('x')</script>"


@pytest.fixture(scope="session")
def chromium(chromium_exe):
    return chromium_exe


class _Tags(HTMLParser):
    """Collects (tag, attrs) of every start tag."""

    def __init__(self):
        super().__init__()
        self.tags: list[tuple[str, dict]] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))


def tags(text: str) -> list[tuple[str, dict]]:
    p = _Tags()
    p.feed(text)
    return p.tags


def _png(path: Path, seed: int, size=(90, 160)) -> Path:
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((*size, 3), np.uint8)
    img[:] = rng.integers(0, 255, 3)
    h, w = size
    cv2.rectangle(img, (w // 4, h // 4), (3 * w // 4, 3 * h // 4), (20, 200, 30), -1)
    cv2.putText(img, str(seed), (5, h - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), img)
    return path


def _stage_reports() -> dict:
    return {
        "partner_fit": {"frames": 40, "frames_valid": 38,
                        "frames_not_valid": {"poor_reprojection": 2},
                        "reprojection_px": {"median": 3.87, "per_view_median": [3.2, 3.8, 7.0, 5.2]},
                        "per_frame": list(range(200)),
                        "note": EVIL, "cpu_s": 12.5,
                        "pairs": [{"regions": ["l_abdomen", "r_fingers"], "facets": [2, 2]}] * 3},
        "marker_fit": {"nested": {"a": {"b": {"c": {"d": 1}}}}, "median_mm": 8.1, "frames": 40,
                       "per_marker": {f"M{i:02d}": {"median": 1.0 + i, "p90": 2.0 + i}
                                      for i in range(70)}},
    }


def build_report(root: Path, seq: str = SEQ, n_spans: int = 2, video: bool = True) -> dict:
    """A small fake QA output: overlay PNGs per span, a plot, a sample frame, an MP4 (and its
    WebM copy), stage reports. Returns {"html", "images": [relpaths], "out_dir"}."""
    from formats.video import write_mp4

    out = root / "qa"
    images = []
    figs = [("Per-frame metrics <flagged shaded>", "metrics plot.png")]
    _png(out / figs[0][1], 100, (200, 320))
    images.append(figs[0][1])
    spans = []
    for k in range(n_spans):
        imgs = [f"overlays/span {k} frame {f}.png" for f in (10 * k + 3, 10 * k + 5)]
        for j, p in enumerate(imgs):
            _png(out / p, 10 * k + j)
        images += imgs
        spans.append({"start": 10 * k + 2, "end": 10 * k + 6, "peak_frame": 10 * k + 5,
                      "reasons": ["partner.reproj_body_px.58860488", "penetration_mm"],
                      "worst": {"partner.reproj_body_px.58860488": 41.2, "penetration_mm": 23.0},
                      "images": imgs})
    spans[-1]["reasons"].append("custom_metric")
    spans[-1]["described"] = ["", "", "the caller's own words"]
    _png(out / "overlays/sample 30.png", 77)
    images.append("overlays/sample 30.png")
    spans.append({"start": 30, "end": 30, "reasons": [], "images": ["overlays/sample 30.png"],
                  "sample": True})
    vid = None
    if video:
        vid = "tiles.mp4"
        frames = [np.full((64, 96, 3), 30 + 20 * i, np.uint8) for i in range(8)]
        write_mp4(out / vid, frames, fps=10)
        webm_copy(out / vid)
    summary = {"frames": 40, "flagged": 10, "rate": 0.25, "people": ["wearer", "partner"],
               "reasons": {"partner.reproj_body_px.58860488": 10, "penetration_mm": 4},
               "not_valid": {"partner": 2}, "sync_offset_frames": {"58860488": 0, "50591643": 2},
               "sync_not_measurable_why": {"65906101": "flat: the cost rises 2 % <2 frames>"},
               "thresholds": {"partner.reproj_body_px.58860488": 15.0, "penetration_mm": 20.0},
               "units": {"partner.reproj_body_px.58860488": "px", "penetration_mm": "mm"},
               "s_per_frame": 0.21, "odd <key>": EVIL}
    html = write_sequence_report(out, sequence=seq, title="QA report", summary=summary,
                                 spans=spans, figures=figs, video=vid,
                                 stage_reports=_stage_reports(),
                                 links={"3D scene": "scene.mcap", "metrics": "metrics.npz"})
    return {"html": html, "images": images, "out_dir": out}


def build_index(root: Path) -> tuple[Path, list[IndexRow]]:
    """Three sequences' reports under root/<group>/<action>/qa and the index at root."""
    specs = [("s01", "Push 1", 40, 4, "flagged"), ("s01", "Hug <2>", 40, 20, "flagged"),
             ("s02", "Kick 1", 50, 0, "ok")]
    rows = []
    for g, a, frames, flagged, status in specs:
        rep = build_report(root / g / a, seq=f"{g}/{a}", n_spans=1, video=False)
        href = os.path.relpath(rep["html"], root)
        thumb = os.path.relpath(rep["out_dir"] / rep["images"][0], root) if a == "Push 1" else None
        rows.append(IndexRow(sequence=f"{g}/{a}", href=href, frames=frames, flagged=flagged,
                             spans=1 if flagged else 0, reasons={"penetration_mm": flagged},
                             not_valid=0, thumbnail=thumb, status=status))
    return write_index(root / "index.html", rows, "Session QA <studio>",
                       notes=["bench & demo", "flagged share = flagged / frames"]), rows


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    return build_report(tmp_path_factory.mktemp("qa report"))


# ----------------------------------------------------------------------------- pure Python

def test_strings_are_escaped_and_page_is_self_contained(report):
    text = report["html"].read_text(encoding="utf-8")
    assert EVIL not in text and "&lt;script&gt;" in text
    assert 'Push 1 &lt;b&gt;&amp;&quot;x&quot;' in text
    t = tags(text)
    assert sum(1 for tag, _ in t if tag == "script") == 1          # only the inline check
    assert not [tag for tag, _ in t if tag in ("link", "iframe", "object", "embed")]
    for tag, a in t:
        for k in ("src", "href"):
            v = a.get(k)
            if v is not None:
                assert not re.match(r"^[a-z][a-z0-9+.-]*:", v, re.I), (tag, v)  # relative only
                assert not os.path.isabs(urllib.parse.unquote(v)), v
    assert "@import" not in text and "url(" not in text
    # every referenced image is a file beside the page (spaces percent-encoded)
    srcs = [a["src"] for tag, a in t if tag == "img"]
    assert len(srcs) == len(report["images"])
    assert "overlays/span%200%20frame%203.png" in srcs
    for s in srcs:
        assert (report["out_dir"] / urllib.parse.unquote(s)).is_file(), s


def test_spans_reasons_in_plain_words_and_stage_reports(report):
    text = report["html"].read_text(encoding="utf-8")
    assert "partner.reproj_body_px.58860488 = 41 px &gt; 15 px" in text
    assert "penetration_mm = 23 mm &gt; 20 mm" in text
    assert "the caller&#x27;s own words" in text                    # no threshold: 'described'
    assert "Sample of the rest" in text and "Frames 2–6 (5 frames), worst at frame 5" in text
    assert "Foxglove" in text and 'href="scene.mcap"' in text
    assert text.count("<details>") >= 2 and "partner_fit" in text and "marker_fit" in text
    assert "(+188 more; 200 in all)" in text                       # the long list is cut
    # key figures first: the scalar figure 'frames' comes before the nested table
    pf = text[text.index("<summary>partner_fit"):]
    assert pf.index("frames_valid") < pf.index("per_view_median")
    assert "<summary>partner_fit <span class=\"more\">frames 40, frames_valid 38, " \
        "reprojection_px median 3.9, cpu_s 12</span>" in text
    mf = text[text.index("<summary>marker_fit"):]
    assert mf.index(">frames<") < mf.index(">median_mm<") < mf.index(">nested<")
    # a dict of flat dicts is one table (a row per marker), cut with a count
    assert "<th></th><th>median</th><th>p90</th>" in mf and "<th>M59</th>" in mf
    assert "<th>M60</th>" not in mf and "(+10 more; 70 in all)" in mf
    # the video offers the WebM first (Chromium cannot decode mp4v), the MP4 second
    v = text[text.index("<video"):text.index("</video>")]
    assert v.index("tiles.webm") < v.index("tiles.mp4")
    # sync offsets: the non-zero one is marked; a view that cannot tell is listed with why
    assert re.search(r"50591643</td><td class=\"flag\">2<", text)
    assert re.search(r"65906101</td><td class=\"flag\">not measurable</td><td>flat: the cost "
                     r"rises 2 % &lt;2 frames&gt;<", text)
    assert "sync_not_measurable_why" not in text  # not repeated raw under "More"


def test_describe_reason():
    assert describe_reason("partner.reproj_body_px.58860488", 41.2, 15) == \
        "partner.reproj_body_px.58860488 = 41 px > 15 px"
    assert describe_reason("unexpected_contact_mm", 3.0, 10.0) == "unexpected_contact_mm = 3 mm < 10 mm"
    assert describe_reason("wearer.foot_skate_m_s", 0.412, 0.25) == \
        "wearer.foot_skate_m_s = 0.412 m/s > 0.25 m/s"
    assert "|-2| > 1" in describe_reason("sync_offset_frames.50591643", -2, 1)
    assert describe_reason("partner.not_valid", 1.0, 0.5) == \
        "partner.not_valid: the partner's fit is marked not valid"
    assert describe_reason("x<y>", 2.0, None) == "x<y> = 2"


def test_index_sorting_and_relative_links(tmp_path):
    idx, rows = build_index(tmp_path / "session a")
    assert [r.sequence for r in sort_rows(rows)] == ["s01/Hug <2>", "s01/Push 1", "s02/Kick 1"]
    failed = IndexRow("s09/Bad", "x/report.html", 0, 0, 0, {}, 0, status="failed")
    assert sort_rows(rows + [failed])[0] is failed
    text = idx.read_text(encoding="utf-8")
    assert "Session QA &lt;studio&gt;" in text and "s01/Hug &lt;2&gt;" in text
    t = tags(text)
    order = [a["data-sequence"] for tag, a in t if tag == "tr" and "data-sequence" in a]
    assert order == ["s01/Hug <2>", "s01/Push 1", "s02/Kick 1"]
    hrefs = [a["href"] for tag, a in t if tag == "a" and a.get("href", "").endswith("report.html")]
    assert hrefs[0] == "s01/Hug%20%3C2%3E/qa/report.html"
    assert len(hrefs) == 3 and all((idx.parent / urllib.parse.unquote(h)).is_file() for h in hrefs)
    assert "width:50.0%" in text and "width:0.0%" in text         # the bars: 20/40 and 0/50


def test_bad_input_names_the_field(tmp_path):
    with pytest.raises(InputError, match=r"spans\[0\]\.start"):
        write_sequence_report(tmp_path, sequence="s", title="t", summary={}, spans=[{"end": 3}],
                              figures=[], video=None, stage_reports={})
    with pytest.raises(InputError, match=r"rows\[0\]\.status"):
        write_index(tmp_path / "i.html", [IndexRow("a", "a.html", 1, 0, 0, {}, 0, status="meh")],
                    "t")
    with pytest.raises(InputError, match=r"rows\[0\]\.flagged"):
        write_index(tmp_path / "i.html", [IndexRow("a", "a.html", 1, 5, 0, {}, 0)], "t")


# ----------------------------------------------------------------------------- in Chromium

def _not_blank(png: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] > 500 and img.shape[1] > 500, png
    assert float(img.astype(np.float32).var()) > 200.0, "screenshot is blank"
    return img


def test_sequence_report_in_chromium(chromium, report, tmp_path):
    res = render_in_chromium(report["html"], tmp_path / "report.png")
    assert res["images"] == f"ok {len(report['images'])}", res["images"]
    assert res["broken"] == [] and res["banner"] == ""
    assert res["video"] == "ok 96x64", res["video"]               # the WebM copy plays
    img = _not_blank(res["screenshot"])
    # the page rendered the text and the images: many distinct colours, not one flat page
    assert len(np.unique(img.reshape(-1, 3)[::7], axis=0)) > 50


def test_index_in_chromium(chromium, tmp_path):
    idx, rows = build_index(tmp_path / "session b")
    res = render_in_chromium(idx, tmp_path / "index.png")
    assert res["images"] == "ok 1"                                  # the one thumbnail
    t = tags(res["dom"])
    order = [a["data-sequence"] for tag, a in t if tag == "tr" and "data-sequence" in a]
    assert order == [r.sequence for r in sorted(rows, key=lambda r: -r.flagged / r.frames)]
    hrefs = [a["href"] for tag, a in t if tag == "a" and a.get("href", "").endswith("report.html")]
    assert len(hrefs) == 3 and all((idx.parent / urllib.parse.unquote(h)).is_file() for h in hrefs)
    _not_blank(res["screenshot"])
    # a linked report opens and its images load too
    sub = render_in_chromium(idx.parent / urllib.parse.unquote(hrefs[0]))
    assert sub["images"].startswith("ok ") and sub["video"] == "none"


def test_broken_image_is_reported(chromium, report, tmp_path):
    out = tmp_path / "copy of qa"
    shutil.copytree(report["out_dir"], out)
    gone = "overlays/span 1 frame 15.png"
    (out / gone).unlink()
    (out / "tiles.webm").unlink()                  # the mp4v MP4 left: Chromium cannot decode it
    res = render_in_chromium(out / "report.html", tmp_path / "broken.png")
    assert res["images"] == f"broken {gone}", res["images"]
    assert res["broken"] == [gone]
    assert gone in res["banner"] and f"1 of {len(report['images'])} images" in res["banner"]
    assert res["video"] == "broken tiles.webm, tiles.mp4", res["video"]
    # the red banner is visible at the top of the screenshot
    img = _not_blank(res["screenshot"]).astype(int)
    top = img[5:25, 100:1100]                                        # BGR
    red = (top[..., 2] > 170) & (top[..., 1] < 80) & (top[..., 0] < 80)
    assert red.mean() > 0.5, red.mean()


def test_stage_warnings_are_listed_at_the_top(tmp_path):
    """Every stage report's warning lines (``warnings``, the keypoints' ``video_warnings``)
    come in one list above the flags, naming their stage, escaped, each once; a page whose
    stages warn of nothing has no such list."""
    from qa.report import stage_warnings

    reps = {"capture": {"warnings": ["LTHI: 150 samples unswapped", "LTHI: 150 samples unswapped"]},
            "keypoints": {"video_warnings": ["cam 1: variable frame rate <vfr>"]},
            "partner_fit": {"warnings": ["120 of 800 partner body keypoints (15 %)"], "frames": 3},
            "rig": None, "convert": {"warnings": []}}
    assert stage_warnings(reps) == [("capture", "LTHI: 150 samples unswapped"),
                                    ("keypoints", "cam 1: variable frame rate <vfr>"),
                                    ("partner_fit", "120 of 800 partner body keypoints (15 %)")]
    kw = dict(sequence="s", title="QA", summary={"frames": 3, "flagged": 0}, spans=[],
              figures=[], video=None)
    text = write_sequence_report(tmp_path / "a", stage_reports=reps, **kw).read_text()
    top = text[:text.index("Why frames are flagged")]
    assert "Warnings (3)" in top and "variable frame rate &lt;vfr&gt;" in top
    assert top.count("150 samples unswapped") == 1 and "<b>partner_fit</b>" in top
    quiet = write_sequence_report(tmp_path / "b", stage_reports={"convert": {"warnings": []}},
                                  **kw).read_text()
    assert "Warnings (" not in quiet
