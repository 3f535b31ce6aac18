"""Fake Zaber ASCII stage controller: a device model, a pty server and a pyserial URL handler."""

from fakes.zaber.clock import ManualClock
from fakes.zaber.device import FakeZaberDevice
from fakes.zaber.faults import Faults
from fakes.zaber.motion import Profile
from fakes.zaber.pty import FakeZaberPty
from fakes.zaber.url import FakeZaberSerial, register_url_handler, remove_url_device, url_device

__all__ = [
    "FakeZaberDevice",
    "FakeZaberPty",
    "FakeZaberSerial",
    "Faults",
    "ManualClock",
    "Profile",
    "register_url_handler",
    "remove_url_device",
    "url_device",
]
