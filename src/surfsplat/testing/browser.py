"""Headless Chromium for the browser tests and the viewer check script: find it (installing Debian's
package where it runs as root, as on CI) and look at a page with software WebGL through the DevTools protocol.

The page is driven over the DevTools websocket rather than with `--screenshot`: that flag captures
after a budget of *virtual* time, which runs ahead of the viewer's websocket on a loaded machine,
so the capture could come before the scene arrived. Here the test waits in real time until the
page shows what it expects (or a time limit passes) and then captures it.
"""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

import imageio.v3 as iio
import numpy as np

NAMES = ("chromium", "chromium-browser", "google-chrome")
PACKAGE = "chromium"  # Debian's package


def _which() -> str | None:
    return next((shutil.which(n) for n in NAMES if shutil.which(n)), None)


class BrowserUnavailable(RuntimeError):
    """No headless Chromium here (the message names the package to install); tests skip on it."""


def chromium() -> str:
    """The browser's executable; installed with apt-get when missing and running as root, else
    BrowserUnavailable naming the package to install."""
    exe = _which()
    if exe is None and hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        install = ["apt-get", "install", "-y", "--no-install-recommends", PACKAGE]
        if subprocess.run(install, capture_output=True, env=env, timeout=900).returncode != 0:
            subprocess.run(["apt-get", "update"], capture_output=True, env=env, timeout=300)
            subprocess.run(install, capture_output=True, env=env, timeout=900)
        exe = _which()
    if exe is None:
        raise BrowserUnavailable(f"headless Chromium is not installed (Debian: apt-get install {PACKAGE})")
    return exe


class Browser:
    """One headless Chromium showing `url` in one page of width x height CSS pixels (device scale 1).

    The page opens at launch: navigating a blank page elsewhere can move it to another renderer
    process and detach the DevTools session from it."""

    def __init__(self, exe: str, url: str, width: int = 800, height: int = 600) -> None:
        from websockets.sync.client import connect

        self.profile = tempfile.mkdtemp(prefix="surfsplat-chromium-")
        self.process = subprocess.Popen(
            [
                exe,
                "--headless=new",
                "--no-sandbox",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                "--hide-scrollbars",
                "--no-first-run",
                f"--window-size={width},{height}",
                "--remote-debugging-port=0",
                f"--user-data-dir={self.profile}",
                url,
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            port_file = Path(self.profile) / "DevToolsActivePort"
            deadline = time.monotonic() + 60
            while not (port_file.is_file() and port_file.read_text().strip()):
                if time.monotonic() > deadline or self.process.poll() is not None:
                    raise RuntimeError("headless Chromium did not start its DevTools endpoint")
                time.sleep(0.1)
            port = int(port_file.read_text().split()[0])
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=30) as answer:
                page = next(t for t in json.loads(answer.read()) if t["type"] == "page")
            self.socket = connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=30)
            self._id = 0
            self.call(
                "Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False
            )
        except BaseException:
            self.close()
            raise

    def call(self, method: str, **params) -> dict:
        """One DevTools command; events arriving meanwhile are dropped."""
        self._id += 1
        self.socket.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            message = json.loads(self.socket.recv(timeout=60))
            if message.get("id") == self._id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message.get("result", {})

    def capture(self) -> np.ndarray:
        """The page as it is now: [height, width, 3] uint8."""
        data = self.call("Page.captureScreenshot", format="png")["data"]
        return iio.imread(io.BytesIO(base64.b64decode(data)))[..., :3]

    def wait_for(
        self,
        ready: Callable[[np.ndarray], bool],
        settle: float = 2.0,
        steady: bool = True,
        timeout: float = 60.0,
        alike: float = 1.0,
    ) -> np.ndarray:
        """Capture after `settle` seconds, then every second until `ready(image)` holds, with `steady`
        for two captures in a row that are alike (mean absolute difference below `alike`, in 0..255;
        viser fades splats in over several frames after they arrive, and a frame drawn in software
        takes seconds on a loaded machine); after `timeout` seconds the last capture is returned for
        the test to judge."""
        deadline = time.monotonic() + timeout
        time.sleep(settle)
        previous = None
        while True:
            image = self.capture()
            same = not steady or (previous is not None and np.abs(image.astype(int) - previous).mean() < alike)
            if (ready(image) and same) or time.monotonic() > deadline:
                return image
            previous = image.astype(int)
            time.sleep(1.0)

    def close(self) -> None:
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

    def __exit__(self, *exc: object) -> None:
        self.close()
