"""The annotation page in a real browser (headless Chromium over the DevTools protocol,
``annotate.browser``): load the page, click a facet on each body, accept a proposed pair, set
the interval, save, read the file back with the partner fit's reader, reopen the page and see
what was saved; a bad or stale file, and a save the reader refuses, give a message on the page.

The sequence is the small studio session's handshake (tests/conftest.py), its "fits" the
studio's true motion written as ``marker_fit`` / ``partner_fit`` artifacts into a temporary
outputs folder (the page reads artifacts, it runs no stage).

Chromium: skipped when /usr/bin/chromium is missing, unless MOCAP_REQUIRE_BROWSER is set (as in
tests/test_qa_report.py): then a missing browser fails.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SEQ = "s01/Handshake 1"
ACTION = "Handshake 1"


@pytest.fixture(scope="module")
def chromium(chromium_exe):
    from annotate.browser import Chromium

    with Chromium(chromium_exe, width=1500, height=1000) as b:
        yield b


class _Writer:
    def __init__(self, d: Path):
        self.dir = d

    def save_arrays(self, name, **arrays):
        p = self.dir / f"{name}.npz"
        np.savez(p, **arrays)
        return p


def _true_fits(recipe: Path, outputs: Path) -> None:
    """The studio's true motion of the handshake as the two fit artifacts."""
    from artifacts import BodyFit
    from recipes.schema import load_recipe

    session = load_recipe(recipe, check_files=False).session
    z = np.load(recipe.parent / "gt" / "s01" / f"{ACTION}.npz")
    F = len(z["frames"])
    for p, stage in enumerate(("marker_fit", "partner_fit")):
        d = outputs / session / "s01" / ACTION / stage
        d.mkdir(parents=True)
        BodyFit(body_pose=z["body_pose"][p], global_orient=z["global_orient"][p],
                transl=z["transl"][p], betas=z["betas"][p], frames=np.asarray(z["frames"]),
                valid=np.ones(F, bool), invalid_reason=np.zeros(F, np.int64)).save(_Writer(d))
        (d / "manifest.json").write_text("{}")


@pytest.fixture(scope="module")
def server(small_session, tmp_path_factory, chromium):
    """``python -m annotate`` on a free port; yields (url, the file it writes)."""
    tmp = tmp_path_factory.mktemp("annotate")
    outputs = tmp / "outputs"
    _true_fits(small_session, outputs)
    out = tmp / "labels" / "interaction_contact_signature.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "annotate", "--recipe", str(small_session), "--seq", SEQ,
         "--port", "0", "--out", str(out), "--outputs", str(outputs), "--annotator", "tester"],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    url = None
    end = time.monotonic() + 120
    while time.monotonic() < end:
        ln = proc.stdout.readline()
        if not ln:
            break
        lines.append(ln)
        if "open http://" in ln:
            url = ln.split("open ", 1)[1].split()[0]
            break
    if url is None:
        proc.kill()
        pytest.fail("the annotation server did not start:\n" + "".join(lines))
    drain = threading.Thread(target=lambda: [lines.append(x) for x in proc.stdout], daemon=True)
    drain.start()
    yield url, out
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _open(b, url: str) -> None:
    b.open(url)
    b.wait_for("document.body.dataset.ready === '1'", timeout=60, what="the page ready")
    b.wait_for("window.annotateState.proposal && window.annotateState.proposal.status !== 'computing'",
               timeout=60, what="the proposal")


def _set_frame(b, f: int) -> None:
    b.eval(f"(() => {{ const e = document.getElementById('frame-num'); e.value = '{f}'; "
           "e.dispatchEvent(new Event('change')); })()")
    assert b.eval("window.annotateState.frame") == f


def _rows(b) -> int:
    return b.eval("document.querySelectorAll('#pairs tbody tr').length")


def test_bad_and_stale_files_are_refused_with_a_message(chromium, server, anny):
    from annotate.signature import entry
    from body.regions import region_map

    url, out = server
    b = chromium
    rmap = region_map(anny)
    out.parent.mkdir(parents=True, exist_ok=True)
    good = entry(anny, rmap, "anny", 5, (2, 9), np.array([[int(rmap.faces_of("r_palm")[0]),
                                                            int(rmap.faces_of("l_palm")[0])]]))
    bad = json.loads(json.dumps(good))
    bad["anny_signature"]["face_id"][0][0] = len(anny.faces) + 3
    out.write_text(json.dumps({ACTION: bad}))
    _open(b, url)
    banner = b.eval("document.getElementById('banner').hidden ? '' : document.getElementById('banner').textContent")
    assert "refused" in banner and "facet outside the model's" in banner and str(out) in banner
    assert b.eval("window.annotateState.pairs.length") == 0 and _rows(b) == 0
    # a save the reader refuses (interval past the 24 frames) says why and leaves the file
    before = out.read_bytes()
    b.eval("Object.assign(window.annotateState, {start: 2, end: 40, fr: 5})")
    b.click_element("#save")
    b.wait_for("document.getElementById('banner').textContent.startsWith('Not saved')", what="the refusal")
    assert "outside the sequence's 24 frames" in b.eval("document.getElementById('banner').textContent")
    assert out.read_bytes() == before
    # a file made on another mesh (stale) is refused on reopening
    stale = json.loads(json.dumps(good))
    stale["annotation"]["num_vertices"] = 10475
    out.write_text(json.dumps({ACTION: stale}))
    _open(b, url)
    banner = b.eval("document.getElementById('banner').textContent")
    assert "num_vertices" in banner and "stale" in banner
    assert b.eval("window.annotateState.pairs.length") == 0
    out.unlink()


def test_annotate_save_and_reopen(chromium, server, anny, tmp_path):
    from fitting.contact_signature import load_contact

    url, out = server
    b = chromium
    if out.exists():
        out.unlink()
    _open(b, url)
    assert b.eval("document.getElementById('banner').hidden")
    assert b.eval("window.annotateState.proposal.status") == "ready"
    # one facet on each body, by real clicks at the middle of each 3D view
    b.click(*b.center("#view3d-0"))
    assert b.eval("window.annotateState.pending[0]") is not None
    assert "person 1: click a facet" in b.eval("document.getElementById('pending').textContent")
    b.click(*b.center("#view3d-1"))
    clicked = b.eval("window.annotateState.pairs")
    assert len(clicked) == 1 and _rows(b) == 1
    assert b.eval("window.annotateState.pending") == [None, None]
    # a drag rotates the view and picks nothing
    x, y = b.center("#view3d-0")
    b.call("Input.dispatchMouseEvent", {"type": "mousePressed", "x": x, "y": y, "button": "left", "buttons": 1, "clickCount": 1})
    b.call("Input.dispatchMouseEvent", {"type": "mouseMoved", "x": x + 60, "y": y, "button": "left", "buttons": 1})
    b.call("Input.dispatchMouseEvent", {"type": "mouseReleased", "x": x + 60, "y": y, "button": "left", "buttons": 0, "clickCount": 1})
    assert b.eval("window.annotateState.pending") == [None, None]
    # accept the first proposed pair (facets a few mm apart on the true meshes)
    proposed = b.eval("window.annotateState.proposal.pairs[0]")
    b.click_element("#proposal-body button[title='accept this pair']")
    assert _rows(b) == 2
    # the interval: start 4, contact 12, end 20 (buttons, after scrubbing)
    for f, button in ((4, "#set-start"), (20, "#set-end"), (12, "#set-contact")):
        _set_frame(b, f)
        b.click_element(button)
    assert b.eval("[window.annotateState.start, window.annotateState.end, window.annotateState.fr]") == [4, 20, 12]
    b.click_element("#save")
    b.wait_for("document.body.dataset.saved === '1'", what="the save")
    assert b.eval("document.getElementById('banner').hidden")
    # the file, read by the partner fit's reader
    ann = load_contact(out, ACTION, anny, 24, family="anny")
    assert ann.interval == (4, 20) and ann.frame == 12
    assert ann.facet_pairs.tolist() == [clicked[0], proposed]
    raw = json.loads(out.read_text())[ACTION]
    assert raw["annotation"]["annotator"] == "tester"
    assert raw["annotation"]["num_faces"] == len(anny.faces)
    # reopening shows what was saved
    _open(b, url)
    assert b.eval("window.annotateState.pairs") == [clicked[0], proposed] and _rows(b) == 2
    assert b.eval("[document.getElementById('start-v').textContent, document.getElementById('end-v').textContent, "
                  "document.getElementById('fr-v').textContent]") == ["4", "20", "12"]
    assert b.eval("window.annotateState.frame") == 12
    # the page as a picture: both 3D views drawn (a body on each, not the bare background)
    import cv2

    png = b.screenshot(tmp_path / "page.png")
    img = cv2.imread(str(png))
    for sel in ("#view3d-0", "#view3d-1"):
        r = b.eval(f"(() => {{ const r = document.querySelector('{sel}').getBoundingClientRect(); "
                   "return [r.left, r.top, r.width, r.height]; })()")
        x0, y0, w, h = (int(v) for v in r)
        crop = img[y0:y0 + h, x0:x0 + w].reshape(-1, 3).astype(int)
        background = np.array([0x38, 0x30, 0x2b])  # BGR of the viewport's background
        assert (np.abs(crop - background).sum(1) > 40).mean() > 0.05, sel
    # a correspondence is removable
    b.click_element("#pairs tbody tr:first-child button.remove")
    assert _rows(b) == 1 and b.eval("window.annotateState.pairs") == [proposed]


def test_server_refuses_cross_site_posts_and_foreign_hosts(server):
    """A form post from another site (not JSON) and a request for another host name (DNS
    rebinding) are refused; the file is not written."""
    import http.client
    import urllib.parse

    url, out = server
    u = urllib.parse.urlsplit(url)
    before = out.read_bytes() if out.exists() else None
    body = json.dumps({"fr_id": 3, "start": 2, "end": 5, "pairs": []})
    for headers, code in (({"Content-Type": "text/plain"}, 415),
                          ({"Content-Type": "application/json", "Host": "evil.example:80"}, 403)):
        c = http.client.HTTPConnection(u.hostname, u.port, timeout=10)
        c.request("POST", "/api/save", body=body, headers=headers)
        r = c.getresponse()
        assert r.status == code, (headers, r.status, r.read())
        c.close()
    c = http.client.HTTPConnection(u.hostname, u.port, timeout=10)
    c.request("GET", "/api/session", headers={"Host": "evil.example"})
    assert c.getresponse().status == 403
    c.close()
    assert (out.read_bytes() if out.exists() else None) == before
