"""The fake Zaber controller itself, at the byte level, on a manual clock; and its transports."""

from __future__ import annotations

import math
import os
import select
import signal
import subprocess
import sys
import time

import pytest
import serial

from drivers.zaber_protocol import checksum_ok
from fakes.zaber import (
    FakeZaberDevice,
    FakeZaberPty,
    FakeZaberSerial,
    Faults,
    ManualClock,
    Profile,
    register_url_handler,
    remove_url_device,
    url_device,
)

SPEED = 16384  # maxspeed value: 10000 microsteps/s
ACCEL = 16  # accel value: 16 * 10000 / 1.6384 = 97656.25 microsteps/s^2
V = SPEED / 1.6384
A = ACCEL * 10000 / 1.6384


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def dev(clock: ManualClock) -> FakeZaberDevice:
    return FakeZaberDevice(clock=clock, limit_max=200_000, maxspeed=SPEED, accel=ACCEL, position=5000)


def ask(device: FakeZaberDevice, line: str) -> str:
    """Send one command line, return everything the device sent back (as text)."""
    device.feed(line.encode("ascii") + b"\n")
    return device.read_output().decode("latin-1")


def homed(device: FakeZaberDevice, clock: ManualClock) -> FakeZaberDevice:
    ask(device, "/1 1 home")
    clock.advance(10.0)
    assert device.homed
    return device


# ----- replies ---------------------------------------------------------------------------------
def test_status_and_settings(dev: FakeZaberDevice) -> None:
    assert ask(dev, "/1") == "@01 0 OK IDLE WR 0\r\n"
    assert ask(dev, "/1 0 get deviceid") == "@01 0 OK IDLE WR 50081\r\n"
    assert ask(dev, "/1 get version") == "@01 0 OK IDLE WR 7.38\r\n"
    assert ask(dev, "/1 get system.axiscount") == "@01 0 OK IDLE WR 1\r\n"
    assert ask(dev, "/1 1 get limit.min") == "@01 1 OK IDLE WR 0\r\n"
    assert ask(dev, "/1 1 get limit.max") == "@01 1 OK IDLE WR 200000\r\n"
    assert ask(dev, "/1 1 get maxspeed") == f"@01 1 OK IDLE WR {SPEED}\r\n"
    assert ask(dev, "/1 1 get accel") == f"@01 1 OK IDLE WR {ACCEL}\r\n"
    assert ask(dev, "/1 1 get pos") == "@01 1 OK IDLE WR 5000\r\n"
    assert ask(dev, "/1 1 get limit.home.triggered") == "@01 1 OK IDLE WR 0\r\n"


def test_message_ids_are_echoed(dev: FakeZaberDevice) -> None:
    assert ask(dev, "/1 1 42 get pos") == "@01 1 42 OK IDLE WR 5000\r\n"
    assert ask(dev, "/1 0 07") == "@01 0 07 OK IDLE WR 0\r\n"


def test_addresses_and_axes(dev: FakeZaberDevice) -> None:
    assert ask(dev, "/2 1 get pos") == ""  # another device's command: silence
    assert ask(dev, "/ get deviceid") == "@01 0 OK IDLE WR 50081\r\n"  # all devices
    assert ask(dev, "/0 1 get pos") == "@01 1 OK IDLE WR 5000\r\n"
    assert ask(dev, "/1 2 get pos") == "@01 2 RJ IDLE WR BADAXIS\r\n"
    assert ask(dev, "get pos") == ""  # not a command at all


def test_unknown_commands_and_settings_are_rejected(dev: FakeZaberDevice) -> None:
    assert ask(dev, "/1 1 fly") == "@01 1 RJ IDLE WR BADCOMMAND\r\n"
    assert ask(dev, "/1 1 get warp.factor") == "@01 1 RJ IDLE WR BADCOMMAND\r\n"
    assert ask(dev, "/1 1 move rel 5") == "@01 1 RJ IDLE WR BADCOMMAND\r\n"


def test_tools_echo_and_checksums_in_both_directions(clock: ManualClock) -> None:
    device = FakeZaberDevice(clock=clock, reply_checksums=True)
    assert ask(device, "/01 tools echo:8F") == "@01 0 OK IDLE WR 0:3E\r\n"
    assert ask(device, "/1 tools echo hello") == "@01 0 OK IDLE WR hello:5A\r\n"
    # a command with a wrong checksum is logged but gets no reply
    assert ask(device, "/01 tools echo:8E") == ""
    assert device.received[-1] == "/01 tools echo:8E"


def test_lines_may_arrive_in_pieces_and_together(dev: FakeZaberDevice) -> None:
    for byte in b"/1 1 01 get pos\r":
        dev.feed(bytes([byte]))
    assert dev.read_output() == b""
    dev.feed(b"\n/1 1 02 get pos\n/1 1 03 get limit.max\n")
    assert dev.read_output() == (
        b"@01 1 01 OK IDLE WR 5000\r\n@01 1 02 OK IDLE WR 5000\r\n@01 1 03 OK IDLE WR 200000\r\n"
    )
    assert dev.received == ["/1 1 01 get pos", "/1 1 02 get pos", "/1 1 03 get limit.max"]
    assert bytes(dev.received_bytes).count(b"\n") == 3


# ----- homing and motion -----------------------------------------------------------------------
def test_move_before_homing_is_rejected(dev: FakeZaberDevice) -> None:
    assert ask(dev, "/1 1 move abs 10000") == "@01 1 RJ IDLE WR BADDATA\r\n"
    assert dev.position == 5000 and not dev.busy


def test_homing_moves_to_zero_and_sets_homed(dev: FakeZaberDevice, clock: ManualClock) -> None:
    assert ask(dev, "/1 home") == "@01 0 OK BUSY WR 0\r\n"
    clock.advance(0.1)
    assert 0 < dev.position < 5000 and dev.busy and not dev.homed
    clock.advance(1.0)
    assert dev.position == 0 and dev.homed
    assert ask(dev, "/1 1 get limit.home.triggered") == "@01 1 OK IDLE -- 1\r\n"
    assert dev.warnings == []


def test_targets_outside_the_device_limits_are_rejected(dev: FakeZaberDevice, clock: ManualClock) -> None:
    homed(dev, clock)
    assert ask(dev, "/1 1 move abs 200001") == "@01 1 RJ IDLE -- BADDATA\r\n"
    assert ask(dev, "/1 1 move abs -1") == "@01 1 RJ IDLE -- BADDATA\r\n"
    assert ask(dev, "/1 1 move abs ten") == "@01 1 RJ IDLE -- BADDATA\r\n"
    assert ask(dev, "/1 1 move abs") == "@01 1 RJ IDLE -- BADDATA\r\n"
    assert ask(dev, "/1 1 move abs 200000") == "@01 1 OK BUSY -- 0\r\n"


def test_trapezoidal_motion_follows_maxspeed_and_accel(dev: FakeZaberDevice, clock: ManualClock) -> None:
    homed(dev, clock)
    distance = 100_000
    assert ask(dev, f"/1 1 move abs {distance}") == "@01 1 OK BUSY -- 0\r\n"
    t_acc, d_acc = V / A, V * V / (2 * A)
    total = distance / V + V / A
    start = clock.now
    clock.now = start + t_acc / 2
    assert dev.position == round(A * (t_acc / 2) ** 2 / 2)
    clock.now = start + t_acc + 1.0
    assert dev.position == round(d_acc + V * 1.0)
    clock.now = start + total - t_acc / 2  # half-way through the deceleration
    assert dev.position == round(distance - A * (t_acc / 2) ** 2 / 2)
    assert ask(dev, "/1 1 get pos").startswith("@01 1 OK BUSY -- ")
    clock.now = start + total
    assert ask(dev, "/1 1 get pos") == f"@01 1 OK IDLE -- {distance}\r\n"


def test_profile_shapes() -> None:
    trapezoid = Profile(0.0, 1000.0, 0.0, vmax=100.0, accel=100.0)
    assert trapezoid.duration == pytest.approx(11.0)
    assert trapezoid.state(1.0) == pytest.approx((50.0, 100.0))
    assert trapezoid.state(11.0) == (1000.0, 0.0)
    triangle = Profile(0.0, -100.0, 2.0, vmax=1000.0, accel=100.0)
    assert triangle.duration == pytest.approx(2.0)  # peak speed 100 reached at the middle
    assert triangle.state(3.0) == pytest.approx((-50.0, 100.0))
    assert Profile(5.0, 5.0, 0.0, vmax=1.0, accel=1.0).duration == 0.0
    stopping = trapezoid.stopping(5.0)  # cruising at 100: stops 50 further on in 1 s
    assert (stopping.end, stopping.duration) == (pytest.approx(500.0), pytest.approx(1.0))


def test_profile_without_ramp() -> None:
    """accel 0 (Zaber's "no ramp"): full speed from the first instant, a dead stop at the end."""
    flat = Profile(100.0, 1100.0, 2.0, vmax=500.0, accel=0.0)
    assert flat.no_ramp and flat.duration == pytest.approx(2.0)  # 1000 steps at 500 steps/s
    assert flat.state(2.0) == (100.0, 500.0)
    assert flat.state(2.5) == pytest.approx((350.0, 500.0))
    assert flat.state(3.999) == pytest.approx((1099.5, 500.0))
    assert flat.state(4.0) == (1100.0, 0.0)
    back = Profile(0.0, -300.0, 0.0, vmax=100.0, accel=0.0)
    assert back.duration == pytest.approx(3.0) and back.state(1.5) == pytest.approx((-150.0, 100.0))
    halt = flat.stopping(3.0)  # a stop without ramp ends the motion where it is
    assert (halt.start, halt.end, halt.duration) == (pytest.approx(600.0), pytest.approx(600.0), 0.0)
    assert Profile(7.0, 7.0, 0.0, vmax=1.0, accel=0.0).duration == 0.0


def test_device_with_accel_zero_moves_at_full_speed_at_once(clock: ManualClock) -> None:
    dev = FakeZaberDevice(clock=clock, limit_max=200_000, maxspeed=SPEED, accel=0, position=5000)
    assert ask(dev, "/1 1 get accel") == "@01 1 OK IDLE WR 0\r\n"
    ask(dev, "/1 1 home")
    clock.advance(0.25)  # 2500 of the 5000 steps home at 10000 steps/s, no ramp
    assert dev.position == 2500 and dev.busy
    clock.advance(0.25)
    assert dev.position == 0 and dev.homed and not dev.busy
    assert ask(dev, "/1 1 move abs 100000") == "@01 1 OK BUSY -- 0\r\n"
    clock.advance(0.001)  # no acceleration phase: 10 steps in the first millisecond
    assert dev.position == 10
    clock.advance(4.999)
    assert dev.position == 50_000
    assert ask(dev, "/1 1 stop") == "@01 1 OK IDLE NI 0\r\n"  # stops dead, no deceleration
    clock.advance(1.0)
    assert dev.position == 50_000 and not dev.busy
    ask(dev, "/1 1 move abs 0")
    clock.advance(5.0)
    assert ask(dev, "/1 1 get pos") == "@01 1 OK IDLE -- 0\r\n"


def test_stop_decelerates_and_estop_halts(dev: FakeZaberDevice, clock: ManualClock) -> None:
    homed(dev, clock)
    ask(dev, "/1 1 move abs 100000")
    clock.advance(1.0)
    at_stop = dev.position
    assert ask(dev, "/1 1 stop") == "@01 1 OK BUSY NI 0\r\n"
    clock.advance(1.0)
    assert dev.position == round(at_stop + V * V / (2 * A)) and not dev.busy
    assert ask(dev, "/1 warnings") == "@01 0 OK IDLE NI 01 NI\r\n"
    assert ask(dev, "/1 warnings clear") == "@01 0 OK IDLE -- 01 NI\r\n"  # lists, then clears
    assert ask(dev, "/1 warnings") == "@01 0 OK IDLE -- 00\r\n"
    ask(dev, "/1 1 move abs 150000")
    clock.advance(0.5)
    at_estop = dev.position
    assert ask(dev, "/1 1 estop") == "@01 1 OK IDLE NI 0\r\n"
    clock.advance(1.0)
    assert dev.position == at_estop
    assert ask(dev, "/1 1 stop") == "@01 1 OK IDLE NI 0\r\n"  # stopping a still axis: no change


def test_new_move_interrupts_the_current_one(dev: FakeZaberDevice, clock: ManualClock) -> None:
    homed(dev, clock)
    ask(dev, "/1 1 move abs 100000")
    clock.advance(0.5)
    ask(dev, "/1 1 move abs 1000")
    clock.advance(20.0)
    assert dev.position == 1000


# ----- fault switches --------------------------------------------------------------------------
def test_faults_take_counts_down() -> None:
    faults = Faults(drop_replies=1)
    assert faults.take("drop_replies") and not faults.take("drop_replies")


def test_manual_clock_does_not_go_back() -> None:
    with pytest.raises(ValueError, match=r"a clock cannot go back: advance\(-1\)"):
        ManualClock().advance(-1)


def test_drop_reply_and_silent(dev: FakeZaberDevice) -> None:
    dev.faults.drop_replies = 1
    assert ask(dev, "/1 1 get pos") == ""
    assert ask(dev, "/1 1 get pos") == "@01 1 OK IDLE WR 5000\r\n"
    dev.faults.drop_on = "limit"
    assert ask(dev, "/1 1 get pos") != "" and ask(dev, "/1 1 get limit.max") == ""
    assert ask(dev, "/1 1 get limit.max") != "" and dev.faults.drop_on is None
    dev.faults.silent = True
    assert ask(dev, "/1") == "" and ask(dev, "/1 1 get pos") == ""
    assert dev.received[-2:] == ["/1", "/1 1 get pos"]


def test_delayed_reply_comes_after_the_delay(dev: FakeZaberDevice, clock: ManualClock) -> None:
    dev.faults.delay_replies, dev.faults.delay_s = 1, 0.5
    assert ask(dev, "/1 1 01 get pos") == ""
    assert ask(dev, "/1 1 02 get pos") == "@01 1 02 OK IDLE WR 5000\r\n"  # overtakes it
    clock.advance(0.5)
    assert dev.read_output() == b"@01 1 01 OK IDLE WR 5000\r\n"


def test_garbled_and_bad_checksum_replies(dev: FakeZaberDevice) -> None:
    dev.faults.garble_replies = 1
    dev.feed(b"/1 1 get pos\n")
    assert dev.read_output() == b"@01 1 \xcf\xcb IDLE WR 5000\r\n"
    dev.faults.bad_checksum_replies = 1
    text = ask(dev, "/1 1 get pos")
    assert text.startswith("@01 1 OK IDLE WR 5000:")
    assert checksum_ok(text.strip()) is False
    assert ask(dev, "/1 1 get pos") == "@01 1 OK IDLE WR 5000\r\n"


def test_stall_stops_short_with_fs(dev: FakeZaberDevice, clock: ManualClock) -> None:
    homed(dev, clock)
    dev.faults.stall_at = 0.5
    ask(dev, "/1 1 move abs 100000")
    clock.advance(30.0)
    assert ask(dev, "/1 1 get pos") == "@01 1 OK IDLE FS 50000\r\n"
    assert dev.faults.stall_at is None  # used by that move
    ask(dev, "/1 1 move abs 60000")  # a new move clears FS
    clock.advance(30.0)
    assert ask(dev, "/1 1 get pos") == "@01 1 OK IDLE -- 60000\r\n"


def test_stop_short_silently_and_idle_glitch(dev: FakeZaberDevice, clock: ManualClock) -> None:
    homed(dev, clock)
    dev.faults.stop_short = 700
    ask(dev, "/1 1 move abs 100000")
    clock.advance(30.0)
    assert ask(dev, "/1 1 get pos") == "@01 1 OK IDLE -- 99300\r\n"
    ask(dev, "/1 1 move abs 0")
    clock.advance(1.0)
    dev.faults.idle_glitch = True
    assert ask(dev, "/1 1 get pos").startswith("@01 1 OK IDLE -- ")
    assert ask(dev, "/1 1 get pos").startswith("@01 1 OK BUSY -- ")


def test_homing_that_stops_short_leaves_the_device_unhomed(dev: FakeZaberDevice, clock: ManualClock) -> None:
    dev.faults.stop_short = 10
    ask(dev, "/1 1 home")
    clock.advance(10.0)
    assert dev.position == 10 and not dev.homed and dev.warnings == ["WR"]


def test_info_and_alert_lines(dev: FakeZaberDevice) -> None:
    dev.faults.info_lines = 2
    assert ask(dev, "/1 1 05 get pos") == (
        "@01 1 05 OK IDLE WR 5000\r\n#01 1 05 info from the fake\r\n#01 1 05 info from the fake\r\n"
    )
    dev.faults.alert_lines = 1
    assert dev.read_output() == b"!01 1 IDLE WR\r\n"  # unsolicited: no command needed


def test_vanish_on_command_executes_it_without_reply(dev: FakeZaberDevice, clock: ManualClock) -> None:
    homed(dev, clock)
    dev.faults.vanish_on = "move"
    assert ask(dev, "/1 1 move abs 1000") == ""
    assert dev.faults.vanish and dev.faults.vanish_on is None and dev.busy


# ----- URL handler -----------------------------------------------------------------------------
def test_importing_registers_nothing() -> None:
    code = (
        "import serial, fakes.zaber\n"
        "assert 'fakes.zaber' not in serial.protocol_handler_packages\n"
        "try:\n    serial.serial_for_url('fakezaber://x')\n"
        "except ValueError as e:\n    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    assert "protocol 'fakezaber' not known" in out.stdout, out.stderr


def test_url_handler_talks_to_a_registered_device() -> None:
    register_url_handler()
    register_url_handler()  # idempotent
    device = url_device("url-test", limit_max=1234)
    try:
        port = serial.serial_for_url("fakezaber://url-test", timeout=0.05)
        port.write(b"/1 1 get limit.max\n")
        assert port.in_waiting == len("@01 1 OK IDLE WR 1234\r\n")
        assert port.read(100) == b"@01 1 OK IDLE WR 1234\r\n"
        started = time.monotonic()
        assert port.read(1) == b""
        assert 0.04 < time.monotonic() - started < 0.5
        port.write(b"/1 1 get pos\n")
        port.reset_input_buffer()
        assert port.read(1) == b""
        device.faults.vanish = True
        with pytest.raises(serial.SerialException, match="fakezaber://url-test: device vanished"):
            port.write(b"/1\n")
        with pytest.raises(serial.SerialException, match="device vanished"):
            port.read(1)  # the broken connection stays broken
        port.close()
        again = serial.serial_for_url("fakezaber://url-test", timeout=0.05)  # plugged back
        again.write(b"/1\n")
        assert again.read(100) == b"@01 0 OK IDLE WR 0\r\n"
        with pytest.raises(serial.SerialException, match="port is already open"):
            again.open()
        again.close()
    finally:
        remove_url_device("url-test")


def test_url_handler_errors() -> None:
    register_url_handler()
    url_device("dup")
    try:
        with pytest.raises(ValueError, match="fake device 'dup' exists already"):
            url_device("dup", limit_max=5)
    finally:
        remove_url_device("dup")
    port = FakeZaberSerial()
    with pytest.raises(serial.SerialException, match="must be configured"):
        port.open()
    port.port = "loop://"
    with pytest.raises(serial.SerialException, match=r"expected fakezaber://NAME, got 'loop://'"):
        port.open()
    with pytest.raises(serial.PortNotOpenError):
        port.write(b"/1\n")


# ----- pty server ------------------------------------------------------------------------------
def test_pty_serves_the_device_on_a_real_tty() -> None:
    with FakeZaberPty(FakeZaberDevice(limit_max=777)) as server:
        assert server.port.startswith("/dev/")
        with serial.Serial(server.port, 115200, timeout=0.5) as port:
            assert port.read(1) == b"" or pytest.fail("the fake spoke before any command")
            port.write(b"/1 1 get limit.max\n")
            assert port.read_until(b"\n") == b"@01 1 OK IDLE WR 777\r\n"
    server.close()  # idempotent


def test_pty_vanish_gives_serial_exception() -> None:
    with FakeZaberPty() as server:
        port = serial.Serial(server.port, 115200, timeout=0.2)
        server.device.faults.vanish = True
        deadline = time.monotonic() + 2.0
        while not server.vanished and time.monotonic() < deadline:
            time.sleep(0.005)
        assert server.vanished
        with pytest.raises(serial.SerialException):
            port.write(b"/1\n")
            port.read(1)
        port.close()


def test_main_serves_until_ctrl_c() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "fakes.zaber", "--limit-max", "4242"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 20.0)
        assert ready, "no port name printed"
        first = proc.stdout.readline()
        port_name = first.split(" on ")[1].strip()
        assert os.path.exists(port_name)
        with serial.Serial(port_name, 115200, timeout=2.0) as port:
            port.write(b"/1 1 get limit.max\n")
            assert port.read_until(b"\n") == b"@01 1 OK IDLE WR 4242\r\n"
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
        assert "stopped" in proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_profile_speed_never_negative_or_above_vmax() -> None:
    profile = Profile(0.0, 12345.0, 0.0, vmax=V, accel=A)
    for i in range(200):
        _, v = profile.state(i * profile.duration / 199)
        assert 0.0 <= v <= V + 1e-9 and not math.isnan(v)


def test_an_overlong_line_is_dropped_and_the_buffer_stays_bounded(dev: FakeZaberDevice) -> None:
    from fakes.zaber.device import MAX_LINE_BYTES, RECEIVED_LOG_BYTES

    chunk = b"x" * (1 << 20)
    for _ in range(8):  # 8 MB without a newline
        dev.feed(chunk)
        assert len(dev._inbuf) <= MAX_LINE_BYTES
        assert len(dev.received_bytes) <= RECEIVED_LOG_BYTES
    dev.feed(b"tail of the overlong line\n/1 get pos\n")
    assert dev.dropped_lines == 1 and dev.received_count == 8 * len(chunk) + 37
    assert dev.read_output() == f"@01 0 OK IDLE WR {dev.position}\r\n".encode()  # works again
    dev.feed(b"/1 get " + b"p" * MAX_LINE_BYTES + b"\n")  # too long, though terminated
    assert dev.dropped_lines == 2 and dev.read_output() == b""


def test_unread_replies_are_dropped_beyond_the_bound(dev: FakeZaberDevice) -> None:
    from fakes.zaber.device import MAX_PENDING_REPLIES

    dev.feed(b"/1 get pos\n" * (MAX_PENDING_REPLIES + 10))
    assert dev.dropped_replies == 10
    assert dev.read_output().count(b"\r\n") == MAX_PENDING_REPLIES


def test_a_host_that_writes_without_reading_does_not_block_the_pty_server() -> None:
    import threading

    with FakeZaberPty() as server:
        fd = os.open(server.port, os.O_RDWR | os.O_NOCTTY)
        try:
            # 40,000 commands whose 800 kB of replies are never read: far beyond what the pty
            # holds, so a server that blocked on writing would stop reading and block us too
            writer = threading.Thread(target=lambda: [os.write(fd, b"/1 get pos\n" * 1000)
                                                      for _ in range(40)], daemon=True)
            writer.start()
            writer.join(timeout=30)
            assert not writer.is_alive(), "the host's writes blocked: the server deadlocked"
            time.sleep(0.2)
            assert server.dropped_bytes > 0 and server._thread.is_alive()
            os.set_blocking(fd, False)
            while True:  # drain what the server did send
                try:
                    if not os.read(fd, 65536):
                        break
                except BlockingIOError:
                    time.sleep(0.05)
                    try:
                        os.read(fd, 65536)
                    except BlockingIOError:
                        break
            os.write(fd, b"/1 get pos\n")
            deadline, got = time.monotonic() + 5, b""
            while not got.endswith(b"\r\n") and time.monotonic() < deadline:
                try:
                    got += os.read(fd, 4096)
                except BlockingIOError:
                    time.sleep(0.01)
            assert got.endswith(f"@01 0 OK IDLE WR {server.device.position}\r\n".encode())
        finally:
            os.close(fd)
