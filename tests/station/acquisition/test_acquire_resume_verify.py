"""``ltc acquire --resume`` reads back every done frame and captures the damaged ones again,
saying which; the store then equals an undamaged run bit for bit. ``ltc verify`` reports the
same damage without changing anything."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from station.acquisition.run_store import META_ARRAYS, RunStore
from station.cli import main
from tests.support.configs import small_fake_config_text


def one_depth_text() -> str:
    return small_fake_config_text((40.0, 70.0))


def frames(path) -> np.ndarray:
    s = RunStore.open(path)
    return np.stack([s.read_frame(d, p) for d in range(s.n_depths) for p in range(s.n_patterns)])


@pytest.mark.slow
def test_resume_recaptures_damaged_frames_bit_for_bit(tmp_path, capsys, caplog):
    cfg = tmp_path / "run.toml"
    cfg.write_text(one_depth_text())
    run = tmp_path / "run.zarr"
    assert main(["acquire", str(cfg), "--out", str(run), "--quiet"]) == 0
    clean = tmp_path / "clean.zarr"
    shutil.copytree(run, clean)
    shard = run / "frames" / "c"
    (shard / "0" / "2" / "0" / "0").unlink()  # a deleted frame
    raw = bytearray((shard / "1" / "5" / "0" / "0").read_bytes())
    raw[100] ^= 0x01  # one altered bit
    (shard / "1" / "5" / "0" / "0").write_bytes(bytes(raw))
    capsys.readouterr()

    assert main(["verify", str(run)]) == 1
    out = capsys.readouterr().out
    assert "2 damaged" in out and "depth 0 = 40 mm, pattern 2) is marked done but its data " \
        "is missing" in out and "pattern 5) is marked done but its data fails the crc32c" in out
    assert not (shard / "0" / "2" / "0" / "0").exists()  # verify changed nothing

    assert main(["acquire", str(cfg), "--out", str(run), "--resume", "--json"]) == 0
    report = capsys.readouterr()
    assert "2 done frame(s) are damaged and will be recaptured: (depth 0, pattern 2), " \
        "(depth 1, pattern 5)" in caplog.text  # a warning in the run's log and on stderr
    assert '"frames_recaptured": [[0, 2], [1, 5]]' in report.out
    assert '"frames_written": 2' in report.out
    assert main(["verify", str(run)]) == 0
    np.testing.assert_array_equal(frames(run), frames(clean))
    a, b = RunStore.open(run), RunStore.open(clean)
    np.testing.assert_array_equal(a.done(), b.done())
    for name in ("frame_crc32c", "saturated_px", "stage_target_mm"):
        assert name in META_ARRAYS
        np.testing.assert_array_equal(a.read_meta(0)[name], b.read_meta(0)[name])
        np.testing.assert_array_equal(a.read_meta(1)[name], b.read_meta(1)[name])
