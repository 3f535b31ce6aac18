"""Aravis's fake GigE Vision camera (``Aravis.GvFakeCamera``) in a child process, on loopback.

The child binds GVCP port 3956 on 127.0.0.1 and streams over the real GigE Vision protocol, so
the driver talks to it exactly as to a camera on the network; killing the child is a camera that
vanishes. Only one can listen on 127.0.0.1:3956 at a time, so each test starts its own, with its
own serial number, and stops it on the way out.

Run as a script: ``python tests/support/gv_fake.py SERIAL`` prints ``READY`` once the camera listens
and serves until its stdin closes or it is killed.

The fake's test pattern (Aravis 0.8 ``arvfakecamera.c``, ``diagonal_ramp``): with
``scale = 1 + gain + log10(exposure_us / 10000)``, pixel (x, y) of frame ``id`` (x, y counted
from the region's corner) is ``((x + y + id) % 255) * scale`` in Mono8 and
``((256 * (x + y + id)) % 65535) * scale`` in Mono16, clamped to the format's range.
"""

from __future__ import annotations

import contextlib
import os
import select
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

ADDRESS = "127.0.0.1"
START_TIMEOUT_S = 10.0
SENSOR_SIZE = (2048, 2048)  # ARV_FAKE_CAMERA_SENSOR_WIDTH/HEIGHT
DEFAULT_SIZE = (512, 512)  # ARV_FAKE_CAMERA_WIDTH/HEIGHT_DEFAULT


def expected_pattern(frame_id: int, width: int, height: int, bit_depth: int = 8,
                     exposure_us: float = 10000.0, gain: float = 0.0) -> np.ndarray:
    """The fake camera's documented diagonal ramp for one frame, (height, width)."""
    scale = 1.0 + gain + np.log10(exposure_us / 10000.0)
    yy, xx = np.mgrid[:height, :width].astype(np.int64)
    if bit_depth == 8:
        return np.clip(((xx + yy + frame_id) % 255) * scale, 0, 255).astype(np.uint8)
    return np.clip(((256 * (xx + yy + frame_id)) % 65535) * scale, 0, 65535).astype(np.uint16)


@dataclass
class FakeGvCamera:
    """A running fake camera: its serial number, address and child process."""

    serial: str
    address: str
    process: subprocess.Popen

    def kill(self) -> None:
        """Make the camera vanish at once (SIGKILL), as a pulled cable would."""
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait(timeout=5)


@contextlib.contextmanager
def running_fake_camera(serial: str) -> Iterator[FakeGvCamera]:
    """Start the fake camera ``serial`` in a child process; stop it when the block exits."""
    process = subprocess.Popen(
        [sys.executable, os.path.abspath(__file__), serial],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )
    try:
        _wait_ready(process, serial)
        yield FakeGvCamera(serial, ADDRESS, process)
    finally:
        if process.poll() is None:
            process.stdin.close()  # the child exits when its stdin closes
            try:
                process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=5)
        process.stdout.close()


def _wait_ready(process: subprocess.Popen, serial: str) -> None:
    """Block until the child prints READY; RuntimeError with its output if it fails or is late."""
    fd = process.stdout.fileno()
    output = b""
    deadline = time.monotonic() + START_TIMEOUT_S
    while b"READY\n" not in output:
        remaining = deadline - time.monotonic()
        ready, _, _ = select.select([fd], [], [], max(0.0, remaining))
        chunk = os.read(fd, 4096) if ready else b""
        if not chunk:
            process.kill()
            process.wait(timeout=5)
            why = "did not start in time" if not ready else f"exited with {process.returncode}"
            raise RuntimeError(f"fake GigE camera {serial} {why}; output:\n"
                               f"{output.decode(errors='replace')}")
        output += chunk


def _serve(serial: str) -> int:
    """Child: run the fake camera until stdin closes."""
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    camera = Aravis.GvFakeCamera.new(ADDRESS, serial)
    deadline = time.monotonic() + START_TIMEOUT_S
    while not camera.is_running():
        if time.monotonic() > deadline:
            print(f"fake camera did not start listening on {ADDRESS}", flush=True)
            return 1
        time.sleep(0.01)
    print("READY", flush=True)
    sys.stdin.buffer.read()
    del camera
    return 0


if __name__ == "__main__":
    sys.exit(_serve(sys.argv[1]))
