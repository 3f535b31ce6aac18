"""LTC store chunks carry checksums verified on every read: a deleted, truncated or altered
chunk of a done tile is refused by ``ltc lens`` and reported by ``ltc verify``, naming the
store, array, depth and tile; the undamaged store reads exactly as zarr reads it."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest
import zarr

from fakes.bench import BenchConfig, FakeBench
from station.cli import main
from station.ltc.checked import LtcChunkError
from station.ltc.store import open_ltc_volume
from tests.support.ltc_stores import write_true_ltc_store

DEPTHS = [0.0, 30.0, 60.0, 250.0, 290.0]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    bench = FakeBench(BenchConfig.small(lcd_size=(120, 96), lcd_distance_at_zero_mm=100.0,
                                        pupil_samples=150, subpixels=1))
    root = tmp_path_factory.mktemp("checked")
    return write_true_ltc_store(root / "ltc.zarr", bench, DEPTHS, period=24, tile_px=16)


def lens(store, out, capsys) -> tuple[int, str]:
    code = main(["lens", str(store), "--out", str(out), "--samples", "8", "--grid-step", "8",
                 "--workers", "1", "--quiet"])
    return code, capsys.readouterr().err


def test_checked_reads_equal_zarr_reads(store):
    v = open_ltc_volume(store)
    g = zarr.open_group(str(store), mode="r")
    for name in ("ltc", "origin", "gain", "noise"):
        a, want = getattr(v, name), np.asarray(g[name])
        np.testing.assert_array_equal(a[...], want)
        np.testing.assert_array_equal(a[1, 5:23, 3:37], want[1, 5:23, 3:37])
        np.testing.assert_array_equal(a[:, 17, 2:30], want[:, 17, 2:30])
        np.testing.assert_array_equal(a[-1, :, -3], want[-1, :, -3])


def chunk(store, name, depth, tr, tc):
    extra = {"ltc": "/0/0", "origin": "/0", "lcd_xy": "/0"}.get(name, "")
    return store / name / "c" / f"{depth}/{tr}/{tc}{extra}"


def damage_delete(path):
    path.unlink()


def damage_truncate(path):
    path.write_bytes(path.read_bytes()[:250])


def damage_weight(path):
    a = np.frombuffer(path.read_bytes(), "<f4").copy()
    i = int(np.flatnonzero(np.isfinite(a) & (a != 0))[7])
    a[i] *= 1e6
    path.write_bytes(a.tobytes())


@pytest.mark.parametrize("name, damage, why", [
    ("ltc", damage_delete, "chunk file is missing"),
    ("origin", damage_delete, "chunk file is missing"),
    ("origin", damage_truncate, "truncated or resized"),
    ("ltc", damage_weight, "fails its crc32c"),
    ("gain", damage_weight, "fails its crc32c"),
    ("noise", damage_truncate, "truncated or resized"),
])
@pytest.mark.slow
def test_a_damaged_chunk_is_refused_naming_it(store, tmp_path, capsys, name, damage, why):
    copy = tmp_path / "ltc.zarr"
    shutil.copytree(store, copy)
    damage(chunk(copy, name, 1, 1, 2))
    before = sorted((p.relative_to(copy), p.stat().st_mtime_ns) for p in copy.rglob("*"))
    code, err = lens(copy, tmp_path / "lens.npz", capsys)
    lines = err.strip().splitlines()
    assert code == 1 and len(lines) == 1, err
    assert lines[0].startswith(f"ltc lens: error: {copy}: array '{name}', depth 1, tile (1, 2) "
                               "(camera rows 16.., columns 32..") and why in lines[0], err
    assert not (tmp_path / "lens.npz").exists()
    assert main(["verify", str(copy)]) == 1
    out = capsys.readouterr().out
    assert f"array '{name}', depth 1, tile (1, 2)" in out and "1 damaged" in out, out
    after = sorted((p.relative_to(copy), p.stat().st_mtime_ns) for p in copy.rglob("*"))
    assert after == before  # verify changed nothing


@pytest.mark.slow
def test_an_undamaged_store_verifies_and_gives_the_lens(store, tmp_path, capsys):
    assert main(["verify", str(store), "--json"]) == 0
    out = capsys.readouterr().out
    assert '"ok": true' in out and '"kind": "LTC store"' in out
    code, err = lens(store, tmp_path / "lens.npz", capsys)
    assert code == 0, err
    assert main(["verify", str(tmp_path / "lens.npz")]) == 0
    assert "lens file" in capsys.readouterr().out
    raw = bytearray((tmp_path / "lens.npz").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (tmp_path / "bad.npz").write_bytes(bytes(raw))
    assert main(["verify", str(tmp_path / "bad.npz")]) == 1
    assert "damaged" in capsys.readouterr().out


def test_a_chunk_changed_after_its_first_read_is_verified_again(store, tmp_path):
    """Reads of a few rows of a chunk this process verified whole read only those rows, while
    the chunk's file is unchanged; a chunk replaced since is verified (and refused) again."""
    copy = tmp_path / "ltc.zarr"
    shutil.copytree(store, copy)
    v = open_ltc_volume(copy)
    want = np.asarray(zarr.open_group(str(copy), mode="r")["ltc"][2, 16:18, 32:48])
    np.testing.assert_array_equal(v.ltc[2, 16:32, 32:48][:2], want)  # verified whole
    np.testing.assert_array_equal(v.ltc[2, 16:18, 32:48], want)  # rows only
    v.ltc[1, 0:16, 0:16]  # another chunk read last
    path = chunk(copy, "ltc", 2, 1, 2)
    damage_weight(path)  # rewritten: a new modification time
    os.utime(path, ns=(0, 0))
    with pytest.raises(LtcChunkError, match=r"array 'ltc', depth 2, tile \(1, 2\).*crc32c"):
        v.ltc[2, 16:18, 32:48]
