"""Files written straight to the device: an aligned array goes through O_DIRECT, and
whatever path a file takes (direct, buffered, or direct refused at open or mid-write), its bytes
on disk are the array's, under its final name only."""

import errno
import os

import numpy as np
import pytest

from sim.storage import durable as run_store
from sim.storage.durable import DIRECT_ALIGN, aligned_empty, write_new_file


@pytest.fixture
def opened(monkeypatch):
    """The flags of every os.open, in order."""
    flags: list[int] = []
    real = os.open

    def spy(path, f, *a, **k):
        flags.append(f)
        return real(path, f, *a, **k)

    monkeypatch.setattr(run_store.os, "open", spy)
    return flags


def random_array(shape, dtype=np.float32, seed=0):
    a = aligned_empty(shape, dtype)
    a[...] = np.random.default_rng(seed).normal(size=shape)
    return a


@pytest.mark.parametrize("shape,dtype", [((64, 64, 24, 24), np.float32), ((3, 5, 7), np.uint16),
                                         ((1,), np.float64)])
def test_aligned_empty_starts_on_a_block_boundary(shape, dtype):
    a = aligned_empty(shape, dtype)
    assert a.shape == shape and a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable
    assert a.ctypes.data % DIRECT_ALIGN == 0


def test_an_aligned_array_is_written_direct_with_its_exact_bytes(tmp_path, opened):
    a = random_array((16, 16, 4, 4))  # 16 kB: four blocks
    write_new_file(tmp_path / "c", [a])
    assert opened and opened[0] & os.O_DIRECT
    assert (tmp_path / "c").read_bytes() == a.tobytes()
    assert [p.name for p in tmp_path.iterdir()] == ["c"]


@pytest.mark.parametrize("case", ["unaligned address", "partial block", "two parts", "bytes"])
def test_anything_else_goes_through_the_page_cache_with_its_exact_bytes(tmp_path, opened, case):
    a = random_array((2 * DIRECT_ALIGN,), np.uint8)
    parts = {"unaligned address": [a[1 : 1 + DIRECT_ALIGN]],
             "partial block": [a[: DIRECT_ALIGN - 8]],
             "two parts": [a[:DIRECT_ALIGN], a[DIRECT_ALIGN:]],
             "bytes": [a.tobytes()]}[case]
    write_new_file(tmp_path / "c", parts)
    assert not opened[0] & os.O_DIRECT
    assert (tmp_path / "c").read_bytes() == b"".join(bytes(memoryview(p)) for p in parts)


def test_direct_refused_at_open_falls_back_to_the_page_cache(tmp_path, monkeypatch):
    real, tried = os.open, []

    def refuse(path, f, *a, **k):
        if f & os.O_DIRECT:
            tried.append(path)
            fd = real(path, f & ~os.O_DIRECT, *a, **k)  # as kernels that create, then refuse
            os.close(fd)
            raise OSError(errno.EINVAL, "Invalid argument")
        return real(path, f, *a, **k)

    monkeypatch.setattr(run_store.os, "open", refuse)
    a = random_array((8, 1024))
    write_new_file(tmp_path / "c", [a])
    assert tried
    assert (tmp_path / "c").read_bytes() == a.tobytes()
    assert [p.name for p in tmp_path.iterdir()] == ["c"]  # no temporary file left behind


def test_direct_refused_mid_write_rewrites_the_file_through_the_page_cache(tmp_path,
                                                                          monkeypatch):
    real, calls = os.write, []

    def half_then_refuse(fd, data):
        calls.append(len(data))
        if len(calls) == 1:  # the first block goes to disk, then the device refuses
            return real(fd, memoryview(data)[:DIRECT_ALIGN])
        if len(calls) == 2:
            raise OSError(errno.EINVAL, "Invalid argument")
        return real(fd, data)

    monkeypatch.setattr(run_store.os, "write", half_then_refuse)
    a = random_array((4, 1024))
    write_new_file(tmp_path / "c", [a])
    assert (tmp_path / "c").read_bytes() == a.tobytes()
    assert [p.name for p in tmp_path.iterdir()] == ["c"]


def test_a_full_disk_during_a_direct_write_names_the_file_and_leaves_nothing(tmp_path,
                                                                            monkeypatch):
    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(run_store.os, "write", full)
    with pytest.raises(OSError, match="No space left on device") as err:
        write_new_file(tmp_path / "c", [random_array((1024,))])
    assert err.value.filename == str(tmp_path / "c")
    assert list(tmp_path.iterdir()) == []


def test_reconstructed_tiles_reach_the_store_direct_and_read_back_exactly(tmp_path, opened):
    """The reconstruction's own tiles take the direct path: reconstruct_tile's LTC block is
    page-aligned, the store's writer opens its chunk with O_DIRECT, and zarr reads back the
    exact values (edge tiles, padded to a whole chunk, too)."""
    import zarr

    from station.acquisition.patterns import StationPatternPlan
    from station.ltc.spi import reconstruct_tile
    from station.ltc.store import LtcTileWriter, create_ltc_store

    p, t = 8, 16  # a 16 x 16 tile of 8 x 8 windows: 64 kB, sixteen blocks
    plan = StationPatternPlan.for_lcd((48, 32), p, 3)
    rng = np.random.default_rng(3)
    frames = rng.integers(100, 4000, (len(plan), t, t)).astype(np.uint16)
    blk, _ = reconstruct_tile(frames, plan, None, 0.0, np.zeros((t, t), bool))
    assert blk.ltc.dtype == np.float32 and blk.ltc.ctypes.data % DIRECT_ALIGN == 0
    g = create_ltc_store(tmp_path / "ltc.zarr", depths_mm=[10.0], camera_size=(24, 24),
                         period=p, pitch_mm=0.25, lcd_size=(48, 32), tile_px=t)
    writer = LtcTileWriter(g)
    opened.clear()
    writer.write(0, 0, 0, ltc=blk.ltc.reshape(t, t, p, p))
    writer.write(0, 16, 16, ltc=blk.ltc.reshape(t, t, p, p)[:8, :8])  # the sensor's corner
    assert len(opened) == 2 and all(f & os.O_DIRECT for f in opened)
    back = np.asarray(zarr.open_group(tmp_path / "ltc.zarr", mode="r")["ltc"][0])
    np.testing.assert_array_equal(back[:16, :16], blk.ltc.reshape(t, t, p, p))
    np.testing.assert_array_equal(back[16:, 16:], blk.ltc.reshape(t, t, p, p)[:8, :8])
