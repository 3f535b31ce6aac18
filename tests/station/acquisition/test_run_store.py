"""station.acquisition.run_store: layout, exact readback, frame-by-frame durability, validation errors."""

import numpy as np
import pytest
import zarr

from station.acquisition.patterns import StationPatternPlan
from station.acquisition.run_store import META_ARRAYS, FrameMeta, RunStore, RunStoreError

CAM = (10, 7)  # (width, height)
LCD = (24, 16)
PLAN = StationPatternPlan.for_lcd(LCD, 4, 3)
CONFIG = {"backend": "fake", "depths_mm": [1.0, 2.5], "nested": {"a": [1, 2]}}


def make(tmp_path, name="run.zarr", bit_depth=12, tile_px=4, **kw):
    args = {"config": CONFIG, "plan": PLAN, "depths_mm": [1.0, 2.5], "camera_size": CAM,
            "bit_depth": bit_depth, "lcd_size": LCD, "lcd_pitch_mm": 0.25, "tile_px": tile_px}
    args.update(kw)
    return RunStore.create(tmp_path / name, **args)


def meta(p, d=0, **kw):
    base = {"stage_target_mm": 2.5 if d else 1.0, "stage_measured_mm": 1.0001, "swap_index": p,
            "swap_time_s": 10.0 + p, "camera_timestamp_s": 10.01 + p, "frame_id": 100 + p,
            "exposure_ms": 20.0, "retries": p % 2}
    base.update(kw)
    return FrameMeta(**base)


def frame(d, p, dtype=np.uint16, full=4095):
    rng = np.random.default_rng(1000 * d + p)
    return rng.integers(0, full + 1, (CAM[1], CAM[0])).astype(dtype)


def test_layout_attributes_and_chunking(tmp_path):
    s = make(tmp_path, start_time="2024-05-01T12:00:00+00:00")
    g = zarr.open_group(str(tmp_path / "run.zarr"), mode="r")
    n = len(PLAN)
    assert g["frames"].shape == (2, n, CAM[1], CAM[0]) and g["frames"].dtype == np.uint16
    assert g["frames"].shards == (1, 1, 8, 12)  # one frame = one stored object
    assert g["frames"].chunks == (1, 1, 4, 4)  # inner chunks for tile readers
    assert g["done"].dtype == bool and g["done"].shape == (2, n)
    for name in ("stage_target_mm", "stage_measured_mm", "swap_index", "swap_time_s",
                 "camera_timestamp_s", "frame_id", "exposure_ms", "retries", "saturated_px"):
        assert g[name].shape == (2, n)
    assert g["frame_id"].dtype == np.int64 and g["swap_time_s"].dtype == np.float64
    a = g.attrs
    assert a["config"] == CONFIG and a["start_time"] == "2024-05-01T12:00:00+00:00"
    assert StationPatternPlan.model_validate(a["pattern_set"]) == PLAN
    assert {"python", "numpy", "zarr"} <= set(a["software"])
    assert a["depths_mm"] == [1.0, 2.5] and a["camera_size"] == [10, 7]
    assert s.dtype == np.uint16 and not s.done().any() and s.display_lut is None
    assert make(tmp_path, "b.zarr", bit_depth=8).dtype == np.uint8


def test_frames_and_metadata_read_back_exactly(tmp_path):
    s = make(tmp_path)
    for p in (0, 3, 7):
        s.write_frame(1, p, frame(1, p), meta(p, 1))
    s2 = RunStore.open(tmp_path / "run.zarr")
    for p in (0, 3, 7):
        np.testing.assert_array_equal(s2.read_frame(1, p), frame(1, p))
    m = s2.read_meta(1)
    assert m["frame_id"][3] == 103 and m["retries"][7] == 1 and m["swap_time_s"][0] == 10.0
    assert m["stage_measured_mm"][0] == 1.0001 and m["exposure_ms"][7] == 20.0
    assert m["frame_id"][1] == -1 and np.isnan(m["swap_time_s"][1])  # never written
    assert set(m) == set(META_ARRAYS)
    done = s2.done()
    assert done.sum() == 3 and done[1, [0, 3, 7]].all()


def test_display_lut_is_recorded_exactly(tmp_path):
    lut = 255.0 * np.linspace(0, 1, 1024) ** (1 / 2.2)
    make(tmp_path, display_lut=lut)
    np.testing.assert_array_equal(RunStore.open(tmp_path / "run.zarr").display_lut, lut)
    with pytest.raises(RunStoreError, match="display_lut: lut must be non-decreasing"):
        make(tmp_path, "bad.zarr", display_lut=lut[::-1])


def test_saturated_pixels_are_counted(tmp_path):
    s = make(tmp_path)
    img = np.zeros((CAM[1], CAM[0]), np.uint16)
    img[2, :5] = 4095
    s.write_frame(0, 0, img, meta(0))
    assert s.read_meta(0)["saturated_px"][0] == 5


def test_one_frame_is_one_stored_object(tmp_path):
    s = make(tmp_path)
    s.write_frame(0, 2, frame(0, 2), meta(2))
    files = [f for f in (tmp_path / "run.zarr" / "frames").rglob("*") if f.is_file()]
    assert [f.name for f in files if f.name != "zarr.json"] == ["0"]


def test_first_incomplete_and_is_complete_follow_plan_order(tmp_path):
    s = make(tmp_path)
    assert s.first_incomplete() == (0, 0) and not s.is_complete()
    n = len(PLAN)
    for d in range(2):
        for p in range(n):
            if (d, p) != (1, 5):
                s.write_frame(d, p, frame(d, p), meta(p, d))
    assert s.first_incomplete() == (1, 5)
    s.write_frame(1, 5, frame(1, 5), meta(5, 1))
    assert s.first_incomplete() is None and RunStore.open(s.path).is_complete()


def test_interrupted_write_leaves_frame_untrusted(tmp_path, monkeypatch):
    """A crash after the frame's data but before its done flag: the frame is not trusted and
    a resumed run starts there; the earlier frames are intact."""
    s = make(tmp_path)
    s.write_frame(0, 0, frame(0, 0), meta(0))

    class Crash(Exception):
        pass

    def die(*_):
        raise Crash("killed")

    monkeypatch.setattr(RunStore, "_mark_done", die)  # killed just before the done flag
    with pytest.raises(Crash):
        s.write_frame(0, 1, frame(0, 1), meta(1))
    monkeypatch.undo()
    s2 = RunStore.open(tmp_path / "run.zarr", mode="r+")
    assert s2.first_incomplete() == (0, 1)
    with pytest.raises(RunStoreError, match=r"frame \(0, 1\) is not done"):
        s2.read_frame(0, 1)
    np.testing.assert_array_equal(s2.read_frame(0, 0), frame(0, 0))
    s2.write_frame(0, 1, frame(0, 1), meta(1))  # resume rewrites it
    np.testing.assert_array_equal(s2.read_frame(0, 1), frame(0, 1))


def test_tiles_cover_the_sensor_exactly(tmp_path):
    s = make(tmp_path)
    n = len(PLAN)
    for p in range(n):
        s.write_frame(1, p, frame(1, p), meta(p, 1))
    for t in (None, 3, 64):
        out = np.zeros((n, CAM[1], CAM[0]), np.int64) - 1
        for tile in s.iter_tiles(1, t):
            _, th, tw = tile.frames.shape
            out[:, tile.row0 : tile.row0 + th, tile.col0 : tile.col0 + tw] = tile.frames
        np.testing.assert_array_equal(out, np.stack([frame(1, p) for p in range(n)]))
    with pytest.raises(RunStoreError, match=f"depth 0 has {n} frame"):
        next(s.iter_tiles(0))
    with pytest.raises(RunStoreError, match="tile_px must be >= 1"):
        next(s.iter_tiles(1, 0))


def test_resume_config_check(tmp_path):
    s = make(tmp_path)
    s.require_same_config(dict(CONFIG), PLAN)
    t = make(tmp_path, "t.zarr", config={"lcd_size": (96, 72)})
    t.require_same_config({"lcd_size": (96, 72)}, PLAN)  # tuples read back as lists
    with pytest.raises(RunStoreError, match=r"config differs from the stored run in \['backend'\]"):
        s.require_same_config({**CONFIG, "backend": "real"}, PLAN)
    with pytest.raises(RunStoreError, match="pattern set differs"):
        s.require_same_config(CONFIG, StationPatternPlan.for_lcd(LCD, 4, 4))


def test_create_refuses_to_overwrite_and_bad_arguments(tmp_path):
    make(tmp_path)
    with pytest.raises(RunStoreError, match="run.zarr: already exists"):
        make(tmp_path)
    with pytest.raises(RunStoreError, match="bit_depth must be 1..16"):
        make(tmp_path, "a.zarr", bit_depth=20)
    with pytest.raises(RunStoreError, match="config must be a dict"):
        make(tmp_path, "b.zarr", config=["x"])
    with pytest.raises(RunStoreError, match="config is not JSON-serialisable"):
        make(tmp_path, "b2.zarr", config={"path": tmp_path})
    assert not (tmp_path / "b2.zarr").exists()
    with pytest.raises(RunStoreError, match="depths_mm must list at least one depth"):
        make(tmp_path, "c.zarr", depths_mm=[])
    with pytest.raises(RunStoreError, match="tile_px must be >= 1"):
        make(tmp_path, "d.zarr", tile_px=0)
    with pytest.raises(RunStoreError, match="camera_size must be positive"):
        make(tmp_path, "e.zarr", camera_size=(0, 5))
    with pytest.raises(RunStoreError, match="Gray code does not cover"):
        make(tmp_path, "f.zarr", lcd_size=(400, 16))


def test_write_frame_refuses_bad_frames(tmp_path):
    s = make(tmp_path)
    with pytest.raises(RunStoreError, match=r"has shape \(7, 9\), expected"):
        s.write_frame(0, 0, np.zeros((7, 9), np.uint16), meta(0))
    with pytest.raises(RunStoreError, match="has dtype uint8, expected the camera's uint16"):
        s.write_frame(0, 0, np.zeros((7, 10), np.uint8), meta(0))
    with pytest.raises(RunStoreError, match="values above 4095"):
        s.write_frame(0, 0, np.full((7, 10), 4096, np.uint16), meta(0))
    with pytest.raises(RunStoreError, match="meta must be a FrameMeta"):
        s.write_frame(0, 0, frame(0, 0), {"frame_id": 1})
    with pytest.raises(RunStoreError, match=r"frame index \(depth=2, pattern=0\) outside"):
        s.write_frame(2, 0, frame(0, 0), meta(0))
    assert not s.done().any()


def test_open_validates(tmp_path):
    with pytest.raises(RunStoreError, match="nope.zarr: no such run store"):
        RunStore.open(tmp_path / "nope.zarr")
    make(tmp_path)
    with pytest.raises(RunStoreError, match="mode must be 'r' or 'r\\+'"):
        RunStore.open(tmp_path / "run.zarr", mode="w")
    (tmp_path / "plain").mkdir()
    with pytest.raises(RunStoreError, match="plain: not a zarr group"):
        RunStore.open(tmp_path / "plain")
    g = zarr.open_group(str(tmp_path / "other.zarr"), mode="w")
    g.attrs["format"] = "ltc-store"
    with pytest.raises(RunStoreError, match="attribute 'format' is 'ltc-store'"):
        RunStore.open(tmp_path / "other.zarr")
    g = zarr.open_group(str(tmp_path / "run.zarr"), mode="r+")
    g.attrs["format_version"] = 99
    with pytest.raises(RunStoreError, match="'format_version' is 99, expected 2"):
        RunStore.open(tmp_path / "run.zarr")
    g.attrs["format_version"] = 1
    with pytest.raises(RunStoreError, match="'format_version' is 1, an older run-store layout"):
        RunStore.open(tmp_path / "run.zarr")
    g.attrs["format_version"] = 2
    g.attrs["pattern_set"] = {"fourier": {"period": 2}}
    with pytest.raises(RunStoreError, match="'pattern_set' is not a pattern plan"):
        RunStore.open(tmp_path / "run.zarr")
    g.attrs["pattern_set"] = PLAN.model_dump(mode="json")
    g.attrs["depths_mm"] = [1.0]
    n = len(PLAN)
    with pytest.raises(RunStoreError, match=rf"array 'frames' has shape \(2, {n}, 7, 10\), "
                                            rf"expected \(1, {n}, 7, 10\)"):
        RunStore.open(tmp_path / "run.zarr")
    del g.attrs["start_time"]
    with pytest.raises(RunStoreError, match=r"missing attribute\(s\) \['start_time'\]"):
        RunStore.open(tmp_path / "run.zarr")
    g.attrs["start_time"] = "x"
    g.attrs["depths_mm"] = [1.0, 2.5]
    del g["retries"]
    with pytest.raises(RunStoreError, match=r"missing array\(s\) \['retries'\]"):
        RunStore.open(tmp_path / "run.zarr")


def test_run_records_go_through_the_store(tmp_path):
    s = make(tmp_path)
    w, h = CAM
    a = np.zeros((h, w), bool)
    a[0, 1] = True
    b = np.zeros((h, w), bool)
    b[2, 0] = True
    s.add_code_mask(1, a)
    s.add_code_mask(1, b)  # OR-ed: a resumed depth keeps the earlier mask
    np.testing.assert_array_equal(s.code_mask(1), a | b)
    assert not s.code_mask(0).any()
    with pytest.raises(RunStoreError, match=r"frame index \(depth=2, pattern=0\) outside"):
        s.add_code_mask(2, a)
    s.log_retries(0, 3, ["camera timeout: x"])
    s.log_retries(1, 0, ["stale frame: y", "wrong check code: z"])
    s.set_status("running")
    s.set_frame_check({"bits": 2})
    s.set_status("complete", end_time="2024-01-01T00:00:00+00:00")
    g = RunStore.open(s.path).group
    assert g.attrs["retry_log"] == [
        {"depth": 0, "pattern": 3, "reasons": ["camera timeout: x"]},
        {"depth": 1, "pattern": 0, "reasons": ["stale frame: y", "wrong check code: z"]}]
    assert g.attrs["status"] == "complete" and g.attrs["end_time"].startswith("2024-01-01")
    assert g.attrs["frame_check"] == {"bits": 2}
