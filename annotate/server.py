"""``python -m annotate --recipe R --seq <group>/<action>``: the annotation page on 127.0.0.1.

A ``ThreadingHTTPServer`` (stdlib) serves the page (``annotate/web``), three.js from
``annotate/web/node_modules`` (installed by ``scripts/setup.sh``; nothing is fetched at run
time) and a small JSON/binary API over one :class:`annotate.data.SequenceData`:

- ``GET /api/session``: the sequence, frames, cameras, the model's size, region names and the
  region of every facet, what the file holds for the action (or why it was refused);
- ``GET /api/faces.bin`` (int32 (F, 3)), ``GET /api/mesh.bin?frame=N`` (float32 (2, V, 3); no
  frame or ``rest=1``: the rest pose), ``GET /api/views.jpg?frame=N`` (the four views, 2x2);
- ``GET /api/proposal``: ``{"status": "computing" | "ready" | "none", ...}``
  (``annotate.proposals``, computed in the background at start);
- ``POST /api/save`` ``{"fr_id", "start", "end", "pairs": [[f0, f1], ...], "annotator"}``:
  written by ``annotate.signature.save`` (validated, atomic); 400 with ``{"error"}`` naming the
  file and field when refused (only ``Content-Type: application/json``, so another site's page
  cannot post it; requests whose ``Host`` is not local are refused); ``GET /api/load``: the
  file read back.

The file is ``--out``, default the recipe's ``contact`` file of the sequence (the one the
partner fit reads), else ``<outputs>/<session>/<group>/annotate/interaction_contact_signature.json``.
"""
from __future__ import annotations

import argparse
import json
import mimetypes
import os
import sys
import threading
import urllib.parse
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np

from formats.errors import InputError

WEB = Path(__file__).resolve().parent / "web"
VENDOR = WEB / "node_modules"
VENDOR_ALLOWED = ("three/build/", "three/examples/jsm/")
LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


class Annotator:
    """The state behind the page: the sequence's data, the file, the proposal."""

    def __init__(self, data, out: Path, annotator: str = "", frame: int | None = None,
                 proposals: bool = True, log=None):
        self.data = data
        self.out = Path(out)
        self.annotator = annotator
        self.frame_given = frame is not None
        self.frame = data.fits.frames[0] if frame is None and data.fits is not None else (frame or 0)
        self.frame = int(min(max(int(self.frame), 0), data.n_frames - 1))
        self.log = log or (lambda s: print(s, file=sys.stderr, flush=True))
        self._conversion = None
        self.proposal: dict = {"status": "none", "why": "proposals are off"}
        if proposals:
            self.proposal = {"status": "computing", "done": 0, "total": 0}
            threading.Thread(target=self._propose, daemon=True).start()

    # ---------------------------------------------------------------- proposals
    def _propose(self) -> None:
        from annotate import proposals as P

        d = self.data

        def progress(i, n):
            self.proposal.update(done=i, total=n)
        try:
            if d.fits is not None:
                p = P.from_fits(d.fits.frames, d.fits.at, d.model.faces, d.rmap, progress=progress)
            elif d.keypoints is not None and len(d.cams) >= 2:
                kp, idx = d.keypoints
                p = P.from_keypoints(d.cams, kp.kp[idx], kp.frames, progress=progress)
            else:
                self.proposal = {"status": "none", "why": "no fits and no keypoints on disk"}
                return
        except Exception as e:  # shown on the page; the page still works without a proposal
            self.proposal = {"status": "none", "why": f"proposal failed: {e}"}
            self.log(f"annotate: proposal failed: {e}")
            return
        p["status"] = "ready"
        self.proposal = p
        self.log(f"annotate: proposal from {p['source']}: interval {p['interval']}, "
                 f"contact frame {p['fr_id']}, {len(p['pairs'])} candidate facet pairs")

    # ---------------------------------------------------------------- file
    def conversion(self):
        """(correspondence, SMPL-X target model, its region map) or None (cached)."""
        if self._conversion is None:
            from body.regions import region_map

            c = self.data.conversion()
            self._conversion = (False,) if c is None else (c[0], c[1], region_map(c[1]))
        return None if self._conversion == (False,) else self._conversion

    def load(self) -> dict:
        d = self.data
        from annotate.signature import load

        try:
            saved = load(self.out, d.action, d.model, d.n_frames, d.family, d.rmap)
        except InputError as e:
            return {"saved": None, "load_error": str(e)}
        return {"saved": saved, "load_error": None}

    def save(self, body: dict) -> dict:
        from annotate.signature import entry, save

        d = self.data
        try:
            fr, start, end = int(body["fr_id"]), int(body["start"]), int(body["end"])
            pairs = np.asarray(body.get("pairs", []), np.int64).reshape(-1, 2)
        except (KeyError, TypeError, ValueError) as e:
            raise InputError("request", "body", f"expected fr_id, start, end, pairs: {e}") from None
        if not start <= fr <= end:
            raise InputError(self.out, f"{d.action}.start_fr/end_fr",
                             f"the contact frame {fr} is outside the interval {start}..{end}", fr)
        conv = self.conversion() if d.family == "anny" else None
        e = entry(d.model, d.rmap, d.family, fr, (start, end), pairs,
                  annotator=str(body.get("annotator") or self.annotator), conversion=conv)
        save(self.out, d.action, e, d.model, d.n_frames, d.family, d.rmap,
             target=None if conv is None else (conv[1], conv[2]))
        self.log(f"annotate: saved {len(pairs)} facet pairs, interval {start}..{end}, contact "
                 f"frame {fr} to {self.out}")
        return {"ok": True, "path": str(self.out), **self.load()}

    # ---------------------------------------------------------------- session
    def session(self) -> dict:
        d = self.data
        return {
            "sequence": d.seq_id, "action": d.action, "session": d.recipe.session,
            "n_frames": int(d.n_frames), "frame": self.frame, "frame_given": self.frame_given,
            "cameras": d.cameras,
            "has_video": bool(d.cams), "has_fits": d.has_fits,
            "fit_frames": None if d.fits is None else [int(d.fits.frames[0]), int(d.fits.frames[-1])],
            "has_keypoints": d.keypoints is not None,
            "people": d.people, "markerless": d.seq.markers_on is None,
            "model": {"name": d.model.name, "num_vertices": int(d.model.num_vertices),
                      "num_faces": int(len(d.model.faces))},
            "family": d.family, "regions": list(d.rmap.names),
            "face_region": np.asarray(d.rmap.face_region).tolist(),
            "out": str(self.out), "annotator": self.annotator, **self.load(),
        }


def make_handler(app: Annotator):
    class Handler(BaseHTTPRequestHandler):
        server_version = "annotate/1"

        def log_message(self, fmt, *args):  # quiet: one line per error only
            pass

        def _send(self, code: int, body: bytes, ctype: str) -> None:
            self.send_response(code)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def _json(self, obj, code: int = 200) -> None:
            self._send(code, json.dumps(obj).encode(), "application/json")

        def _file(self, path: Path) -> None:
            if not path.is_file():
                self._json({"error": f"not found: {self.path}"}, 404)
                return
            ctype = mimetypes.guess_type(path.name)[0] or "application/octet-stream"
            if path.suffix == ".js":
                ctype = "text/javascript"
            self._send(200, path.read_bytes(), ctype)

        def _local(self) -> bool:
            """Only requests addressed to this server by a local name (no DNS rebinding)."""
            host = (self.headers.get("Host") or "").rsplit(":", 1)[0].strip("[]")
            if host in LOCAL_HOSTS:
                return True
            self._json({"error": f"refused: Host {self.headers.get('Host')!r} is not local"}, 403)
            return False

        def do_GET(self):  # noqa: N802 (http.server's name)
            if not self._local():
                return
            u = urllib.parse.urlsplit(self.path)
            q = urllib.parse.parse_qs(u.query)
            route = urllib.parse.unquote(u.path)
            try:
                if route in ("/", "/index.html"):
                    self._file(WEB / "index.html")
                elif route.startswith("/static/"):
                    name = route[len("/static/"):]
                    if "/" in name or name.startswith("."):
                        self._json({"error": "not found"}, 404)
                    else:
                        self._file(WEB / name)
                elif route.startswith("/vendor/"):
                    rel = route[len("/vendor/"):]
                    if ".." in rel.split("/") or not rel.startswith(VENDOR_ALLOWED):
                        self._json({"error": "not found"}, 404)
                    else:
                        self._file(VENDOR / rel)
                elif route == "/api/session":
                    self._json(app.session())
                elif route == "/api/load":
                    self._json(app.load())
                elif route == "/api/proposal":
                    self._json(app.proposal)
                elif route == "/api/faces.bin":
                    self._send(200, np.ascontiguousarray(app.data.model.faces, "<i4").tobytes(),
                               "application/octet-stream")
                elif route == "/api/mesh.bin":
                    frame = None if q.get("rest") == ["1"] or "frame" not in q else int(q["frame"][0])
                    V = np.ascontiguousarray(app.data.vertices(frame), "<f4")
                    self.send_response(200)
                    body = V.tobytes()
                    self.send_header("Content-Type", "application/octet-stream")
                    self.send_header("Content-Length", str(len(body)))
                    mf = app.data.mesh_frame(frame) if frame is not None else None
                    self.send_header("X-Mesh-Frame", "rest" if mf is None else str(mf))
                    self.send_header("Cache-Control", "no-store")
                    self.end_headers()
                    self.wfile.write(body)
                elif route == "/api/views.jpg":
                    if not app.data.cams:
                        self._json({"error": "the sequence has no video"}, 404)
                        return
                    self._send(200, app.data.views_jpeg(int(q.get("frame", ["0"])[0])), "image/jpeg")
                else:
                    self._json({"error": f"not found: {route}"}, 404)
            except InputError as e:
                self._json({"error": str(e)}, 400)
            except (ValueError, KeyError) as e:
                self._json({"error": f"bad request {self.path}: {e}"}, 400)
            except (BrokenPipeError, ConnectionResetError):
                pass

        def do_POST(self):  # noqa: N802
            if not self._local():
                return
            route = urllib.parse.urlsplit(self.path).path
            # JSON only: another site's page cannot send that without a CORS preflight, which
            # this server never grants, so it cannot write the file behind the annotator's back
            if (self.headers.get("Content-Type") or "").split(";")[0].strip() != "application/json":
                self._json({"error": "POST /api/save: Content-Type must be application/json"}, 415)
                return
            if route != "/api/save":
                self._json({"error": f"not found: {route}"}, 404)
                return
            try:
                n = int(self.headers.get("Content-Length", "0"))
                body = json.loads(self.rfile.read(n) or b"{}")
                if not isinstance(body, dict):
                    raise InputError("request", "body", "expected a JSON object")
                self._json(app.save(body))
            except InputError as e:
                app.log(f"annotate: save refused: {e}")
                self._json({"error": str(e)}, 400)
            except json.JSONDecodeError as e:
                self._json({"error": f"request body: not JSON: {e}"}, 400)

    return Handler


def default_out(data, outputs: Path) -> Path:
    if data.seq.contact is not None:
        return Path(data.seq.contact)
    return Path(outputs) / data.recipe.session / data.group / "annotate" / "interaction_contact_signature.json"


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m annotate", description=__doc__.split("\n\n")[0])
    ap.add_argument("--recipe", type=Path, required=True)
    ap.add_argument("--seq", required=True, help="<group>/<action>")
    ap.add_argument("--frame", type=int, default=None, help="the frame shown first")
    ap.add_argument("--port", type=int, default=8765, help="0: any free port")
    ap.add_argument("--out", type=Path, default=None,
                    help="the interaction_contact_signature.json to write (default: the recipe's "
                         "contact file of the sequence)")
    ap.add_argument("--annotator", default=os.environ.get("USER", ""))
    ap.add_argument("--outputs", type=Path, default=Path(os.environ.get("PIPELINE_OUTPUTS", "outputs")))
    ap.add_argument("--no-proposals", action="store_true")
    return ap


def serve(args) -> int:
    from annotate.data import SequenceData
    from recipes.schema import RecipeError

    if not (VENDOR / "three" / "build" / "three.module.js").is_file():
        print(f"annotate: three.js is not installed under {VENDOR} (run `make setup`)", file=sys.stderr)
        return 2
    try:
        data = SequenceData(args.recipe, args.seq, args.outputs)
    except (InputError, RecipeError) as e:
        print(f"annotate: {e}", file=sys.stderr)
        return 2
    out = args.out or default_out(data, args.outputs)
    app = Annotator(data, out, args.annotator, args.frame, proposals=not args.no_proposals)
    try:
        httpd = ThreadingHTTPServer(("127.0.0.1", args.port), make_handler(app))
    except OSError as e:
        print(f"annotate: cannot listen on 127.0.0.1:{args.port}: {e.strerror} (PORT=0: any free "
              "port)", file=sys.stderr)
        data.close()
        return 2
    httpd.daemon_threads = True
    print(f"annotate: {data.seq_id}: {data.n_frames} frames, fits {'yes' if data.has_fits else 'no'}, "
          f"keypoints {'yes' if data.keypoints is not None else 'no'}; file {out}", flush=True)
    print(f"annotate: open http://127.0.0.1:{httpd.server_address[1]}/ (Ctrl-C to stop)", flush=True)
    try:
        httpd.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        httpd.server_close()
        data.close()
    return 0


def main(argv=None) -> int:
    return serve(parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
