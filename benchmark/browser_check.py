"""Open a report in headless Chromium and say what a reader would find broken: images that do not load,
console errors and uncaught script exceptions; keep a screenshot of the whole page.

Why a browser: a report whose HTML is well formed can still show broken images (a chart written elsewhere, a
path relative to the wrong folder) or log errors, and only a browser says so. It talks the Chrome DevTools
Protocol over a pipe (``--remote-debugging-pipe``: NUL-separated JSON on file descriptors 3 and 4), so it
needs no driver and no websocket package, only a Chromium binary (Debian's ``chromium`` package).
"""
from __future__ import annotations

import base64
import json
import os
import select
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from lumibench.errors import UserError

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
# each image's source and whether it decoded to a picture (complete and of non-zero width)
_IMAGES_JS = ("JSON.stringify(Array.from(document.images).map("
              "i => [i.getAttribute('src'), i.complete && i.naturalWidth > 0]))")


def find_browser() -> str | None:
    """The Chromium binary: ``$LUMIBENCH_CHROMIUM`` if set, else the first of :data:`BROWSERS` on the PATH."""
    env = os.environ.get("LUMIBENCH_CHROMIUM")
    if env:
        return env if shutil.which(env) else None
    return next((b for b in map(shutil.which, BROWSERS) if b), None)


@dataclass
class PageCheck:
    """What the browser saw: every ``<img>`` (source, loaded), the console's errors, the screenshot's path."""
    images: list[tuple[str, bool]] = field(default_factory=list)
    console_errors: list[str] = field(default_factory=list)
    screenshot: Path | None = None

    @property
    def broken_images(self) -> list[str]:
        return [src for src, ok in self.images if not ok]

    @property
    def ok(self) -> bool:
        return not self.broken_images and not self.console_errors


class _Pipe:
    """One Chromium process and its DevTools pipe: send a command, wait for its answer, keep the events."""

    def __init__(self, browser: str, profile: str, timeout: float):
        to_chrome_r, self._w = os.pipe()
        self._r, from_chrome_w = os.pipe()

        def child_fds():  # the protocol's fixed descriptors: Chromium reads 3 and writes 4
            os.dup2(to_chrome_r, 3)
            os.dup2(from_chrome_w, 4)

        self.proc = subprocess.Popen(
            [browser, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run", "--mute-audio",
             "--hide-scrollbars", "--window-size=1440,1000", "--remote-debugging-pipe", f"--user-data-dir={profile}", "about:blank"],
            pass_fds=(3, 4), preexec_fn=child_fds, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self.timeout, self._buf, self._id, self.events = timeout, b"", 0, []

    def call(self, method: str, params: dict | None = None, session: str | None = None) -> dict:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}, **({"sessionId": session} if session else {})}
        os.write(self._w, json.dumps(msg).encode() + b"\0")
        want = self._id
        reply = self.wait(lambda m: m.get("id") == want, f"an answer to {method}")
        if "error" in reply:
            raise UserError(f"Chromium refused {method}: {reply['error'].get('message')}")
        return reply.get("result", {})

    def wait(self, pred, what: str, timeout: float | None = None) -> dict | None:
        """The first message ``pred`` accepts (others are kept as events); None when ``timeout`` is given and
        passes quietly, else a UserError naming ``what``."""
        end = time.monotonic() + (self.timeout if timeout is None else timeout)
        while True:
            while b"\0" in self._buf:
                raw, self._buf = self._buf.split(b"\0", 1)
                m = json.loads(raw)
                if pred(m):
                    return m
                self.events.append(m)
            left = end - time.monotonic()
            if left <= 0:
                if timeout is not None:
                    return None
                raise UserError(f"Chromium sent no {what} within {self.timeout:.0f} s")
            if select.select([self._r], [], [], min(left, 0.1))[0]:
                chunk = os.read(self._r, 1 << 20)
                if not chunk:
                    raise UserError(f"Chromium exited before {what} (exit code {self.proc.poll()})")
                self._buf += chunk

    def close(self) -> None:
        try:
            os.write(self._w, json.dumps({"id": 0, "method": "Browser.close"}).encode() + b"\0")
            self.proc.wait(10)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()
        finally:
            os.close(self._w)
            os.close(self._r)


def check_page(html: str | Path, screenshot: str | Path | None = None, browser: str | None = None,
               timeout: float = 60.0, settle_s: float = 0.5) -> PageCheck:
    """Load ``html`` (a file) in headless Chromium, wait for its load event and ``settle_s`` more, and
    return its images' state and console errors (``console.error``, uncaught exceptions, resources that
    failed to load); a full-page PNG goes to ``screenshot`` when given."""
    page = Path(html)
    if not page.is_file():
        raise UserError(f"{page}: no such report (run `make eval` first, or pass the report.html to check)")
    browser = browser or find_browser()
    if browser is None:
        raise UserError("no Chromium found (install Debian's `chromium` package, or set LUMIBENCH_CHROMIUM)")
    with tempfile.TemporaryDirectory(prefix="lumibench-chromium-") as profile:
        pipe = _Pipe(browser, profile, timeout)
        try:
            target = pipe.call("Target.createTarget", {"url": "about:blank"})["targetId"]
            sid = pipe.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
            for domain in ("Page", "Runtime", "Log"):
                pipe.call(f"{domain}.enable", session=sid)
            pipe.call("Page.navigate", {"url": page.resolve().as_uri()}, sid)
            pipe.wait(lambda m: m.get("method") == "Page.loadEventFired", "load event for the page")
            pipe.wait(lambda m: False, "", timeout=settle_s)  # late console messages
            value = pipe.call("Runtime.evaluate", {"expression": _IMAGES_JS, "returnByValue": True}, sid)
            images = [(str(src), bool(ok)) for src, ok in json.loads(value["result"]["value"])]
            shot = None
            if screenshot is not None:
                data = pipe.call("Page.captureScreenshot", {"format": "png", "captureBeyondViewport": True}, sid)
                shot = Path(screenshot)
                shot.parent.mkdir(parents=True, exist_ok=True)
                shot.write_bytes(base64.b64decode(data["data"]))
        finally:
            pipe.close()
    return PageCheck(images, _errors(pipe.events), shot)


def _errors(events: list[dict]) -> list[str]:
    out = []
    for e in events:
        method, p = e.get("method"), e.get("params", {})
        if method == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
            out.append("console.error: " + " ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", [])))
        elif method == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            out.append("exception: " + str((d.get("exception") or {}).get("description") or d.get("text")))
        elif method == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
            entry = p["entry"]
            out.append(f"{entry.get('source')}: {entry.get('text')}" + (f" ({entry['url']})" if entry.get("url") else ""))
    return out
