"""Shared fixtures: a real X server (Debian's Xvfb) for display tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.support.xvfb import XVFB_SCREEN, XvfbServer, start_xvfb


@pytest.fixture(scope="session")
def xvfb_display() -> Iterator[XvfbServer]:
    """A session-wide Xvfb screen of ``XVFB_SCREEN``; ``DISPLAY`` points at it while it runs.
    Fails (never skips) when Xvfb is missing."""
    with start_xvfb(*XVFB_SCREEN) as server, pytest.MonkeyPatch.context() as patch:
        patch.setenv("DISPLAY", server.display)
        patch.delenv("WAYLAND_DISPLAY", raising=False)
        yield server
