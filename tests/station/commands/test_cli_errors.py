"""What ``ltc`` does with an error: a root of ours, an ``OSError`` or a validation error is one
line (exit 1, or 2 for usage); anything else is a bug (exit 3), with its traceback under
``--debug`` or ``LTC_DEBUG=1`` and always in the run's log file."""

from __future__ import annotations

import errno
import os
import re

import numpy as np
import pytest
from pydantic import BaseModel, ValidationError

from drivers import CameraTimeout, DeviceError
from drivers.stage_errors import StageTimeout
from sim.errors import SimError, SimInputError
from sim.fpp.scan_input import ScanInputError
from station.acquisition.config import ConfigError
from station.cli import EXIT_BUG, main
from station.errors import StationError, StationInputError, UsageError
from station.ltc.store import LtcStoreError
from tests.support.cli import call


def shape_bug(*_args, **_kwargs):
    """A numpy shape error, as a bug in our code would raise it."""
    return np.ones((3, 2)) @ np.ones((3, 2))


def _validation_error() -> ValidationError:
    class Model(BaseModel):
        depth_mm: float

    try:
        Model(depth_mm="deep")
    except ValidationError as exc:
        return exc
    raise AssertionError("not refused")


@pytest.fixture
def cloud(tmp_path):
    return tmp_path / "c.ply"


def test_a_numpy_shape_bug_is_reported_as_a_bug_with_exit_3_and_no_traceback(
        cloud, capsys, monkeypatch):
    monkeypatch.delenv("LTC_DEBUG", raising=False)
    monkeypatch.setattr("sim.fpp.cloud.read_ply", shape_bug)
    code, out, err = call(["measure", str(cloud), "--sphere"], capsys)
    assert code == EXIT_BUG == 3
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err and out == ""
    assert lines[0].startswith("ltc measure: bug: ValueError: matmul: ")
    assert "internal error" in lines[0] and "--debug" in lines[0] and "LTC_DEBUG=1" in lines[0]


@pytest.mark.parametrize("how", ["--debug", "LTC_DEBUG=1"])
def test_debug_prints_the_bugs_traceback_then_the_bug_line(how, cloud, capsys, monkeypatch):
    monkeypatch.delenv("LTC_DEBUG", raising=False)
    monkeypatch.setattr("sim.fpp.cloud.read_ply", shape_bug)
    args = ["measure", str(cloud), "--sphere"]
    if how == "--debug":
        args.insert(0, "--debug")
    else:
        monkeypatch.setenv("LTC_DEBUG", "1")
    code, _, err = call(args, capsys)
    assert code == EXIT_BUG
    assert err.startswith("Traceback (most recent call last):")
    assert "in shape_bug" in err and "ValueError: matmul: " in err  # where, and what
    last = err.strip().splitlines()[-1]
    assert last.startswith("ltc measure: bug: ValueError: matmul: ") and "--debug" not in last


def test_a_bug_in_a_sequence_keeps_its_traceback_in_run_log(tmp_path, capsys, monkeypatch):
    from station.sequence import Sequence

    monkeypatch.delenv("LTC_DEBUG", raising=False)
    assert main(["config", "--example", "fake"]) == 0
    cfg = tmp_path / "fake.toml"
    cfg.write_text(capsys.readouterr().out)
    monkeypatch.setattr(Sequence, "_check", shape_bug)
    seq = tmp_path / "seq"
    code, _, err = call(["run", str(cfg), "--out", str(seq)], capsys)
    log = (seq / "run.log").read_text()
    assert code == EXIT_BUG
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ltc run: bug: ValueError: matmul: ")
    assert f"it is in {seq / 'run.log'}" in lines[0]
    assert "check: failed: matmul: " in log  # the sequence's own record of the step
    tail = log[log.index("ERROR station.cli ltc run: bug: matmul: "):]
    assert "Traceback (most recent call last):" in tail and "in shape_bug" in tail


@pytest.mark.parametrize("error", [
    DeviceError("stage on /dev/ttyUSB0: no reply within 2 s"),
    StageTimeout("stage on /dev/ttyUSB0: move to 5 mm not finished in 3 s"),
    CameraTimeout("camera 0: no frame within 1 s"),
    SimError("scene.toml: the rig has no camera"),
    SimInputError("scene.toml: field 'objects': must not be empty"),
    ScanInputError("images/: no images"),
    StationError("acquire: the run store is locked by pid 12"),
    StationInputError("lut.npy: lut must be non-decreasing"),
    ConfigError("bench.toml: field 'depths_mm': empty"),
    LtcStoreError("ltc.zarr: not an LTC store"),
    OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "c.ply"),
    _validation_error(),
], ids=lambda e: type(e).__name__)
def test_each_domain_root_is_one_line_with_exit_1(error, cloud, capsys, monkeypatch):
    def fail(*_args, **_kwargs):
        raise error

    monkeypatch.setenv("LTC_DEBUG", "1")  # an expected failure has no traceback even so
    monkeypatch.setattr("sim.fpp.cloud.read_ply", fail)
    code, _, err = call(["measure", str(cloud), "--sphere"], capsys)
    lines = err.strip().splitlines()
    assert code == 1 and len(lines) == 1, err
    assert lines[0].startswith("ltc measure: error: ") and "Traceback" not in err
    if isinstance(error, OSError):
        assert lines[0].startswith("ltc measure: error: c.ply: no space left on device; free ")
    elif isinstance(error, ValidationError):
        assert "depth_mm" in lines[0]
    else:
        assert lines[0] == f"ltc measure: error: {error}"


def test_a_usage_error_is_one_line_with_exit_2(cloud, capsys, monkeypatch):
    def fail(*_args, **_kwargs):
        raise UsageError("--sphere needs a cloud with points")

    monkeypatch.setattr("sim.fpp.cloud.read_ply", fail)
    code, _, err = call(["measure", str(cloud), "--sphere"], capsys)
    assert code == 2 and err == "ltc measure: error: --sphere needs a cloud with points\n"


def test_every_error_we_raise_derives_from_a_package_root():
    import drivers.errors
    import drivers.frame_code
    import drivers.stage_errors
    import drivers.zaber_protocol
    import sim.fpp.scan_input
    import sim.metrology.measure
    import sim.optics.measured_lens
    import sim.storage.errors
    import sim.storage.lock
    import station.acquisition.align
    import station.acquisition.config
    import station.acquisition.gamma
    import station.acquisition.run_reader
    import station.acquisition.run_store
    import station.lens.geometry
    import station.lens.rays
    import station.ltc.checked
    import station.ltc.store
    import station.ltc.verify

    roots = (DeviceError, SimError, StationError)
    modules = [drivers.errors, drivers.frame_code, drivers.stage_errors, drivers.zaber_protocol,
               sim.fpp.scan_input, sim.metrology.measure, sim.optics.measured_lens,
               station.acquisition.align, station.acquisition.config, station.acquisition.gamma,
               sim.storage.errors, sim.storage.lock, station.acquisition.run_reader,
               station.acquisition.run_store, station.lens.geometry, station.lens.rays,
               station.ltc.checked, station.ltc.store, station.ltc.verify]
    errors = {v for m in modules for v in vars(m).values()
              if isinstance(v, type) and issubclass(v, Exception) and v.__module__ == m.__name__}
    assert len(errors) >= 30
    assert [e.__qualname__ for e in errors if not issubclass(e, roots)] == []
    assert issubclass(CameraTimeout, drivers.errors.CameraError)


def test_a_run_log_records_every_device_exchange_at_debug(tmp_path, capsys, monkeypatch):
    from drivers.stage import ZaberStage
    from fakes.zaber import FakeZaberDevice, FakeZaberPty
    from station.sequence import Sequence

    def check_on_a_fake_stage(self):
        device = FakeZaberDevice(limit_max=500_000, position=100_000, maxspeed=327_680,
                                 accel=16_384)
        with FakeZaberPty(device) as server, ZaberStage(
                server.port, microstep_um=0.1, travel_mm=(0.0, 40.0), poll_s=0.005) as stage:
            stage.home()
            stage.move_to(3.25)
        raise StationError("stopped after the stage exchange")

    assert main(["config", "--example", "fake"]) == 0
    cfg = tmp_path / "fake.toml"
    cfg.write_text(capsys.readouterr().out)
    monkeypatch.setattr(Sequence, "_check", check_on_a_fake_stage)
    seq = tmp_path / "seq"
    code, _, err = call(["run", str(cfg), "--out", str(seq)], capsys)
    assert code == 1 and err.startswith("ltc run: error: stopped after the stage exchange")
    log = (seq / "run.log").read_text().splitlines()
    sent = [line for line in log if " DEBUG drivers.zaber_link " in line and ": sent " in line]
    got = [line for line in log if " DEBUG drivers.zaber_link " in line and ": got " in line]
    assert any(re.search(r"sent '/1 1 \d\d move abs 32500:[0-9A-F]{2}'$", line) for line in sent)
    assert len(got) >= len(sent) > 3
    assert any(" DEBUG drivers.stage " in line and "move to 3.25 mm: done at 3.25 mm" in line
               for line in log)
    assert any("check: failed: stopped after the stage exchange" in line for line in log)
