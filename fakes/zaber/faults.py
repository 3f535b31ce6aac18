"""Fault switches of the fake Zaber controller, set by tests at any time."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Faults:
    """What the fake should get wrong next. Counters count down as the faults are used.

    Reply faults apply to the next replies the device produces; motion faults to the next
    motion (``move abs`` or ``home``) that starts; ``vanish`` is acted on by the transport
    (the pty server closes the pty; the URL port raises ``SerialException`` once).
    """

    drop_replies: int = 0  # replies that are never sent
    drop_on: str | None = None  # drop the reply to the next command containing this text
    delay_replies: int = 0  # replies sent only ``delay_s`` after they are due
    delay_s: float = 1.0
    garble_replies: int = 0  # replies with bit errors (top bit set on the flag bytes)
    bad_checksum_replies: int = 0  # replies with a wrong ``:CC``
    silent: bool = False  # no reply at all while set
    stall_at: float | None = None  # fraction (0-1) of the next motion where it stalls with FS
    stop_short: int = 0  # microsteps the next motion ends short of its target, silently
    idle_glitch: bool = False  # the next status or 'get' reply during motion says IDLE
    info_lines: int = 0  # '#' info lines sent right after the next reply
    alert_lines: int = 0  # '!' alert lines sent unsolicited as soon as the transport polls
    vanish: bool = False  # the connection drops now
    vanish_on: str | None = None  # drop the connection when a command containing this arrives

    def take(self, name: str) -> bool:
        """Use one count of counter ``name``; True when there was one."""
        count = getattr(self, name)
        if count > 0:
            setattr(self, name, count - 1)
            return True
        return False
