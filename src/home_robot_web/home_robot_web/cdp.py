"""A headless Chromium driven over the DevTools protocol (tests, benchmark, screenshots; no ROS): the project's one
browser driver (the web page's tests and benchmark, the exploration live view's screenshots).

Real clicks and typing go through ``Input.*`` (the page sees trusted events, as from a person);
page state is read with ``Runtime.evaluate``. Needs the ``chromium`` package (Debian); nothing is
downloaded. Every wait has a deadline and raises :class:`BrowserError` when it passes.

Usage::

    with Chromium() as browser:
        page = browser.page(width=390, height=844, mobile=True)
        page.navigate("http://127.0.0.1:8090/")
        page.wait_for("window.hr && hr.connected", 20)
        page.type("#cmd", "give me the bottle"); page.press_enter()
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from typing import Any

from websockets.sync.client import ClientConnection, connect

from home_robot_web.errors import WebUiError


class BrowserError(WebUiError):
    """Chromium is missing, did not start, or a page did not do what was awaited in time."""


def chromium_path() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


class Page:
    """One tab. Not thread-safe (one caller at a time)."""

    def __init__(self, ws: ClientConnection, target_id: str) -> None:
        self._ws, self.target_id, self._seq = ws, target_id, 0

    def call(self, method: str, timeout_s: float = 30.0, **params: Any) -> dict[str, Any]:
        self._seq += 1
        seq = self._seq
        self._ws.send(json.dumps({"id": seq, "method": method, "params": params}))
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserError(f"chromium did not answer {method} within {timeout_s:g} s")
            try:
                msg = json.loads(self._ws.recv(timeout=left))
            except TimeoutError as exc:
                raise BrowserError(f"chromium did not answer {method} within {timeout_s:g} s") from exc
            if msg.get("id") == seq:
                if "error" in msg:
                    raise BrowserError(f"{method}: {msg['error'].get('message', msg['error'])}")
                return msg.get("result", {})

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression (JSON-able), awaited if it is a promise."""
        res = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in res:
            raise BrowserError(f"{expression[:80]!r} threw: {res['exceptionDetails'].get('text')} "
                               f"{res['exceptionDetails'].get('exception', {}).get('description', '')[:200]}")
        return res.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout_s: float, interval_s: float = 0.02) -> Any:
        """Poll ``expression`` until it is truthy; returns its value. Raises BrowserError after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            value = self.evaluate(expression)
            if value:
                return value
            if time.monotonic() > deadline:
                raise BrowserError(f"not true within {timeout_s:g} s: {expression}")
            time.sleep(interval_s)

    def navigate(self, url: str, timeout_s: float = 30.0) -> None:
        self.call("Page.navigate", url=url, timeout_s=timeout_s)
        self.wait_for("document.readyState === 'complete'", timeout_s)

    def set_viewport(self, width: int, height: int, mobile: bool = False, scale: float = 1.0) -> None:
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=scale,
                  mobile=mobile)
        if mobile:
            self.call("Emulation.setTouchEmulationEnabled", enabled=True, maxTouchPoints=5)

    def center_of(self, selector: str) -> tuple[float, float]:
        box = self.evaluate(f"(() => {{ const e = document.querySelector({json.dumps(selector)}); if (!e) return null;"
                            " e.scrollIntoView({block: 'center'}); const r = e.getBoundingClientRect();"
                            " return [r.left + r.width / 2, r.top + r.height / 2]; })()")
        if box is None:
            raise BrowserError(f"no element {selector!r} on the page")
        return float(box[0]), float(box[1])

    def click(self, selector: str) -> float:
        """A real mouse click in the middle of ``selector``. Returns ``time.monotonic()`` just before the
        button is released (when the browser fires ``click``)."""
        x, y = self.center_of(selector)
        self.call("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y)
        self.call("Input.dispatchMouseEvent", type="mousePressed", x=x, y=y, button="left", clickCount=1)
        t0 = time.monotonic()
        self.call("Input.dispatchMouseEvent", type="mouseReleased", x=x, y=y, button="left", clickCount=1)
        return t0

    def type(self, selector: str, text: str) -> None:
        """Focus ``selector``, clear it and type ``text``."""
        self.evaluate(f"(() => {{ const e = document.querySelector({json.dumps(selector)}); e.focus(); "
                      "e.value = ''; })()")
        self.call("Input.insertText", text=text)

    def press_enter(self) -> None:
        for kind in ("keyDown", "keyUp"):
            self.call("Input.dispatchKeyEvent", type=kind, key="Enter", code="Enter", windowsVirtualKeyCode=13,
                      text="\r" if kind == "keyDown" else "")

    def text(self, selector: str) -> str:
        return self.evaluate(f"(document.querySelector({json.dumps(selector)}) || {{}}).textContent || ''")

    def screenshot(self, path: str, timeout_s: float = 30.0) -> None:
        """Save what the tab shows as a PNG."""
        data = self.call("Page.captureScreenshot", timeout_s=timeout_s, format="png")["data"]
        with open(path, "wb") as fh:
            fh.write(base64.b64decode(data))

    def close(self) -> None:
        try:
            self._ws.close()
        except Exception:  # closing a tab that chromium already closed
            pass


class Chromium:
    """A headless Chromium with its own empty profile, removed at :meth:`close`.

    Args:
        start_timeout_s: longest wait for its DevTools port.
        webgl: draw WebGL in software (SwiftShader), for pages with a 3-D scene on a machine without a GPU.
    """

    def __init__(self, start_timeout_s: float = 60.0, webgl: bool = False) -> None:
        exe = chromium_path()
        if exe is None:
            raise BrowserError("no chromium on the PATH (Debian: apt-get install chromium)")
        self._profile = tempfile.mkdtemp(prefix="home_robot_web_chromium_")
        self._proc = subprocess.Popen(
            [exe, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run", "--no-default-browser-check",
             "--disable-extensions", "--disable-background-networking", "--disable-sync", "--mute-audio",
             "--remote-debugging-port=0", "--remote-debugging-address=127.0.0.1", "--remote-allow-origins=*",
             *(("--enable-unsafe-swiftshader", "--use-angle=swiftshader") if webgl else ()),
             f"--user-data-dir={self._profile}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            env={**os.environ, "TMPDIR": self._profile})  # its singleton socket folder goes with the profile
        self._pages: list[Page] = []
        port_file = os.path.join(self._profile, "DevToolsActivePort")
        deadline = time.monotonic() + start_timeout_s
        self.port = 0
        while time.monotonic() < deadline and self._proc.poll() is None:
            try:
                with open(port_file) as fh:
                    self.port = int(fh.readline().strip() or 0)
            except (OSError, ValueError):
                pass
            if self.port:
                break
            time.sleep(0.05)
        if not self.port:
            self.close()
            raise BrowserError(f"chromium did not open its DevTools port within {start_timeout_s:g} s")

    def _json(self, path: str, method: str = "GET") -> Any:
        req = urllib.request.Request(f"http://127.0.0.1:{self.port}{path}", method=method)
        with urllib.request.urlopen(req, timeout=10) as r:
            return json.load(r)

    def page(self, width: int = 1280, height: int = 900, mobile: bool = False) -> Page:
        """A new tab with the given viewport."""
        target = self._json("/json/new?about:blank", method="PUT")
        ws = connect(target["webSocketDebuggerUrl"], max_size=None, open_timeout=10)
        page = Page(ws, target["id"])
        page.call("Page.enable")
        page.call("Runtime.enable")
        page.set_viewport(width, height, mobile)
        self._pages.append(page)
        return page

    def close_page(self, page: Page) -> None:
        """Close the tab, as a person closing it (its websocket to the robot goes away)."""
        page.close()
        with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/json/close/{page.target_id}", timeout=10):
            pass
        self._pages.remove(page)

    def close(self) -> None:
        for page in self._pages:
            page.close()
        self._pages.clear()
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(5)
        shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
