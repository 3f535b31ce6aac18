"""Run stores that cannot be silently wrong: frame checksums, cross-checks of the
attributes against the frame records, the writer lock, atomic creation, and the writer queue's
frames equal to the serial path's, bit for bit."""

import errno
import os
import re
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import zarr

from sim.storage.lock import LOCK_NAME
from station.acquisition.acquire import AcquisitionError, Event, acquire
from station.acquisition.config import parse_config
from station.acquisition.patterns import StationPatternPlan
from station.acquisition.run_store import FrameCorruptError, FrameMeta, RunStore, RunStoreError
from station.cli import main
from tests.support.configs import small_fake_config_text

CAM = (20, 13)  # (width, height): edge chunks are partial with tile 8
LCD = (24, 16)
PLAN = StationPatternPlan.for_lcd(LCD, 4, 4)


def meta(p: int, z: float = 40.0) -> FrameMeta:
    return FrameMeta(stage_target_mm=z, stage_measured_mm=z, swap_index=p, swap_time_s=0.0,
                     camera_timestamp_s=0.0, frame_id=p, exposure_ms=20.0)


def frame(p: int) -> np.ndarray:
    return np.random.default_rng(p).integers(0, 4096, CAM[::-1]).astype(np.uint16)


@pytest.fixture
def run(tmp_path):
    """A complete one-depth run store of random 12-bit frames."""
    s = RunStore.create(tmp_path / "run.zarr", config={}, plan=PLAN, depths_mm=[40.0],
                        camera_size=CAM, bit_depth=12, lcd_size=LCD, lcd_pitch_mm=0.25,
                        tile_px=8)
    for p in range(len(PLAN)):
        s.write_frame(0, p, frame(p), meta(p))
    return s


def shard(s: RunStore, p: int):
    return s.path / "frames" / "c" / "0" / str(p) / "0" / "0"


def test_frames_read_back_exactly_through_the_store_tiles_and_zarr(run):
    n = len(PLAN)
    want = np.stack([frame(p) for p in range(n)])
    assert run.verify() == n
    for p in (0, 5, n - 1):
        np.testing.assert_array_equal(run.read_frame(0, p), want[p])
    np.testing.assert_array_equal(zarr.open_group(str(run.path), mode="r")["frames"][0], want)
    for t in (8, 5, 64):
        got = np.zeros_like(want)
        for tile in run.iter_tiles(0, t, block_bytes=1):  # one tile per block too
            _, th, tw = tile.frames.shape
            got[:, tile.row0 : tile.row0 + th, tile.col0 : tile.col0 + tw] = tile.frames
        np.testing.assert_array_equal(got, want)
    tile = run.read_tile(0, 3, 5, 7, 9)  # not aligned to the chunks
    np.testing.assert_array_equal(tile.frames, want[:, 3:10, 5:14])
    crc = run.read_meta(0)["frame_crc32c"]
    assert (crc >= 0).all() and len(set(crc.tolist())) == n


def _delete(path):
    path.unlink()


def _truncate(path):
    os.truncate(path, path.stat().st_size - 100)


def _flip_data(path):
    raw = bytearray(path.read_bytes())
    raw[3 * 132 + 17] ^= 0x04  # chunk 3 (8 x 8 uint16 + crc32c = 132 bytes), a pixel's bit
    path.write_bytes(bytes(raw))


def test_prefetch_is_a_hint_only(run):
    """Prefetching a row of tiles changes nothing read, and is silent about damage, which the
    read then refuses."""
    want = [t.frames.copy() for t in run.read_tile_row(0, 8, 0, 3)]
    run.prefetch_tile_row(0, 8, 0, 3)
    for got, w in zip(run.read_tile_row(0, 8, 0, 3), want, strict=True):
        np.testing.assert_array_equal(got.frames, w)
    shard(run, 5).unlink()
    run.prefetch_tile_row(0, 8, 0, 3)
    with pytest.raises(FrameCorruptError, match=r"pattern 5\) is marked done but its data is "
                                                r"missing"):
        run.read_tile_row(0, 8, 0, 3)


def _flip_index(path):
    raw = bytearray(path.read_bytes())
    raw[-10] ^= 0x01
    path.write_bytes(bytes(raw))


@pytest.mark.parametrize("damage", [_delete, _truncate, _flip_data, _flip_index])
def test_damaged_frame_fails_reconstruction_naming_depth_and_pattern(run, damage, tmp_path,
                                                                     capsys):
    damage(shard(run, 5))
    with pytest.raises(FrameCorruptError, match=r"frame \(depth 0 = 40 mm, pattern 5\)"):
        run.read_frame(0, 5)
    code = main(["reconstruct", str(run.path), "--out", str(tmp_path / "ltc.zarr"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 1
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert re.search(r"ltc reconstruct: error: .*run\.zarr: frame \(depth 0 = 40 mm, pattern 5\) "
                     r"is marked done but its data", err), err


def test_attributes_that_disagree_with_the_frame_records_are_refused(run, tmp_path, capsys):
    g = zarr.open_group(str(run.path), mode="r+")
    g.attrs["depths_mm"] = [70.0]
    with pytest.raises(RunStoreError, match=r"attribute 'depths_mm' \[70.0\] disagrees with the "
                                            r"recorded stage target of \d+ done frame"):
        RunStore.open(run.path)
    assert main(["reconstruct", str(run.path), "--out", str(tmp_path / "ltc.zarr")]) == 1
    assert "attribute 'depths_mm'" in capsys.readouterr().err
    g.attrs["depths_mm"] = [40.0]
    g.attrs["tile_px"] = 16
    with pytest.raises(RunStoreError, match=r"attribute 'tile_px' \(16\) disagrees with array "
                                            "'frames' chunks"):
        RunStore.open(run.path)
    g.attrs["tile_px"] = 8
    g.attrs["bit_depth"] = 8
    with pytest.raises(RunStoreError, match=r"attribute 'bit_depth' \(8\) disagrees"):
        RunStore.open(run.path)
    g.attrs["bit_depth"] = 12
    g.attrs["config"] = {"display": {"pitch_mm": 0.3}}
    with pytest.raises(RunStoreError, match="attribute 'lcd_pitch_mm' .* disagrees with the "
                                            "stored config's display.pitch_mm"):
        RunStore.open(run.path)
    g.attrs["config"] = {}
    RunStore.open(run.path)
    with pytest.raises(RunStoreError, match=r"stage target 41.0 mm, but depth 0 is 40.0 mm"):
        RunStore.open(run.path, "r+").write_frame(0, 0, frame(0), meta(0, 41.0))


# ---- acquisition: atomic creation, writer queue, writer errors --------------------------------


def one_depth_text() -> str:
    return small_fake_config_text()


def stop_at(pattern: int):
    def hook(event, hw):
        if event == Event(0, pattern):
            raise KeyboardInterrupt
    return hook


KILL_AT_CREATION = textwrap.dedent("""
    import os, signal, sys
    from pathlib import Path
    import station.acquisition.run_store as rs
    from station.acquisition.acquire import acquire
    from station.acquisition.config import load_config
    out, after_rename = Path(sys.argv[2]), sys.argv[3] == "1"
    real = rs.fsync_path
    def fsync(path):
        real(path)
        if not after_rename and path.name == "zarr.json" and path.parent.name == "frames":
            os.kill(os.getpid(), signal.SIGKILL)  # mid-creation, the temporary store half made
        if after_rename and Path(path) == out.parent:
            os.kill(os.getpid(), signal.SIGKILL)  # just after the rename
    rs.fsync_path = fsync
    acquire(load_config(sys.argv[1]), out, progress=False)
""")


@pytest.mark.parametrize("after_rename", [False, True])
def test_acquire_killed_at_store_creation_can_start_fresh_or_resume(tmp_path, after_rename):
    cfg = tmp_path / "one.toml"
    cfg.write_text(one_depth_text())
    out = tmp_path / "run.zarr"
    proc = subprocess.run([sys.executable, "-c", KILL_AT_CREATION, str(cfg), str(out),
                           str(int(after_rename))], capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    config = parse_config(one_depth_text(), "<one>")
    if after_rename:  # a complete store, not locked yet: --resume takes it up
        assert RunStore.open(out).done().sum() == 0
        with pytest.raises(KeyboardInterrupt):
            acquire(config, out, resume=True, progress=False, before_event=stop_at(3))
    else:  # nothing at --out (the half-made temporary folder is beside it): start fresh
        assert not out.exists()
        assert [p.name.startswith(".run.zarr.creating-") for p in tmp_path.iterdir()
                if p.name != "one.toml"] == [True]
        with pytest.raises(AcquisitionError, match="no such run store"):
            acquire(config, out, resume=True, progress=False)
        with pytest.raises(KeyboardInterrupt):
            acquire(config, out, progress=False, before_event=stop_at(3))
    store = RunStore.open(out)
    assert store.done()[0].tolist() == [True] * 3 + [False] * (store.n_patterns - 3)
    assert not (out / LOCK_NAME).exists()


def test_writer_queue_gives_the_frames_of_the_serial_path(tmp_path):
    config = parse_config(one_depth_text(), "<one>")
    acquire(config, tmp_path / "serial.zarr", progress=False, writer_queue=0)
    acquire(config, tmp_path / "queued.zarr", progress=False, writer_queue=3)
    a = zarr.open_group(str(tmp_path / "serial.zarr"), mode="r")
    b = zarr.open_group(str(tmp_path / "queued.zarr"), mode="r")
    assert np.asarray(b["done"][...]).all()
    for name in ("frames", "done", "code_mask", "frame_crc32c", "saturated_px", "retries",
                 "stage_target_mm", "stage_measured_mm"):
        np.testing.assert_array_equal(np.asarray(a[name][...]), np.asarray(b[name][...]))
    assert RunStore.open(tmp_path / "queued.zarr").verify() == a["done"].size


def test_a_writer_error_stops_the_run_with_one_error_and_keeps_what_is_done(tmp_path,
                                                                            monkeypatch):
    config = parse_config(one_depth_text(), "<one>")
    real = RunStore.store_encoded

    def full_disk(self, frame):
        if frame.pattern == 4:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.path))
        return real(self, frame)

    monkeypatch.setattr(RunStore, "store_encoded", full_disk)
    out = tmp_path / "run.zarr"
    with pytest.raises(AcquisitionError, match=r"run\.zarr: could not write frame \(depth 0, "
                                               r"pattern 4\): .*no space left on device; free "
                                               r"some space.*frames written before it are done"):
        acquire(config, out, progress=False)
    monkeypatch.undo()
    store = RunStore.open(out)
    assert store.done()[0, :4].all() and not store.done()[0, 4:].any()
    assert store.group.attrs["status"] == "failed" and not (out / LOCK_NAME).exists()
    for p in range(4):
        store.read_frame(0, p)

