"""A real X server (Debian's Xvfb) for the display tests: ``start_xvfb`` and the session's
screen size ``XVFB_SCREEN``."""

from __future__ import annotations

import contextlib
import os
import select
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

XVFB_SCREEN = (320, 240, 24)  # width, height, depth of the session's virtual screen
XVFB_START_TIMEOUT_S = 10.0


@dataclass(frozen=True)
class XvfbServer:
    """A running Xvfb: ``display`` is the value for ``DISPLAY`` (':n')."""

    display: str
    width: int
    height: int
    depth: int
    process: subprocess.Popen


def _fail_start(message: str, log: Path) -> None:
    tail = log.read_text(errors="replace")[-2000:] if log.exists() else ""
    pytest.fail(f"{message}\nXvfb output:\n{tail}", pytrace=False)


@contextlib.contextmanager
def start_xvfb(width: int, height: int, depth: int = 24) -> Iterator[XvfbServer]:
    """Run Xvfb with one ``width`` x ``height`` x ``depth`` screen on a free display number
    (chosen by the server itself through ``-displayfd``) until the block exits."""
    executable = shutil.which("Xvfb")
    if executable is None:
        pytest.fail("Xvfb is not on PATH: install Debian's 'xvfb' package to run the display tests",
                    pytrace=False)
    read_fd, write_fd = os.pipe()
    with tempfile.TemporaryDirectory(prefix="xvfb-") as tmp:
        log = Path(tmp) / "xvfb.log"
        with open(log, "wb") as log_file:
            process = subprocess.Popen(
                [executable, "-displayfd", str(write_fd), "-screen", "0", f"{width}x{height}x{depth}",
                 "-nolisten", "tcp", "-noreset"],
                pass_fds=(write_fd,), stdout=log_file, stderr=subprocess.STDOUT,
            )
        os.close(write_fd)
        try:
            number = _read_display_number(read_fd, process, log)
            socket = Path(f"/tmp/.X11-unix/X{number}")
            deadline = time.monotonic() + XVFB_START_TIMEOUT_S
            while not socket.exists():
                if process.poll() is not None or time.monotonic() > deadline:
                    _fail_start(f"Xvfb :{number} did not create {socket}", log)
                time.sleep(0.01)
            yield XvfbServer(f":{number}", width, height, depth, process)
        finally:
            os.close(read_fd)
            process.terminate()
            try:
                process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def _read_display_number(read_fd: int, process: subprocess.Popen, log: Path) -> int:
    """The display number Xvfb writes (followed by a newline) once it accepts connections."""
    data = b""
    deadline = time.monotonic() + XVFB_START_TIMEOUT_S
    while not data.endswith(b"\n"):
        remaining = deadline - time.monotonic()
        ready, _, _ = select.select([read_fd], [], [], max(0.0, remaining))
        if not ready:
            _fail_start(f"Xvfb gave no display number within {XVFB_START_TIMEOUT_S} s", log)
        chunk = os.read(read_fd, 64)
        if not chunk:
            _fail_start(f"Xvfb exited (code {process.wait()}) before giving a display number", log)
        data += chunk
    return int(data)
