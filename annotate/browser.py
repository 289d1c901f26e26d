"""A headless Chromium driven over the DevTools protocol (CDP), for the page's tests and its
screenshot. Stdlib only: Chromium's ``--remote-debugging-pipe`` reads commands on fd 3 and
writes replies and events on fd 4, each a JSON message ending with a NUL byte (no websocket).

    with Chromium() as b:
        b.open("http://127.0.0.1:8765/")
        b.wait_for("document.body.dataset.ready === '1'")
        b.click(*b.center("#view3d-0"))
        b.screenshot("page.png")

The binary is ``qa.report.chromium_path()`` (the QA tests' browser), run with the QA report's
flags (headless, no network services) and a fresh profile, in its own process group; closing
(or a timeout) ends that group.
"""
from __future__ import annotations

import base64
import json
import os
import queue
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from pathlib import Path


class BrowserError(RuntimeError):
    pass


class Chromium:
    def __init__(self, exe: str | None = None, width: int = 1500, height: int = 1000,
                 timeout: float = 30.0):
        from qa.report import CHROMIUM_FLAGS, chromium_path

        exe = exe or chromium_path()
        if exe is None:
            raise FileNotFoundError("chromium is not installed (make browser)")
        self.timeout = timeout
        self.width, self.height = width, height
        self._profile = tempfile.mkdtemp(prefix="annotate-chromium-")
        to_r, self._to_w = os.pipe()      # we write commands, Chromium reads on fd 3
        self._from_r, from_w = os.pipe()  # Chromium writes on fd 4, we read

        def child_fds():
            os.dup2(to_r, 3)
            os.dup2(from_w, 4)

        cmd = [exe, *CHROMIUM_FLAGS, "--remote-debugging-pipe", f"--user-data-dir={self._profile}",
               f"--window-size={width},{height}", "--hide-scrollbars", "about:blank"]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, preexec_fn=child_fds, pass_fds=(3, 4),
                                     start_new_session=True)
        os.close(to_r)
        os.close(from_w)
        self._id = 0
        self._replies: dict[int, queue.Queue] = {}
        self._lock = threading.Lock()
        self.console: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.session = None
        target = self.call("Target.createTarget", {"url": "about:blank"}, session=False)["targetId"]
        self.session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True},
                                 session=False)["sessionId"]
        for domain in ("Page", "Runtime"):
            self.call(f"{domain}.enable")
        self.call("Emulation.setDeviceMetricsOverride", {"width": width, "height": height,
                                                         "deviceScaleFactor": 1, "mobile": False})

    # ---------------------------------------------------------------- protocol
    def _read(self) -> None:
        buf = b""
        while True:
            try:
                chunk = os.read(self._from_r, 1 << 16)
            except OSError:
                break
            if not chunk:
                break
            buf += chunk
            while b"\0" in buf:
                raw, buf = buf.split(b"\0", 1)
                msg = json.loads(raw)
                if "id" in msg:
                    with self._lock:
                        q = self._replies.get(msg["id"])
                    if q is not None:
                        q.put(msg)
                elif msg.get("method") == "Runtime.consoleAPICalled":
                    args = msg["params"].get("args", [])
                    self.console.append(" ".join(str(a.get("value", a.get("description", ""))) for a in args))
                elif msg.get("method") == "Runtime.exceptionThrown":
                    d = msg["params"]["exceptionDetails"]
                    self.console.append("exception: " + str(d.get("exception", {}).get("description", d.get("text"))))

    def call(self, method: str, params: dict | None = None, session: bool = True,
             timeout: float | None = None) -> dict:
        with self._lock:
            self._id += 1
            i = self._id
            q = self._replies[i] = queue.Queue()
        msg = {"id": i, "method": method, "params": params or {}}
        if session and self.session:
            msg["sessionId"] = self.session
        os.write(self._to_w, json.dumps(msg).encode() + b"\0")
        try:
            reply = q.get(timeout=timeout or self.timeout)
        except queue.Empty:
            raise BrowserError(f"chromium: no reply to {method} within {timeout or self.timeout} s") from None
        finally:
            with self._lock:
                self._replies.pop(i, None)
        if "error" in reply:
            raise BrowserError(f"chromium: {method}: {reply['error']}")
        return reply.get("result", {})

    # ---------------------------------------------------------------- page
    def open(self, url: str) -> None:
        self.call("Page.navigate", {"url": url})

    def eval(self, expr: str, await_promise: bool = False):
        r = self.call("Runtime.evaluate", {"expression": expr, "returnByValue": True,
                                           "awaitPromise": await_promise})
        if "exceptionDetails" in r:
            d = r["exceptionDetails"]
            raise BrowserError(f"page: {expr[:80]}: {d.get('exception', {}).get('description', d.get('text'))}")
        return r.get("result", {}).get("value")

    def wait_for(self, expr: str, timeout: float | None = None, what: str = ""):
        """Poll ``expr`` until it is truthy; returns its value."""
        end = time.monotonic() + (timeout or self.timeout)
        guarded = f"(() => {{ try {{ return ({expr}); }} catch (e) {{ return null; }} }})()"
        while time.monotonic() < end:
            v = self.eval(guarded)
            if v:
                return v
            time.sleep(0.1)
        raise BrowserError(f"page: {what or expr} not true within {timeout or self.timeout} s "
                           f"(console: {self.console[-5:]})")

    def center(self, selector: str) -> tuple[float, float]:
        """The viewport coordinates of the centre of the element ``selector``."""
        r = self.eval(f"(() => {{ const r = document.querySelector({json.dumps(selector)})"
                      ".getBoundingClientRect(); return [r.left + r.width / 2, r.top + r.height / 2]; })()")
        if r is None:
            raise BrowserError(f"page: no element {selector}")
        return float(r[0]), float(r[1])

    def click(self, x: float, y: float) -> None:
        """A left click at viewport (x, y), as real mouse events (move, press, release)."""
        self.call("Input.dispatchMouseEvent", {"type": "mouseMoved", "x": x, "y": y})
        for t in ("mousePressed", "mouseReleased"):
            self.call("Input.dispatchMouseEvent", {"type": t, "x": x, "y": y, "button": "left",
                                                   "buttons": 1 if t == "mousePressed" else 0,
                                                   "clickCount": 1})

    def click_element(self, selector: str) -> None:
        self.eval(f"document.querySelector({json.dumps(selector)}).scrollIntoView({{block: 'center'}})")
        self.click(*self.center(selector))

    def screenshot(self, path: str | Path) -> Path:
        png = base64.b64decode(self.call("Page.captureScreenshot", {"format": "png"})["data"])
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(png)
        return path

    # ---------------------------------------------------------------- lifetime
    def close(self) -> None:
        try:
            self.call("Browser.close", session=False, timeout=5)
        except (BrowserError, OSError):
            pass
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.proc.wait()
        for fd in (self._to_w, self._from_r):
            try:
                os.close(fd)
            except OSError:
                pass
        if self.proc.stderr is not None:
            self.proc.stderr.close()
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
