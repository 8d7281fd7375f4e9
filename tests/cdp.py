"""A small Chrome DevTools Protocol client for driving Debian's headless chromium in tests.

Starts ``/usr/bin/chromium`` with a throw-away profile, reads the DevTools port from
``DevToolsActivePort`` and talks to the browser over one websocket (the ``websockets``
package's synchronous client), using flattened sessions for pages::

    with Chromium() as browser:
        page = browser.new_page()
        page.navigate("http://127.0.0.1:8080")
        page.wait_for("document.querySelector('canvas') !== null")
        image = page.screenshot()  # (height, width, 3) uint8
"""

from __future__ import annotations

import base64
import itertools
import json
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
from websockets.sync.client import connect

CHROMIUM = "/usr/bin/chromium"

#: WebGL through SwiftShader; ``--use-gl=swiftshader`` gives a blank scene.
FLAGS = [
    "--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--no-first-run", "--hide-scrollbars", "--mute-audio", "--remote-debugging-port=0",
]


class CDPError(RuntimeError):
    """The browser answered a command with an error, died, or a wait timed out."""


class Chromium:
    """A headless chromium process and a DevTools connection to it.

    Arguments:
        executable: the chromium binary.
        window_size: ``(width, height)`` of pages in pixels.
        start_timeout: seconds to wait for the DevTools endpoint.

    Raises:
        FileNotFoundError: ``executable`` does not exist.
        CDPError: the browser exited or did not open its DevTools port in time.
    """

    def __init__(self, executable: str = CHROMIUM, window_size: tuple[int, int] = (1280, 800),
                 start_timeout: float = 30.0):
        if not Path(executable).exists():
            raise FileNotFoundError(executable)
        self.window_size = window_size
        self.profile = Path(tempfile.mkdtemp(prefix="softbody-chromium-"))
        self.log = open(self.profile / "stderr.log", "w+")
        self.process = subprocess.Popen(
            [executable, *FLAGS, f"--user-data-dir={self.profile}",
             f"--window-size={window_size[0]},{window_size[1]}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=self.log)
        port_file = self.profile / "DevToolsActivePort"
        deadline = time.monotonic() + start_timeout
        while not (port_file.exists() and len(port_file.read_text().splitlines()) >= 2):
            if self.process.poll() is not None:
                self.close()
                raise CDPError(f"chromium exited with status {self.process.returncode}: {self.stderr()}")
            if time.monotonic() > deadline:
                self.close()
                raise CDPError(f"chromium did not open its DevTools port in {start_timeout} s: {self.stderr()}")
            time.sleep(0.05)
        port, path = port_file.read_text().splitlines()[:2]
        self.ws = connect(f"ws://127.0.0.1:{port}{path}", max_size=None, open_timeout=start_timeout)
        self._ids = itertools.count(1)

    def stderr(self) -> str:
        """The browser's error output so far (the last 2000 characters)."""
        self.log.flush()
        self.log.seek(0)
        return self.log.read()[-2000:]

    def send(self, method: str, session: str | None = None, timeout: float = 30.0, **params: Any) -> dict:
        """Send one command and wait for its answer (events in between are dropped).

        Arguments:
            method: e.g. ``"Page.navigate"``.
            session: a page session id from :meth:`new_page`, or ``None`` for the browser.
            timeout: seconds to wait for the answer.
            **params: the command's parameters.

        Returns:
            The command's ``result`` dict.

        Raises:
            CDPError: the browser answered with an error or did not answer in time.
        """
        msg_id = next(self._ids)
        msg = {"id": msg_id, "method": method, "params": params}
        if session is not None:
            msg["sessionId"] = session
        self.ws.send(json.dumps(msg))
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise CDPError(f"no answer to {method} in {timeout} s")
            try:
                reply = json.loads(self.ws.recv(timeout=remaining))
            except TimeoutError:
                continue
            if reply.get("id") == msg_id:
                if "error" in reply:
                    raise CDPError(f"{method} failed: {reply['error']}")
                return reply.get("result", {})

    def new_page(self) -> Page:
        """Open a new tab and attach to it."""
        target = self.send("Target.createTarget", url="about:blank")["targetId"]
        session = self.send("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        page = Page(self, target, session)
        page.send("Page.enable")
        page.send("Runtime.enable")
        page.send("Emulation.setDeviceMetricsOverride", width=self.window_size[0],
                  height=self.window_size[1], deviceScaleFactor=1, mobile=False)
        return page

    def close(self) -> None:
        """Close the connection, end the browser process and delete its profile."""
        ws = getattr(self, "ws", None)
        if ws is not None:
            ws.close()
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.log.close()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Page:
    """One tab of a :class:`Chromium`."""

    def __init__(self, browser: Chromium, target: str, session: str):
        self.browser, self.target, self.session = browser, target, session

    def send(self, method: str, **params: Any) -> dict:
        """Send a command to this page; see :meth:`Chromium.send`."""
        return self.browser.send(method, session=self.session, **params)

    def navigate(self, url: str) -> None:
        """Load ``url``.

        Raises:
            CDPError: the navigation failed (e.g. nothing listens at ``url``).
        """
        result = self.send("Page.navigate", url=url)
        if result.get("errorText"):
            raise CDPError(f"navigating to {url} failed: {result['errorText']}")

    def evaluate(self, expression: str) -> Any:
        """Evaluate a JavaScript expression in the page and return its (JSON) value.

        Raises:
            CDPError: the expression threw.
        """
        result = self.send("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            raise CDPError(f"{expression!r} threw: {result['exceptionDetails'].get('text')} "
                           f"{result['exceptionDetails'].get('exception', {}).get('description', '')}")
        return result.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout: float = 30.0, interval: float = 0.1) -> Any:
        """Poll a JavaScript expression until it is truthy; returns its value.

        Raises:
            CDPError: still falsy after ``timeout`` seconds.
        """
        deadline = time.monotonic() + timeout
        while True:
            value = self.evaluate(expression)
            if value:
                return value
            if time.monotonic() > deadline:
                raise CDPError(f"{expression!r} still false after {timeout} s")
            time.sleep(interval)

    def wait_for_text(self, text: str, timeout: float = 30.0) -> None:
        """Wait until the page's visible text contains ``text``.

        Raises:
            CDPError: not there after ``timeout`` seconds.
        """
        self.wait_for(f"(document.body?.innerText ?? '').includes({json.dumps(text)})", timeout)

    def close(self) -> None:
        """Close the tab."""
        self.browser.send("Target.closeTarget", targetId=self.target)

    def screenshot(self) -> np.ndarray:
        """The page as an ``(height, width, 3)`` uint8 RGB image."""
        data = self.send("Page.captureScreenshot", format="png")["data"]
        return np.asarray(iio.imread(base64.b64decode(data), extension=".png"))[..., :3]
