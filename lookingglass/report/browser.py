"""report.html in headless Chromium: what the page logged, which requests it made, screenshots.

Used by the tests (the report in a real browser) and by `demo` (its summary picture is a screenshot
of the report's first screen). Chromium is driven over the DevTools protocol on a pipe
(`--remote-debugging-pipe`: JSON messages ending in a NUL byte), so no websocket library is needed;
WebGL runs on SwiftShader, Chromium's CPU renderer, so no GPU or display either. Chromium comes from
the system (Debian: `apt-get install chromium`; scripts/setup.sh installs it when it can):
`find_chromium` says whether there is one.
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import select
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "chrome")
WINDOW = (1280, 800)  # the first screen: the README's screenshot, demo's summary.png


def find_chromium() -> str | None:
    """The Chromium (or Chrome) executable: $LOOKINGGLASS_CHROMIUM, else the first on PATH; None
    when there is none."""
    named = os.environ.get("LOOKINGGLASS_CHROMIUM")
    if named:
        return shutil.which(named)
    return next((path for path in map(shutil.which, NAMES) if path), None)


def _high_fd(fd: int, lowest: int = 10) -> int:
    """`fd` moved to a descriptor number >= `lowest` (the original closed)."""
    moved = fcntl.fcntl(fd, fcntl.F_DUPFD, lowest)
    os.close(fd)
    return moved


class Chromium:
    """A headless Chromium process and its DevTools connection (a context manager).

    `call(method, params, session)` sends one command and returns its result; the events that
    arrive meanwhile are kept in `events` (dicts with "method" and "params")."""

    def __init__(self, binary: str | None = None):
        binary = binary or find_chromium()
        if binary is None:
            raise FileNotFoundError("no chromium on PATH (Debian: apt-get install chromium)")
        self._profile = tempfile.TemporaryDirectory(prefix="lookingglass-chromium-")
        to_browser, self._write = os.pipe()
        self._read, from_browser = os.pipe()
        # the browser reads commands on its fd 3 and writes replies on fd 4: a Python trampoline puts
        # the pipe's ends there (from fds of 10 and up, so neither lands on the other) and execs it
        to_browser, from_browser = (_high_fd(fd) for fd in (to_browser, from_browser))
        command = [binary, "--headless", "--no-sandbox", "--remote-debugging-pipe", "--use-angle=swiftshader",
                   "--enable-unsafe-swiftshader", "--hide-scrollbars", "--no-first-run", "--no-default-browser-check",
                   "--disable-extensions", "--disable-sync", "--disable-background-networking",
                   "--disable-component-update", f"--user-data-dir={self._profile.name}", "about:blank"]
        self._log = open(Path(self._profile.name) / "chromium.log", "w+b")  # noqa: SIM115 - closed in close()
        trampoline = "import os, sys; os.dup2(int(sys.argv[1]), 3); os.dup2(int(sys.argv[2]), 4); " \
                     "os.execvp(sys.argv[3], sys.argv[3:])"
        self.process = subprocess.Popen([sys.executable, "-c", trampoline, str(to_browser), str(from_browser), *command],
                                        pass_fds=(to_browser, from_browser), stdin=subprocess.DEVNULL,
                                        stdout=self._log, stderr=subprocess.STDOUT)
        os.close(to_browser)
        os.close(from_browser)
        self._buffer = b""
        self._next_id = 0
        self.events: list[dict] = []

    def __enter__(self) -> "Chromium":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self.process.poll() is None:
            try:
                self.call("Browser.close", timeout=5)
            except (OSError, RuntimeError, TimeoutError):
                pass
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        for fd in (self._read, self._write):
            try:
                os.close(fd)
            except OSError:
                pass
        self._log.close()
        self._profile.cleanup()

    def log_tail(self, lines: int = 15) -> str:
        """The end of Chromium's own output (its errors), for a failure's message."""
        self._log.flush()
        self._log.seek(0)
        return "\n".join(self._log.read().decode(errors="replace").splitlines()[-lines:])

    def call(self, method: str, params: dict | None = None, session: str | None = None,
             timeout: float = 60) -> dict:
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        os.write(self._write, json.dumps(message).encode() + b"\0")
        end = time.monotonic() + timeout
        while True:
            while b"\0" in self._buffer:
                raw, self._buffer = self._buffer.split(b"\0", 1)
                reply = json.loads(raw)
                if reply.get("id") == self._next_id:
                    if "error" in reply:
                        raise RuntimeError(f"{method}: {reply['error']}")
                    return reply.get("result", {})
                if "method" in reply:
                    self.events.append(reply)
            left = end - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"chromium did not answer {method} in {timeout} s")
            if self.process.poll() is not None:
                raise RuntimeError(f"chromium exited ({self.process.returncode}) during {method}:\n{self.log_tail()}")
            if select.select([self._read], [], [], min(left, 0.5))[0]:
                chunk = os.read(self._read, 1 << 20)
                if not chunk:
                    raise RuntimeError(f"chromium closed its DevTools pipe during {method}:\n{self.log_tail()}")
                self._buffer += chunk


@dataclass
class PageLoad:
    """log: the page's own record (#lg-log: errors, rendered, layers, resources, canvas rect);
    requests: the URLs the page requested besides itself and its data: URIs (the Network domain);
    console: the page's console errors, uncaught exceptions and the browser's error log entries
    (a blocked request, a failed load); screen: PNG screenshot of the first screen; canvas: PNG of
    the 3D view's WebGL drawing alone (read back from the canvas); view: PNG screenshot of the 3D
    view as shown (the drawing with the controls over it)."""

    log: dict
    requests: list[str] = field(default_factory=list)
    console: list[str] = field(default_factory=list)
    screen: bytes = b""
    canvas: bytes = b""
    view: bytes = b""


def load_page(html: str | Path, binary: str | None = None, size: tuple[int, int] = WINDOW,
              timeout: float = 120) -> PageLoad:
    """Open `html` in headless Chromium at `size` (CSS pixels, scale 1), wait until its 3D view has
    drawn every mesh (or `timeout` seconds, or an error), and return what happened."""
    url = Path(html).resolve().as_uri()
    with Chromium(binary) as browser:
        target = browser.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = browser.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        for domain in ("Page", "Runtime", "Network", "Log"):
            browser.call(f"{domain}.enable", session=session)
        browser.call("Emulation.setDeviceMetricsOverride", {"width": size[0], "height": size[1],
                                                            "deviceScaleFactor": 1, "mobile": False}, session=session)
        browser.call("Page.navigate", {"url": url}, session=session)

        def evaluate(expression: str):
            result = browser.call("Runtime.evaluate", {"expression": expression, "returnByValue": True},
                                  session=session)
            return result.get("result", {}).get("value")

        end = time.monotonic() + timeout
        while time.monotonic() < end:
            state = evaluate("document.readyState !== 'complete' ? 'loading' : !window.lgLog ? 'no report' : "
                             "lgLog.errors.length ? 'failed' : lgLog.rendered ? 'drawn' : 'drawing'")
            if state in ("drawn", "failed", "no report"):
                break
            time.sleep(0.25)
        log = json.loads(evaluate("JSON.stringify(window.lgLog || {})") or "{}")
        screen = base64.b64decode(browser.call("Page.captureScreenshot", {"format": "png"}, session=session)["data"])
        pixels = evaluate("(function () { var c = document.getElementById('lg-canvas');"
                          " return c ? c.toDataURL('image/png') : ''; })()") or ""
        canvas = base64.b64decode(pixels.split(",", 1)[1]) if pixels.startswith("data:image/png;base64,") else b""
        view = b""
        rect = evaluate("(function () { var c = document.getElementById('lg-canvas'); if (!c) return null;"
                        " var r = c.getBoundingClientRect(); return [r.left, r.top, r.width, r.height]; })()")
        if rect and rect[2] >= 1 and rect[3] >= 1:
            clip = {"x": rect[0], "y": rect[1], "width": rect[2], "height": rect[3], "scale": 1}
            view = base64.b64decode(browser.call("Page.captureScreenshot", {"format": "png", "clip": clip},
                                                 session=session)["data"])
        events = [e for e in browser.events if e.get("sessionId") == session]
    requests, console = [], []
    for event in events:
        method, params = event["method"], event.get("params", {})
        if method == "Network.requestWillBeSent":
            requested = params["request"]["url"]
            if requested != url and not requested.startswith(("data:", "about:")):
                requests.append(requested)
        elif method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
            console.append("console." + params["type"] + ": " + " ".join(
                str(a.get("value", a.get("description", ""))) for a in params.get("args", [])))
        elif method == "Runtime.exceptionThrown":
            details = params.get("exceptionDetails", {})
            console.append("uncaught: " + str(details.get("exception", {}).get("description", details.get("text"))))
        elif method == "Log.entryAdded" and params.get("entry", {}).get("level") == "error":
            entry = params["entry"]
            console.append(f"{entry.get('source')}: {entry.get('text')} {entry.get('url', '')}".strip())
    return PageLoad(log, requests, console, screen, canvas, view)


def screenshot(html: str | Path, png: str | Path, binary: str | None = None, size: tuple[int, int] = WINDOW,
               timeout: float = 120) -> Path:
    """Write a PNG of the first `size` pixels of `html` once its 3D view has drawn; returns its path."""
    from ..fileio import write_atomic

    load = load_page(html, binary, size, timeout)
    Path(png).parent.mkdir(parents=True, exist_ok=True)
    return write_atomic(png, lambda tmp: Path(tmp).write_bytes(load.screen))
