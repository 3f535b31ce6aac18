"""Zaber ASCII protocol as pure functions: format and parse commands and replies, LRC checksums.

Lines are handled as ``str`` without their terminator; the caller adds ``"\\n"`` when writing
and strips ``"\\r\\n"`` after reading. Positions and speeds stay in device units here.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.errors import DeviceError, DeviceSettingError

SPEED_UNIT = 1.6384  # device ``maxspeed`` value per µstep/s: µsteps/s = value / SPEED_UNIT
ACCEL_UNIT = 1.6384 / 10000  # device ``accel`` value per µstep/s²: µsteps/s² = value / ACCEL_UNIT
NO_WARNING = "--"
FLAGS = ("OK", "RJ")
STATUSES = ("BUSY", "IDLE")


class ZaberFormatError(DeviceError, ValueError):
    """A line that is not a well-formed Zaber ASCII message."""


class ZaberChecksumError(ZaberFormatError):
    """A message whose ``:CC`` checksum does not match its content."""


def lrc(payload: str) -> int:
    """LRC of ``payload`` (the text after the leading ``/@!#`` up to ``:``): ``(-sum) mod 256``."""
    return (-sum(payload.encode("ascii"))) & 0xFF


def append_checksum(line: str) -> str:
    """Return ``line`` (starting with ``/``, ``@``, ``!`` or ``#``) with ``:CC`` appended."""
    return f"{line}:{lrc(line[1:]):02X}"


def split_checksum(line: str) -> tuple[str, int | None]:
    """Split ``line`` into (message without checksum, checksum or None when it carries none)."""
    head, sep, tail = line.rpartition(":")
    if sep and len(tail) == 2 and all(c in "0123456789abcdefABCDEF" for c in tail):
        return head, int(tail, 16)
    return line, None


def checksum_ok(line: str) -> bool | None:
    """True/False when ``line`` carries a checksum that matches/does not; None when it has none."""
    head, cc = split_checksum(line)
    if cc is None:
        return None
    return lrc(head[1:]) == cc


@dataclass(frozen=True)
class Command:
    """A parsed host command ``/[addr] [axis] [id] text``; 0 means all devices / whole device."""

    address: int
    axis: int
    msg_id: int | None
    text: str  # command and arguments, e.g. "move abs 10000"; "" for a bare status request


def format_command(
    text: str,
    *,
    address: int = 1,
    axis: int = 0,
    msg_id: int | None = None,
    checksum: bool = False,
) -> str:
    """Format ``/address axis [id] text[:CC]`` (no terminator)."""
    if not 0 <= address <= 99:
        raise DeviceSettingError(f"Zaber address must be 0-99, got {address}")
    if not 0 <= axis <= 9:
        raise DeviceSettingError(f"Zaber axis must be 0-9, got {axis}")
    if msg_id is not None and not 0 <= msg_id <= 99:
        raise DeviceSettingError(f"Zaber message id must be 0-99, got {msg_id}")
    parts = [f"/{address}", str(axis)]
    if msg_id is not None:
        parts.append(f"{msg_id:02d}")
    if text:
        parts.append(text)
    line = " ".join(parts)
    return append_checksum(line) if checksum else line


def _body(line: str, lead: str, what: str) -> str:
    """The text of a stripped message ``line`` after its ``lead`` character and before any
    checksum; ZaberFormatError / ZaberChecksumError quoting the line."""
    if not line.startswith(lead):
        raise ZaberFormatError(f"not a Zaber {what}: {line!r}")
    if not line.isascii():
        raise ZaberFormatError(f"non-ASCII characters in Zaber {what}: {line!r}")
    if checksum_ok(line) is False:
        raise ZaberChecksumError(f"bad checksum in {line!r}")
    return split_checksum(line)[0][1:]


def parse_command(line: str) -> Command:
    """Parse a host command line; raise ZaberFormatError / ZaberChecksumError."""
    line = line.strip()
    tokens = _body(line, "/", "command").split()
    numbers: list[int] = []
    while tokens and len(numbers) < 3 and tokens[0].isdigit():
        numbers.append(int(tokens.pop(0)))
    address = numbers[0] if len(numbers) > 0 else 0
    axis = numbers[1] if len(numbers) > 1 else 0
    msg_id = numbers[2] if len(numbers) > 2 else None
    return Command(address, axis, msg_id, " ".join(tokens))


@dataclass(frozen=True)
class Reply:
    """A parsed ``@nn a [id] FL STATUS WW data`` reply."""

    address: int
    axis: int
    msg_id: int | None
    flag: str  # "OK" or "RJ"
    status: str  # "BUSY" or "IDLE"
    warning: str  # top warning, "--" when none
    data: str  # value, "0", or the rejection reason

    @property
    def rejected(self) -> bool:
        return self.flag == "RJ"

    @property
    def busy(self) -> bool:
        return self.status == "BUSY"

    @property
    def fault(self) -> bool:
        """True when the top warning is an ``F*`` fault."""
        return self.warning.startswith("F")


def format_reply(reply: Reply, *, checksum: bool = False) -> str:
    """Format a reply line (no terminator), with ``:CC`` when ``checksum``."""
    parts = [f"@{reply.address:02d}", str(reply.axis)]
    if reply.msg_id is not None:
        parts.append(f"{reply.msg_id:02d}")
    parts += [reply.flag, reply.status, reply.warning, reply.data]
    line = " ".join(parts)
    return append_checksum(line) if checksum else line


def parse_reply(line: str) -> Reply:
    """Parse an ``@`` reply line; verify its checksum when it carries one.

    Raises ZaberChecksumError on a checksum mismatch, ZaberFormatError on anything malformed
    (also a reply without its data field); every message quotes the (stripped) line.
    """
    line = line.strip()
    tokens = _body(line, "@", "reply").split(" ")
    try:
        address = _number(tokens.pop(0), 2, 2, "address")
        axis = _number(tokens.pop(0), 1, 1, "axis")
        msg_id = None if tokens[0] in FLAGS else _number(tokens.pop(0), 1, 2, "message id")
        flag, status, warning, data = tokens[0], tokens[1], tokens[2], " ".join(tokens[3:])
    except IndexError:
        raise ZaberFormatError(f"truncated Zaber reply: {line!r}") from None
    except ValueError as exc:
        raise ZaberFormatError(f"malformed Zaber reply: {line!r} ({exc})") from None
    if flag not in FLAGS or status not in STATUSES or not _is_warning(warning):
        raise ZaberFormatError(f"malformed Zaber reply: {line!r}")
    if not data:
        raise ZaberFormatError(f"truncated Zaber reply (no data field): {line!r}")
    return Reply(address, axis, msg_id, flag, status, warning, data)


def _number(token: str, min_len: int, max_len: int, what: str) -> int:
    """``token`` as a number of ``min_len``-``max_len`` ASCII digits; ValueError naming ``what``."""
    if not (token.isascii() and token.isdigit() and min_len <= len(token) <= max_len):
        raise ValueError(f"expected a {min_len}-{max_len} digit {what}, got {token!r}")
    return int(token)


def _is_warning(token: str) -> bool:
    return token == NO_WARNING or (len(token) == 2 and token.isascii() and token.isupper())
