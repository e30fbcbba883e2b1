"""Headless Chromium driven over the DevTools protocol: the viewer's tests and
``experiments/view.py`` load the page, set lights and read the canvas back as a person's browser
shows it. Needs a ``chromium`` (or ``chromium-browser``, ``google-chrome``) on the PATH and the
``websocket-client`` package (the ``test`` extra); :func:`find_chromium` says why not when not.
"""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

from ..errors import TorchspecError

__all__ = ["BrowserError", "Browser", "find_chromium"]

NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = (
    "--headless=new",
    "--no-sandbox",  # root in a container has no user namespace for the sandbox
    "--use-angle=swiftshader",  # WebGL2 without a GPU
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-background-timer-throttling",
    "--disable-renderer-backgrounding",
    "--hide-scrollbars",
)


class BrowserError(TorchspecError):
    """Chromium could not be started or driven, or the page reported an error."""


def find_chromium() -> tuple[str | None, str]:
    """``(executable, "")``, or ``(None, why)`` when no browser or no websocket client is found."""
    try:
        import websocket  # noqa: F401
    except ImportError:
        return None, "the websocket-client package is not installed (pip install torchspec[test])"
    for name in NAMES:
        found = shutil.which(name)
        if found:
            return found, ""
    return None, f"no headless browser on the PATH (looked for {', '.join(NAMES)}; apt-get install chromium)"


class Browser:
    """One headless Chromium with one page, a ``width x height`` viewport at device scale 1.

    Use as a context manager; :meth:`call` sends a DevTools command, :meth:`evaluate` runs
    JavaScript (awaiting a promise) and returns its JSON value.
    """

    def __init__(self, width: int = 800, height: int = 600, timeout: float = 60.0):
        executable, why = find_chromium()
        if executable is None:
            raise BrowserError(why)
        import websocket

        self.timeout = timeout
        self.profile = tempfile.mkdtemp(prefix="torchspec-chromium-")
        self.process = subprocess.Popen(
            [executable, *FLAGS, "--remote-debugging-port=0", f"--user-data-dir={self.profile}",
             f"--window-size={width},{height}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            port = self._port()
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as answer:
                pages = [t for t in json.load(answer) if t.get("type") == "page"]
            self.socket = websocket.create_connection(
                pages[0]["webSocketDebuggerUrl"], timeout=timeout, suppress_origin=True
            )
        except Exception:
            self.close()
            raise
        self.next_id = 0
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)

    def _port(self) -> int:
        file = Path(self.profile) / "DevToolsActivePort"
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            if file.exists() and file.read_text().strip():
                return int(file.read_text().split()[0])
            if self.process.poll() is not None:
                raise BrowserError(f"chromium exited with status {self.process.returncode} before it listened")
            time.sleep(0.05)
        raise BrowserError(f"chromium did not open its DevTools port in {self.timeout:g} s")

    def call(self, method: str, **params) -> dict:
        """Send a DevTools command and return its result (events in between are dropped)."""
        self.next_id += 1
        self.socket.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            message = json.loads(self.socket.recv())
            if message.get("id") == self.next_id:
                if "error" in message:
                    raise BrowserError(f"{method}: {message['error'].get('message')}")
                return message.get("result", {})

    def evaluate(self, expression: str):
        """The JSON value of ``expression`` (a promise is awaited); a thrown error raises."""
        result = self.call("Runtime.evaluate", expression=expression, awaitPromise=True, returnByValue=True)
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            text = details.get("exception", {}).get("description") or details.get("text")
            raise BrowserError(f"the page raised: {text}")
        return result["result"].get("value")

    def open(self, url: str) -> None:
        """Load ``url`` and wait for the viewer to be ready (``window.torchspecView.ready``)."""
        self.call("Page.navigate", url=url)
        deadline = time.monotonic() + self.timeout
        while not self.evaluate("document.readyState === 'complete' && 'torchspecView' in window"):
            if time.monotonic() > deadline:
                raise BrowserError(f"{url} did not load in {self.timeout:g} s")
            time.sleep(0.02)
        self.evaluate("torchspecView.ready.then(() => true)")

    def show(self, **options) -> dict:
        """Set the page's view (``torchspecView.show``: ``light``, ``layer``, ``exposure``,
        ``snap``, ``compare``, ``zoom``, ``centre``, ``origin``); returns what it shows."""
        return self.evaluate(f"torchspecView.show({json.dumps(options)})")

    def read(self, x: int, y: int, width: int, height: int) -> np.ndarray:
        """The canvas's pixels ``(height, width, 4)`` uint8 from its point ``(x, y)`` (top left),
        once every tile the view wants is drawn."""
        self.evaluate("torchspecView.settle()")
        data = self.evaluate(f"torchspecView.read({x}, {y}, {width}, {height})")
        return np.frombuffer(base64.b64decode(data), dtype=np.uint8).reshape(height, width, 4)

    def screenshot(self, path: str | Path) -> None:
        """The page as a PNG at ``path``, once settled."""
        self.evaluate("torchspecView.settle()")
        Path(path).write_bytes(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"]))

    def close(self) -> None:
        """Stop the browser and remove its profile."""
        socket = getattr(self, "socket", None)
        if socket is not None:
            socket.close()
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
