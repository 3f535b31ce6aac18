"""Aravis for GenICam cameras: loading Aravis 0.8 through PyGObject (or an error naming what
to install), listing the cameras it finds, and probing whether a GigE Vision device still
answers. :class:`drivers.genicam.GenICamCamera` drives one camera through it.
"""

from __future__ import annotations

import socket
import struct
import time
from dataclasses import dataclass
from typing import Any

from drivers.errors import AravisUnavailable

__all__ = ["CameraInfo", "INSTALL_HINT", "list_cameras"]

INSTALL_HINT = (
    "install Debian's gir1.2-aravis-0.8 (Aravis 0.8 and its typelib) and, to build PyGObject "
    "from PyPI, libgirepository1.0-dev libcairo2-dev pkg-config gcc (and python3-dev for "
    "Debian's python3); then `pip install -e '.[genicam]'` (or run scripts/setup.sh)"
)

GVCP_PORT = 3956
PROBE_TIMEOUT_S = 0.2  # a live GigE Vision device answers a register read within this


@dataclass(frozen=True)
class CameraInfo:
    """One device found by :func:`list_cameras`."""

    device_id: str
    vendor: str
    model: str
    serial: str
    protocol: str  # "GigEVision", "USB3Vision", ...
    address: str  # IP address for GigE Vision, else ""


def _aravis() -> Any:
    """The ``Aravis`` module (0.8), or :class:`AravisUnavailable` naming what to install."""
    try:
        import gi
    except ImportError as exc:
        raise AravisUnavailable(f"GenICam cameras need PyGObject (module 'gi'): {INSTALL_HINT}") \
            from exc
    try:
        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ValueError, ImportError) as exc:
        raise AravisUnavailable(f"GenICam cameras need Aravis 0.8 ({exc}): {INSTALL_HINT}") \
            from exc
    return Aravis


def _glib_error() -> type[BaseException]:
    from gi.repository import GLib

    return GLib.Error


def list_cameras() -> list[CameraInfo]:
    """Discover GenICam devices on every Aravis interface (GigE Vision discovery takes ~1 s)."""
    arv = _aravis()
    arv.update_device_list()
    found = []
    for i in range(arv.get_n_devices()):
        found.append(CameraInfo(
            device_id=arv.get_device_id(i) or "", vendor=arv.get_device_vendor(i) or "",
            model=arv.get_device_model(i) or "", serial=arv.get_device_serial_nbr(i) or "",
            protocol=arv.get_device_protocol(i) or "", address=arv.get_device_address(i) or "",
        ))
    return found


def _gvcp_answers(address: str, timeout_s: float) -> bool:
    """True when a GigE Vision device at ``address`` answers a register read (the Version
    register, which any host may read) within ``timeout_s`` seconds."""
    request_id = 0x7A01
    packet = struct.pack(">BBHHHI", 0x42, 0x01, 0x0080, 4, request_id, 0x0000)  # READREG_CMD
    deadline = time.monotonic() + timeout_s
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.connect((address, GVCP_PORT))
            sock.send(packet)
            while (remaining := deadline - time.monotonic()) > 0:
                sock.settimeout(remaining)
                reply = sock.recv(64)
                if len(reply) >= 8 and struct.unpack(">HHHH", reply[:8])[1::2] == (0x0081, request_id):
                    return True
    except OSError:  # refused (nothing listens), unreachable, or timed out
        return False
    return False
