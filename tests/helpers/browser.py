"""Headless Chromium for the browser tests: `surfsplat.testing.browser`, skipping the test where no
Chromium is installed."""

from __future__ import annotations

import pytest

from surfsplat.testing.browser import Browser, BrowserUnavailable
from surfsplat.testing.browser import chromium as find_chromium

__all__ = ["Browser", "chromium"]


def chromium() -> str:
    """The browser's executable, or the test skips naming the package to install."""
    try:
        return find_chromium()
    except BrowserUnavailable as err:
        pytest.skip(str(err))
