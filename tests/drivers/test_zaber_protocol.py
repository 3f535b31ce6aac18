"""Zaber ASCII protocol functions: checksums, command formatting and parsing, reply parsing."""

from __future__ import annotations

import pytest

from drivers.zaber_protocol import (
    Command,
    Reply,
    ZaberChecksumError,
    ZaberFormatError,
    append_checksum,
    checksum_ok,
    format_command,
    format_reply,
    lrc,
    parse_command,
    parse_reply,
    split_checksum,
)


@pytest.mark.parametrize(
    "line, expected",
    [("/01 tools echo", "/01 tools echo:8F"), ("/1 1 move abs 10000", "/1 1 move abs 10000:40")],
)
def test_checksum_examples_from_hardware_md(line: str, expected: str) -> None:
    assert append_checksum(line) == expected
    assert checksum_ok(expected) is True
    assert lrc(line[1:]) == int(expected[-2:], 16)


def test_checksum_is_minus_the_byte_sum_mod_256() -> None:
    # "1" is 0x31: -0x31 mod 256 = 0xCF; the bytes plus the checksum sum to 0 mod 256
    assert lrc("1") == 0xCF
    payload = "01 1 OK IDLE -- 0"
    assert (sum(payload.encode()) + lrc(payload)) % 256 == 0


def test_checksum_ok_detects_mismatch_and_absence() -> None:
    assert checksum_ok("/1 1 move abs 10000:41") is False
    assert checksum_ok("/1 1 move abs 10000") is None
    assert split_checksum("/1 1 move abs 10000:40") == ("/1 1 move abs 10000", 0x40)
    assert split_checksum("@01 1 OK IDLE -- a:b") == ("@01 1 OK IDLE -- a:b", None)


def test_format_command_with_and_without_message_id() -> None:
    assert format_command("get pos", address=1, axis=1) == "/1 1 get pos"
    assert format_command("get pos", address=1, axis=1, msg_id=7) == "/1 1 07 get pos"
    assert format_command("", address=2, axis=0) == "/2 0"
    assert format_command("move abs 10000", address=1, axis=1, checksum=True) == "/1 1 move abs 10000:40"


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(address=100), "address must be 0-99, got 100"),
        (dict(axis=10), "axis must be 0-9, got 10"),
        (dict(msg_id=100), "message id must be 0-99, got 100"),
    ],
)
def test_format_command_refuses_out_of_range_fields(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        format_command("get pos", **kwargs)


@pytest.mark.parametrize(
    "line, expected",
    [
        ("/", Command(0, 0, None, "")),
        ("/1", Command(1, 0, None, "")),
        ("/01 tools echo:8F", Command(1, 0, None, "tools echo")),
        ("/1 1 move abs 10000:40\r\n", Command(1, 1, None, "move abs 10000")),
        ("/1 1 12 get pos", Command(1, 1, 12, "get pos")),
        ("/1 home", Command(1, 0, None, "home")),
    ],
)
def test_parse_command(line: str, expected: Command) -> None:
    assert parse_command(line) == expected


def test_parse_command_errors() -> None:
    with pytest.raises(ZaberFormatError, match="not a Zaber command: 'get pos'"):
        parse_command("get pos")
    with pytest.raises(ZaberChecksumError, match="bad checksum in '/01 tools echo:8E'"):
        parse_command("/01 tools echo:8E")


def test_reply_round_trip_with_id_and_checksum() -> None:
    reply = Reply(1, 1, 5, "OK", "BUSY", "--", "12345")
    line = format_reply(reply, checksum=True)
    assert line.startswith("@01 1 05 OK BUSY -- 12345:")
    assert parse_reply(line + "\r\n") == reply
    assert parse_reply(format_reply(reply)) == reply


def test_parse_reply_fields() -> None:
    reply = parse_reply("@01 0 RJ IDLE WR BADDATA")
    assert reply == Reply(1, 0, None, "RJ", "IDLE", "WR", "BADDATA")
    assert reply.rejected and not reply.busy and not reply.fault
    stalled = parse_reply("@02 1 33 OK IDLE FS 400")
    assert stalled.fault and stalled.msg_id == 33 and stalled.address == 2
    assert parse_reply("@01 0 OK IDLE WR 01 WR").data == "01 WR"


@pytest.mark.parametrize(
    "line, error, match",
    [
        ("#01 0 info", ZaberFormatError, "not a Zaber reply"),
        ("@01 1 OK IDLE -- 0:00", ZaberChecksumError, "bad checksum"),
        ("@01 1 OK", ZaberFormatError, "truncated Zaber reply"),
        ("@01 1 OK SLEEPY -- 0", ZaberFormatError, "malformed Zaber reply"),
        ("@01 1 OK IDLE xx 0", ZaberFormatError, "malformed Zaber reply"),
        ("@1 1 OK IDLE -- 0", ZaberFormatError,
         r"malformed Zaber reply: '@1 1 OK IDLE -- 0' \(expected a 2-2 digit address, got '1'\)"),
        ("@01 1 123 OK IDLE -- 0", ZaberFormatError,
         r"'@01 1 123 OK IDLE -- 0' \(expected a 1-2 digit message id, got '123'\)"),
        ("@01 1 05 OK IDLE --", ZaberFormatError,
         r"truncated Zaber reply \(no data field\): '@01 1 05 OK IDLE --'"),
        ("@01 1 OK IDLE -- \xe9:00", ZaberFormatError,
         r"non-ASCII characters in Zaber reply: '@01 1 OK IDLE -- \xe9:00'"),
    ],
)
def test_parse_reply_rejects_malformed_lines(line: str, error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        parse_reply(line)


def test_speed_and_accel_units_are_defined_once_in_the_protocol_module() -> None:
    import pathlib

    import drivers.stage
    import fakes.hardware
    import fakes.zaber.device
    from drivers import zaber_protocol

    # docs/hardware.md: speed in microsteps/s = maxspeed / 1.6384; microsteps/s^2 = accel * 10000 / 1.6384
    assert zaber_protocol.SPEED_UNIT == 1.6384
    assert 16 / zaber_protocol.ACCEL_UNIT == pytest.approx(16 * 10000 / 1.6384, rel=1e-12)
    for module in (drivers.stage, fakes.zaber.device, fakes.hardware):
        assert module.SPEED_UNIT is zaber_protocol.SPEED_UNIT
    root = pathlib.Path(zaber_protocol.__file__).parents[1]
    defining = sorted(str(path.relative_to(root)) for package in ("drivers", "fakes", "station")
                      for path in (root / package).rglob("*.py")
                      if any(line.startswith(("SPEED_UNIT =", "ACCEL_UNIT ="))
                             for line in path.read_text().splitlines()))
    assert defining == ["drivers/zaber_protocol.py"]
