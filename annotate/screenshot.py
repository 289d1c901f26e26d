"""``python -m annotate.screenshot --recipe R --seq S --png docs/annotate.png``: a picture of the
annotation page on a sequence, with the proposal accepted (interval and a few candidate pairs)
and the views at the contact frame. The page is served in-process on a free port and written
to a temporary file (the sequence's own file is never touched); headless Chromium takes the
picture (``annotate.browser``).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from http.server import ThreadingHTTPServer
from pathlib import Path


def take(recipe: Path, seq: str, png: Path, outputs: Path, pairs: int = 4,
         width: int = 1400, height: int = 960) -> Path:
    import cv2

    from annotate.browser import Chromium
    from annotate.data import SequenceData
    from annotate.server import Annotator, make_handler

    data = SequenceData(recipe, seq, outputs)
    with tempfile.TemporaryDirectory(prefix="annotate-shot-") as tmp:
        app = Annotator(data, Path(tmp) / "interaction_contact_signature.json", "screenshot")
        httpd = ThreadingHTTPServer(("127.0.0.1", 0), make_handler(app))
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        try:
            with Chromium(width=width, height=height, timeout=120) as b:
                b.open(f"http://127.0.0.1:{httpd.server_address[1]}/")
                b.wait_for("document.body.dataset.ready === '1'", timeout=120)
                b.wait_for("window.annotateState.proposal.status !== 'computing'", timeout=300)
                if b.eval("!!document.getElementById('accept-interval')"):
                    b.click_element("#accept-interval")
                b.eval(f"window.annotateState.proposal.pairs.slice(0, {pairs}).forEach((q) => "
                       "document.querySelectorAll(\"#proposal-body button[title='accept this pair']\")"
                       "[window.annotateState.proposal.pairs.indexOf(q)].click())")
                b.click(*b.center("#view3d-0"))  # one facet picked, waiting for its partner
                b.eval("window.scrollTo(0, 0)")
                time.sleep(1.5)  # the views image at the contact frame
                raw = b.screenshot(Path(tmp) / "page.png")
                img = cv2.imread(str(raw))
        finally:
            httpd.shutdown()
            httpd.server_close()
            data.close()
    png.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(png), img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return png


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m annotate.screenshot", description=__doc__.split("\n\n")[0])
    ap.add_argument("--recipe", type=Path, default=Path("recipes/demo.yaml"))
    ap.add_argument("--seq", default="s01/Handshake 1")
    ap.add_argument("--png", type=Path, default=Path("docs/annotate.png"))
    ap.add_argument("--outputs", type=Path, default=Path("outputs"))
    a = ap.parse_args(argv)
    print(take(a.recipe, a.seq, a.png, a.outputs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
