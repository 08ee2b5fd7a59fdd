"""Headless Chromium for the viewer tests: find it (installing Debian's package where the tests run
as root, as on CI) and take screenshots of a page with software WebGL."""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

NAMES = ("chromium", "chromium-browser", "google-chrome")
PACKAGE = "chromium"  # Debian's package


def _which() -> str | None:
    return next((shutil.which(n) for n in NAMES if shutil.which(n)), None)


def chromium() -> str:
    """The browser's executable; installed with apt-get when missing and running as root, else the
    test skips naming the package to install."""
    exe = _which()
    if exe is None and hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        install = ["apt-get", "install", "-y", "--no-install-recommends", PACKAGE]
        if subprocess.run(install, capture_output=True, env=env, timeout=900).returncode != 0:
            subprocess.run(["apt-get", "update"], capture_output=True, env=env, timeout=300)
            subprocess.run(install, capture_output=True, env=env, timeout=900)
        exe = _which()
    if exe is None:
        pytest.skip(f"headless Chromium is not installed (Debian: apt-get install {PACKAGE})")
    return exe


def screenshot(
    exe: str,
    url: str,
    path: Path,
    width: int = 800,
    height: int = 600,
    ready: Callable[[np.ndarray], bool] | None = None,
    attempts: int = 3,
) -> np.ndarray:
    """Load `url`, let it run on virtual time (page, websocket, splat sorting and fade-in), and
    return the screenshot [height, width, 3] uint8. WebGL runs on SwiftShader (no GPU needed).

    Virtual time runs ahead of the websocket on a loaded machine, so a page can be captured before
    the scene has arrived: while `ready(image)` is false the page is loaded again with twice the
    time, `attempts` times at most (the last image is returned either way, for the test to judge).
    """
    for attempt in range(attempts):
        command = [
            exe,
            "--headless=new",
            "--no-sandbox",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--hide-scrollbars",
            f"--virtual-time-budget={15000 * 2**attempt}",
            f"--window-size={width},{height}",
            f"--screenshot={path}",
            url,
        ]
        done = subprocess.run(command, capture_output=True, text=True, timeout=180)
        assert done.returncode == 0 and path.is_file(), done.stderr[-1000:]
        image = iio.imread(path)[..., :3]
        if ready is None or ready(image):
            break
    return image
