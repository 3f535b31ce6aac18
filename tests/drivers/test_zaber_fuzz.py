"""Fuzzing (hypothesis) of what reads the wire: the Zaber reply/command parsers, the deadline line
reader, and the driver's reply handling. Whatever the bytes: a typed result or a typed error
that quotes the offending text, and never a hang past the deadline."""

from __future__ import annotations

import ast
import re
import time

import pytest
import serial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.serial_lines import MAX_LINE, LineReader
from drivers.stage import StageConnectionLost, StageProtocolError, ZaberStage
from drivers.zaber_protocol import (
    FLAGS,
    STATUSES,
    Reply,
    ZaberChecksumError,
    ZaberFormatError,
    append_checksum,
    format_reply,
    parse_command,
    parse_reply,
)
from fakes.zaber import FakeZaberDevice

EXAMPLES = {"parse_reply": 600, "parse_command": 400, "line_reader": 150, "driver_reply": 120}
FUZZ = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)

# pieces that make near-valid replies likely, mixed with arbitrary text
REPLY_PIECES = st.sampled_from(["@", "@01", "@99", " ", "1", "0", "05", "123", "OK", "RJ", "BUSY",
                                "IDLE", "--", "FS", "WR", "BADDATA", "5000", "-7", ":", ":4F",
                                "#", "!", "/", "\r", "\n", "\t", "\x00", "\xe9", "\u2007", "Ⅸ"])
REPLY_TEXT = st.one_of(
    st.text(max_size=60),
    st.lists(st.one_of(REPLY_PIECES, st.text(max_size=4)), max_size=14).map("".join),
    st.builds(lambda r, cc: format_reply(r, checksum=cc), st.builds(
        Reply, st.integers(0, 99), st.integers(0, 9), st.none() | st.integers(0, 99),
        st.sampled_from(FLAGS), st.sampled_from(STATUSES), st.sampled_from(["--", "FS", "WR", "NI"]),
        st.from_regex(r"[A-Z0-9 -]{0,8}[A-Z0-9]", fullmatch=True)), st.booleans()),
)


def quoted(exc: Exception, line: str) -> bool:
    return repr(line.strip()) in str(exc)


@pytest.mark.slow
@settings(max_examples=EXAMPLES["parse_reply"], **FUZZ)
@given(REPLY_TEXT)
def test_fuzz_parse_reply(line: str) -> None:
    try:
        reply = parse_reply(line)
    except ZaberFormatError as exc:  # ZaberChecksumError included
        assert quoted(exc, line), (str(exc), line)
        if isinstance(exc, ZaberChecksumError):
            assert line.strip().startswith("@") and re.search(r":[0-9A-Fa-f]{2}$", line.strip())
        return
    # accepted: a well-formed reply that formats back to the same line (checksum aside)
    assert 0 <= reply.address <= 99 and 0 <= reply.axis <= 9 and reply.flag in FLAGS
    assert reply.status in STATUSES and reply.data
    text = line.strip()
    assert format_reply(reply) == re.sub(r":[0-9A-Fa-f]{2}$", "", text) or \
        append_checksum(format_reply(reply)).upper() == text.upper() or \
        format_reply(reply).replace(f" {reply.msg_id:02d} " if reply.msg_id is not None else "\0",
                                    f" {reply.msg_id} ") == re.sub(r":[0-9A-Fa-f]{2}$", "", text)


@settings(max_examples=EXAMPLES["parse_command"], **FUZZ)
@given(st.one_of(st.text(max_size=40),
                 st.lists(st.one_of(REPLY_PIECES.map(lambda p: "/" if p == "@" else p),
                                    st.sampled_from(["get pos", "move abs", "home"])),
                          max_size=10).map("".join)))
def test_fuzz_parse_command(line: str) -> None:
    """The fake controller parses whatever a host sends: a command or ZaberFormatError, never
    another exception (which would kill the fake's serving thread)."""
    try:
        cmd = parse_command(line)
    except ZaberFormatError as exc:
        assert quoted(exc, line), (str(exc), line)
        return
    assert line.strip().startswith("/") and line.strip().isascii()
    assert cmd.address >= 0 and cmd.axis >= 0
    device = FakeZaberDevice()  # and the fake itself survives the line
    device.feed(line.encode("utf-8") + b"\n")
    device.read_output()


# ----- the deadline line reader ------------------------------------------------------------------
class ChunkPort:
    """A port that hands out ``chunks`` (b"" is a read that times out), then raises
    ``SerialException`` if ``fail`` is set, else times out forever. Reads honour ``size``."""

    def __init__(self, chunks: list[bytes], fail: bool) -> None:
        self.chunks, self.fail, self.timeout = list(chunks), fail, 0.002

    @property
    def in_waiting(self) -> int:
        return len(self.chunks[0]) if self.chunks else 0

    def read(self, size: int = 1) -> bytes:
        if not self.chunks:
            if self.fail:
                raise serial.SerialException("cable pulled")
            time.sleep(self.timeout)
            return b""
        chunk = self.chunks[0]
        if not chunk:
            self.chunks.pop(0)
            time.sleep(self.timeout)
            return b""
        self.chunks[0] = chunk[size:]
        if not self.chunks[0]:
            self.chunks.pop(0)
        return chunk[:size]


CHUNKS = st.lists(st.one_of(st.binary(max_size=40), st.sampled_from([b"\n", b"\r\n", b"", b"\x00"]),
                            st.integers(1, 1500).map(lambda n: b"x" * n),
                            st.integers(1, 1500).map(lambda n: b"x" * n + b"\n")), max_size=12)


@pytest.mark.slow
@settings(max_examples=EXAMPLES["line_reader"], **FUZZ)
@given(CHUNKS, st.booleans())
def test_fuzz_line_reader(chunks: list[bytes], fail: bool) -> None:
    port = ChunkPort(chunks, fail)
    reader = LineReader(port)
    lines: list[bytes] = []
    for _ in range(sum(len(c) for c in chunks) + 3):  # more calls than there can be lines
        started = time.monotonic()
        deadline = started + 0.01
        try:
            line = reader.read_line(deadline)
        except serial.SerialException as exc:  # a port error comes through as itself
            assert fail and not port.chunks and "cable pulled" in str(exc)
            break
        finally:
            assert time.monotonic() <= deadline + port.timeout + 0.25  # never a hang (0.25: load)
        if line is None:
            break
        assert len(line) <= MAX_LINE
        assert (line.endswith(b"\n") and line.count(b"\n") == 1) or \
            (b"\n" not in line and len(line) == MAX_LINE)
        lines.append(line)
    else:
        pytest.fail("read_line kept returning lines")
    data = b"".join(chunks)
    unread = sum(len(c) for c in port.chunks)  # a deadline may pass before all was read
    assert b"".join(lines) + bytes(reader._buf) == data[:len(data) - unread]  # nothing lost or invented
    assert b"\n" not in reader._buf[:MAX_LINE] and len(reader._buf) < MAX_LINE


# ----- the driver's reply handling ----------------------------------------------------------------
class FuzzPort:
    """A port in front of a fake device; once ``script`` is set, the reply to the next command
    is replaced by it (``{ID}`` becomes that command's message id)."""

    port = "fuzz://"

    def __init__(self) -> None:
        self.device = FakeZaberDevice(limit_max=500_000, position=100_000)
        self.timeout: float | None = None
        self.script: bytes | None = None
        self._buf = bytearray()

    def write(self, data: bytes) -> int:
        self.device.feed(data)
        out = self.device.read_output()
        if self.script is not None:
            msg_id = data.split(b" ")[2]
            out, self.script = self.script.replace(b"{ID}", msg_id), None
        self._buf += out
        return len(data)

    def read(self, size: int = 1) -> bytes:
        if not self._buf:
            time.sleep(self.timeout or 0.0)
        data = bytes(self._buf[:size])
        del self._buf[:size]
        return data

    def close(self) -> None:
        pass


WIRE_PIECES = st.sampled_from([b"@01 1 {ID} OK IDLE -- 5000\r\n", b"@01 1 {ID} ", b"@01 1 ", b"@02 1 {ID} ",
                               b"OK ", b"RJ ", b"IDLE ", b"BUSY ", b"-- ", b"FS ", b"5000", b"1_0",
                               b"\r\n", b"\n", b"#", b"!", b":", b":00", b"\xcf", b"\x00", b" "])
WIRE = st.lists(st.one_of(WIRE_PIECES, st.binary(max_size=12)), max_size=12).map(b"".join)
WHAT = ("garbled reply", "not a Zaber ASCII reply", "reply fails its checksum", "reply carries no message id",
        "reply from device", "expected an integer")


@pytest.fixture(scope="module")
def fuzz_stage() -> ZaberStage:
    port = FuzzPort()
    stage = ZaberStage(port, microstep_um=0.1, travel_mm=(0.0, 40.0), timeout_s=0.03, checksum=False)
    yield stage
    stage.close()


@pytest.mark.slow
@settings(max_examples=EXAMPLES["driver_reply"], **FUZZ)
@given(WIRE)
def test_fuzz_driver_reply_handling(fuzz_stage: ZaberStage, wire: bytes) -> None:
    """position_mm on any reply bytes: a position from a valid matching reply, or StageProtocolError
    quoting the offending line, or StageConnectionLost after timeout_s; nothing else, no hang."""
    port: FuzzPort = fuzz_stage._port  # type: ignore[assignment]
    port._buf.clear()
    fuzz_stage._reader._buf.clear()  # each example starts on a clean line
    port.script = wire
    started = time.monotonic()
    try:
        value = fuzz_stage.position_mm
    except StageProtocolError as exc:
        match = re.fullmatch(r"fuzz://: sent '(/1 1 (\d\d) get pos)', got (b?'.*'|b?\".*\"): (.*)",
                             str(exc), flags=re.S)
        assert match and match.group(4).startswith(WHAT), str(exc)
        got = ast.literal_eval(match.group(3))
        raw = wire.replace(b"{ID}", match.group(2).encode())
        assert (got if isinstance(got, bytes) else got.encode()) in raw  # quotes what came back
    except StageConnectionLost as exc:
        assert re.fullmatch(r"fuzz://: sent '/1 1 \d\d get pos': no reply within 0.03 s", str(exc))
    else:
        assert value == 0.5 and b"@01 1 {ID} OK IDLE -- 5000" in wire
    assert time.monotonic() - started < 0.03 + 0.2
