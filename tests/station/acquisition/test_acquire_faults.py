"""Acquisition and reconstruction under faults, from the outside: a disk that fills up part
way (``ltc acquire`` and ``ltc reconstruct`` end with one line, exit 1, and finish to
bit-identical stores once there is space again), and a fake-bench run with random camera,
display and stage faults finished by retries and ``--resume``."""

from __future__ import annotations

import errno
import logging
from pathlib import Path

import numpy as np
import pytest
import zarr
import zarr.storage._local as zarr_local

from drivers.interfaces import DeviceError
from sim.storage import durable
from station.acquisition import run_store
from station.acquisition.acquire import acquire
from station.acquisition.backend import Hardware, open_fake_hardware
from station.acquisition.config import example_text, parse_config
from station.cli import main
from station.errors import StationError

pytestmark = pytest.mark.timeout(240)

SMALL = {  # the fake example cut down as in test_acquire.py: two depths, P = 4, coarse truth
    "depths_mm = [40.0, 70.0, 130.0, 160.0]": "depths_mm = [40.0, 160.0]",
    "period = 12": "period = 4",
    "timeout_s = 2.0": "timeout_s = 0.05",
    "pupil_samples = 200 ": "pupil_samples = 48 ",
    "subpixels = 2": "subpixels = 1",
}


def small_text() -> str:
    text = example_text("fake")
    for old, new in SMALL.items():
        assert old in text, old
        text = text.replace(old, new, 1)
    return text


def small_config():
    return parse_config(small_text(), "<small>")


def read_store(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    """The run store's arrays (read straight from zarr) and attributes."""
    g = zarr.open_group(str(path), mode="r")
    return {name: np.asarray(g[name][...]) for name in ("frames", "done", "retries", "code_mask",
                                                        "camera_timestamp_s")}, dict(g.attrs)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """A fault-free run of the small config and its LTC store."""
    tmp = tmp_path_factory.mktemp("ref")
    (tmp / "small.toml").write_text(small_text())
    assert main(["acquire", str(tmp / "small.toml"), "--out", str(tmp / "run.zarr"),
                 "--quiet"]) == 0
    assert main(["reconstruct", str(tmp / "run.zarr"), "--out", str(tmp / "ltc.zarr"),
                 "--quiet", "--json"]) == 0
    return tmp


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


class FullDisk:
    """Every file write under ``root`` counts its bytes; once ``budget`` bytes are written the
    disk is full: writes raise ``OSError(ENOSPC)`` naming the file, as the kernel's would,
    until :meth:`free`. Patched: ``zarr.storage._local._put`` (every chunk and metadata file
    zarr writes) and ``sim.storage.durable.write_all`` (every shard, per-frame record and
    LTC tile the stores write themselves, also as the run store imported it)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, root: Path, budget: int) -> None:
        self.root, self.left, self.refused = str(root), budget, 0
        self._put, self._write = zarr_local._put, durable.write_all
        monkeypatch.setattr(zarr_local, "_put", self.put)
        monkeypatch.setattr(durable, "write_all", self.write)
        monkeypatch.setattr(run_store, "write_all", self.write)

    def _spend(self, path: Path, n: int) -> None:
        if str(path).startswith(self.root):
            if n > self.left:
                self.refused += 1
                raise OSError(errno.ENOSPC, "No space left on device", str(path))
            self.left -= n

    def put(self, path: Path, value, exclusive: bool = False) -> int:
        self._spend(path, len(value.as_buffer_like()))
        return self._put(path, value, exclusive)

    def write(self, path: Path, fd: int, parts: list, offset: int | None = None) -> None:
        self._spend(path, sum(memoryview(p).nbytes for p in parts))
        self._write(path, fd, parts, offset)

    def free(self) -> None:
        self.left = 1 << 60


def _one_error_line(capsys, command: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"ltc {command}: error: "), err
    return err[0]


@pytest.mark.slow
def test_acquire_into_a_full_disk_stops_with_one_line_and_resumes_bit_identical(
        reference, tmp_path, monkeypatch, capsys):
    ref, _ = read_store(reference / "run.zarr")
    cfg, out = reference / "small.toml", tmp_path / "run.zarr"
    disk = FullDisk(monkeypatch, tmp_path, _size(reference / "run.zarr") // 2)
    capsys.readouterr()
    assert main(["acquire", str(cfg), "--out", str(out), "--quiet"]) == 1
    line = _one_error_line(capsys, "acquire")
    assert "no space left on device; free some space, then run the command again (with " \
           "--resume" in line and str(out) in line and disk.refused >= 1
    before, attrs = read_store(out)
    done = before["done"]
    assert 0 < done.sum() < done.size  # the disk filled part way
    np.testing.assert_array_equal(before["frames"][done], ref["frames"][done])  # nothing lost
    disk.free()
    assert main(["acquire", str(cfg), "--out", str(out), "--resume", "--quiet"]) == 0
    after, attrs = read_store(out)
    assert after["done"].all() and attrs["status"] == "complete"
    for name in ("frames", "code_mask"):
        np.testing.assert_array_equal(after[name], ref[name])
    np.testing.assert_array_equal(after["camera_timestamp_s"][done],
                                  before["camera_timestamp_s"][done])  # none written twice


@pytest.mark.slow
def test_reconstruct_into_a_full_disk_stops_with_one_line_and_resumes_bit_identical(
        reference, tmp_path, monkeypatch, capsys):
    out = tmp_path / "ltc.zarr"
    disk = FullDisk(monkeypatch, tmp_path, _size(reference / "ltc.zarr") // 3)
    capsys.readouterr()
    # one worker: the full disk is simulated in this process
    args = ["reconstruct", str(reference / "run.zarr"), "--out", str(out), "--quiet",
            "--workers", "1"]
    assert main(args) == 1
    line = _one_error_line(capsys, "reconstruct")
    assert "no space left on device" in line and str(out) in line and disk.refused >= 1
    assert "--resume" in line
    # the incomplete store is refused by the lens, and finished by --resume
    assert main(["lens", str(out), "--out", str(tmp_path / "lens.npz"), "--quiet"]) == 1
    assert "incomplete" in _one_error_line(capsys, "lens")
    disk.free()
    assert main(args + ["--resume"]) == 0
    got, want = (zarr.open_group(str(p), mode="r") for p in (out, reference / "ltc.zarr"))
    for name in ("ltc", "origin", "gain", "noise", "lcd_xy"):
        np.testing.assert_array_equal(np.asarray(got[name]), np.asarray(want[name]))


# ---- random faults --------------------------------------------------------------------------

FAULTS = ("camera timeout", "camera stale", "camera drop", "camera garbage", "display repeat",
          "stage garbled reply", "stage bad checksum", "stage stall", "stage short")


@pytest.mark.slow
def test_random_faults_are_retried_or_resumed_to_the_fault_free_frames(reference, tmp_path,
                                                                       caplog):
    """Faults at a seeded rate of 12 % per event: every run either completes or stops with
    a typed one-line error, and resuming finishes the store with the fault-free frames."""
    rng = np.random.default_rng(17)
    injected: dict[str, int] = {}

    def fault(event, hw):
        if rng.random() >= 0.12:
            return
        kind = FAULTS[rng.integers(len(FAULTS))]
        injected[kind] = injected.get(kind, 0) + 1
        cam = hw.camera.faults
        if kind == "camera timeout":
            cam.timeout = 1
        elif kind == "camera stale":
            cam.stale = 2
        elif kind == "camera drop":
            cam.drop = 3
        elif kind == "camera garbage":
            cam.garbage = 2
        elif kind == "display repeat":
            hw.display.faults.repeat_previous = 1
        else:  # the stage faults hit the next move (at the next depth) or the next replies
            f = bench["fake"].device.faults
            if kind == "stage garbled reply":
                f.garble_replies = 1
            elif kind == "stage bad checksum":
                f.bad_checksum_replies = 1
            elif kind == "stage stall":
                f.stall_at = 0.5
            else:
                f.stop_short = 50

    out = tmp_path / "run.zarr"
    config = small_config()
    failures, retries, bench = [], {}, {}
    caplog.set_level(logging.ERROR)
    for _ in range(12):
        try:
            with open_fake_hardware(config) as fake:  # a fresh bench per run, as a re-run gets
                bench["fake"] = fake
                summary = acquire(config, out, resume=out.exists(), progress=False,
                                  hw=Hardware(fake.stage, fake.lcd, fake.camera),
                                  before_event=fault)
        except (StationError, DeviceError, ValueError, OSError) as exc:  # the CLI's one line
            failures.append(f"{type(exc).__name__}: {' '.join(str(exc).split())[:120]}")
            continue
        for k, v in summary["retries"].items():
            retries[k] = retries.get(k, 0) + v
        break
    else:
        pytest.fail(f"not complete after 12 runs: {failures}")
    after, attrs = read_store(out)
    ref, _ = read_store(reference / "run.zarr")
    assert after["done"].all() and attrs["status"] == "complete"
    np.testing.assert_array_equal(after["frames"], ref["frames"])
    assert sum(injected.values()) >= 8 and retries  # faults happened and were retried
    print(f"\nrandom faults: injected {injected}; runs failed {len(failures)} "
          f"({failures}); retries in the final run {retries}")
