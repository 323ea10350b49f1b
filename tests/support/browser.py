"""A headless Chromium driven over the DevTools protocol on a pipe
(--remote-debugging-pipe: JSON messages, NUL-terminated, commands on fd 3,
replies and events on fd 4), so the tests need no browser automation package
and no browser download: Debian's `chromium`, found on PATH."""

from __future__ import annotations

import base64
import contextlib
import json
import os
import select
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def find_browser() -> str | None:
    return next((path for name in BROWSERS if (path := shutil.which(name))), None)


class BrowserError(RuntimeError):
    pass


class Browser:
    """One headless browser with one page; `events` collects what the page
    reports (console messages, exceptions, log entries, failed loads)."""

    def __init__(self, executable: str, timeout: float = 60.0) -> None:
        self.timeout = timeout
        self._profile = tempfile.mkdtemp(prefix="mogaf-browser-")
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        # high numbers first, so the dup2 onto 3 and 4 in the child cannot clobber one another
        high_r, high_w = os.dup(to_browser_r) + 100, os.dup(from_browser_w) + 100
        os.dup2(to_browser_r, high_r)
        os.dup2(from_browser_w, high_w)

        def child_fds() -> None:
            os.dup2(high_r, 3)
            os.dup2(high_w, 4)

        self.proc = subprocess.Popen(
            [
                executable,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--no-first-run",
                "--mute-audio",
                "--autoplay-policy=no-user-gesture-required",
                "--remote-debugging-pipe",
                f"--user-data-dir={self._profile}",
                "--window-size=1280,1600",
                "about:blank",
            ],
            pass_fds=(3, 4, high_r, high_w),
            preexec_fn=child_fds,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for fd in (to_browser_r, from_browser_w, high_r, high_w):
            os.close(fd)
        self._buffer = b""
        self._next_id = 0
        self.events: list[dict[str, Any]] = []
        target = self.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        self._session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        for domain in ("Page", "Runtime", "Log", "Network"):
            self.call(f"{domain}.enable", session=True)

    # ------------------------------------------------------------ protocol
    def _read_message(self, deadline: float) -> dict[str, Any]:
        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._from_browser], [], [], left)[0]:
                raise BrowserError("the browser did not answer in time")
            chunk = os.read(self._from_browser, 1 << 20)
            if not chunk:
                raise BrowserError("the browser closed its pipe (crashed or exited)")
            self._buffer += chunk
        raw, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(raw)

    def call(self, method: str, params: dict[str, Any] | None = None, *, session: bool = False) -> dict[str, Any]:
        self._next_id += 1
        message: dict[str, Any] = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = self._session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + self.timeout
        while True:
            reply = self._read_message(deadline)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise BrowserError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            if "method" in reply:
                self.events.append(reply)

    def _wait_for_event(self, method: str, since: int = 0, **params: Any) -> int:
        """Until an event `method` whose params include `params` (a frame: its
        id) has been seen among the events from index `since` on; its index."""
        deadline = time.monotonic() + self.timeout

        def matches(e: dict[str, Any]) -> bool:
            got = e.get("params", {})
            return e["method"] == method and all(
                (got.get(k) or {}).get("id") == v if k == "frame" else got.get(k) == v for k, v in params.items()
            )

        while True:
            found = [i for i in range(since, len(self.events)) if matches(self.events[i])]
            if found:
                return found[-1]
            message = self._read_message(deadline)
            if "method" in message:
                self.events.append(message)

    # ------------------------------------------------------------ page
    def open(self, url: str) -> None:
        """Load `url` and wait for its load event (what earlier pages reported stays in `events`)."""
        since = len(self.events)
        frame = self.call("Page.navigate", {"url": url}, session=True)["frameId"]
        self._wait_for_event("Page.loadEventFired", since)
        self._wait_for_event("Page.frameStoppedLoading", since, frameId=frame)

    def evaluate(self, expression: str, frame: str | None = None) -> Any:
        """The value of a JavaScript expression (promises awaited), in the
        page or in its child frame `frame` (an id from `child_frames`)."""
        params: dict[str, Any] = {
            "expression": expression,
            "returnByValue": True,
            "awaitPromise": True,
            "timeout": self.timeout * 1000,
        }
        if frame is not None:
            params["contextId"] = self._context_of(frame)
        result = self.call("Runtime.evaluate", params, session=True)
        if "exceptionDetails" in result:
            raise BrowserError(f"script failed: {result['exceptionDetails'].get('text')} {result['result']}")
        return result["result"].get("value")

    def wait_until(self, condition: str, timeout: float | None = None) -> Any:
        """The first truthy value of the JavaScript expression `condition`, polled
        in the page every 20 ms; BrowserError if it stays falsy for `timeout` s."""
        ms = int(1000 * (self.timeout if timeout is None else timeout))
        value = self.evaluate(
            f"""new Promise(done => {{
              const start = Date.now();
              (function poll() {{
                const value = ({condition});
                if (value || Date.now() - start > {ms}) return done(value || null);
                setTimeout(poll, 20);
              }})();
            }})"""
        )
        if not value:
            raise BrowserError(f"still false after {ms} ms: {condition}")
        return value

    def child_frames(self) -> list[tuple[str, str]]:
        """(frame id, url) of the page's child frames (iframes), each loaded."""
        tree = self.call("Page.getFrameTree", session=True)["frameTree"]
        frames = [(c["frame"]["id"], c["frame"].get("url", "")) for c in tree.get("childFrames", [])]
        for frame, _ in frames:
            # its first (about:blank) document also stops loading: wait for the one it navigated to
            navigated = self._wait_for_event("Page.frameNavigated", frame=frame)
            self._wait_for_event("Page.frameStoppedLoading", navigated, frameId=frame)
        return frames

    def _context_of(self, frame: str) -> int:
        """The default JavaScript context of a frame: data: URL frames have an
        opaque origin, so the page's own scripts cannot look inside them."""
        deadline = time.monotonic() + self.timeout
        while True:
            for e in reversed(self.events):
                ctx = e.get("params", {}).get("context", {})
                aux = ctx.get("auxData", {})
                if (
                    e["method"] == "Runtime.executionContextCreated"
                    and aux.get("frameId") == frame
                    and aux.get("isDefault")
                ):
                    return ctx["id"]
            message = self._read_message(deadline)
            if "method" in message:
                self.events.append(message)

    def screenshot(self, path: str | os.PathLike) -> Path:
        data = self.call("Page.captureScreenshot", {"format": "png", "captureBeyondViewport": True}, session=True)
        out = Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(base64.b64decode(data["data"]))
        return out

    def problems(self) -> list[str]:
        """Console errors, uncaught exceptions, error log entries and failed loads seen so far."""
        out = []
        for e in self.events:
            p = e.get("params", {})
            if e["method"] == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                out.append("console: " + " ".join(str(a.get("value", a.get("description", ""))) for a in p["args"]))
            elif e["method"] == "Runtime.exceptionThrown":
                d = p["exceptionDetails"]
                out.append(f"exception: {d.get('text')} {d.get('exception', {}).get('description', '')}")
            elif e["method"] == "Log.entryAdded" and p["entry"]["level"] == "error":
                out.append(f"log: {p['entry']['text']} {p['entry'].get('url', '')}")
            elif e["method"] == "Network.loadingFailed" and not p.get("canceled"):
                out.append(f"load failed: {p.get('errorText')} ({p.get('type')})")
        return out

    def close(self) -> None:
        with contextlib.suppress(BrowserError):
            self.call("Browser.close")
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for fd in (self._to_browser, self._from_browser):
            with contextlib.suppress(OSError):
                os.close(fd)
        shutil.rmtree(self._profile, ignore_errors=True)
