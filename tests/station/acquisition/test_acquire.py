"""Acquisition runs on the fake bench: the check code, retries, durability (SIGKILL + resume),
refusals before anything moves, teardown, and `ltc acquire` + `ltc reconstruct` end to end."""

import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zarr
from scipy import ndimage

from drivers.display import DisplayError
from drivers.frame_code import (
    FrameCodeError,
    FrameCodeLayout,
    calibrate_code,
    frame_code_rect,
    read_code,
    render_frame_code,
    stamp_frame_code,
)
from drivers.stage import ZaberStage
from fakes import hardware as fake_hardware
from fakes.bench import FakeBench
from fakes.hardware import parse_fake_settings
from fakes.lcd import FakeLCD
from fakes.truth import lens_truth, optical_centre_error
from station.acquisition.acquire import (
    AcquisitionError,
    Event,
    acquire,
    config_differences,
    plan_events,
)
from station.acquisition.backend import Hardware, open_fake_hardware, open_hardware
from station.acquisition.config import example_text, parse_config
from station.acquisition.run_store import CODE_MASK, RunStore
from station.cli import main
from station.lens.centroids import window_stats

EXAMPLE = example_text("fake")


def small_text(**extra: str) -> str:
    """The fake example cut down for fast tests: two depths, P = 4, a coarse ground-truth LTC,
    short camera timeouts. ``extra`` maps an example line to its replacement."""
    text = EXAMPLE
    edits = {
        "depths_mm = [40.0, 70.0, 130.0, 160.0]": "depths_mm = [40.0, 160.0]",
        "period = 12": "period = 4",
        "timeout_s = 2.0": "timeout_s = 0.05",
        "pupil_samples = 200 ": "pupil_samples = 48 ",
        "subpixels = 2": "subpixels = 1",
        **extra,
    }
    for old, new in edits.items():
        assert old in text, old
        text = text.replace(old, new, 1)
    return text


def small_config(**extra: str):
    return parse_config(small_text(**extra), "<small>")


def read_store(path):
    g = zarr.open_group(str(path), mode="r")
    return {name: np.asarray(g[name][...]) for name in ("frames", "done", "retries", CODE_MASK,
                                                        "camera_timestamp_s")}, dict(g.attrs)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted, fault-free run of the small config."""
    out = tmp_path_factory.mktemp("ref") / "run.zarr"
    summary = acquire(small_config(), out, progress=False)
    arrays, attrs = read_store(out)
    return {"summary": summary, "arrays": arrays, "attrs": attrs, "path": out}


# ---- the check code, pure ---------------------------------------------------------------------


def test_blocks_code_layout_origin_and_rect():
    layout = FrameCodeLayout(bits=3, block_px=4, style="blocks", columns=2, origin=(10, 6))
    assert layout.grid == (2, 2) and layout.shape == (8, 8)
    image = render_frame_code(0b101, layout)
    assert image[::4, ::4].tolist() == [[255, 0], [255, 0]]  # MSB first, row-major, spare black
    assert frame_code_rect(layout, (40, 30)) == (10, 6, 8, 8)
    stamped = stamp_frame_code(np.full((30, 40), 77, np.uint8), 0b101, layout)
    assert (stamped[6:14, 10:18] == image).all() and (stamped[:6] == 77).all()
    with pytest.raises(ValueError, match=r"at origin \(10, 6\) reaches \(18, 14\), outside the "
                                         r"16x12 display"):
        frame_code_rect(layout, (16, 12))
    with pytest.raises(ValueError, match="frame code 8 out of range 0..7 for 3 bits"):
        render_frame_code(8, layout)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"style": "qr"}, "frame code style must be one of .*, got 'qr'"),
    ({"columns": -1}, "frame code columns must be >= 0, got -1"),
    ({"origin": (-1, 0)}, r"frame code origin must be \(x, y\) >= 0 display pixels, got \(-1, 0\)"),
])
def test_blocks_code_layout_validation(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FrameCodeLayout(**kwargs)


def _camera(lcd: np.ndarray, rng: np.random.Generator, blur: float = 2.5) -> np.ndarray:
    """A defocused camera view of an LCD image (float luminance 0..255): blur, gain, noise."""
    img = ndimage.gaussian_filter(lcd.astype(np.float64), blur)
    return 20.0 + 12.0 * img + rng.normal(0.0, 3.0, img.shape)


def _calibration(layout, rng, size=(48, 40), blur=2.5):
    w, h = size
    dark = np.zeros((h, w), np.uint8)
    codes = np.stack([_camera(stamp_frame_code(dark, v, layout), rng, blur)
                      for v in range(2**layout.bits)])
    background = _camera(stamp_frame_code(dark + 255, 0, layout), rng, blur)
    return codes, background


def test_calibrated_code_reads_through_heavy_blur_and_masks_what_it_pollutes():
    rng = np.random.default_rng(1)
    layout = FrameCodeLayout(bits=2, block_px=10, style="blocks", columns=2, origin=(14, 14))
    cal = calibrate_code(*_calibration(layout, rng), 0)
    for v in range(4):  # every value, on random patterns (the code replaces them in its rect)
        for _ in range(5):
            pattern = rng.integers(0, 256, (40, 48)).astype(np.uint8)
            assert read_code(_camera(stamp_frame_code(pattern, v, layout), rng), cal) == v
    # polluted pixels: exactly those within the blur's reach of the code's rectangle
    x, y, w, h = frame_code_rect(layout, (48, 40))
    near = np.zeros((40, 48), bool)
    near[y - 2 : y + h + 2, x - 2 : x + w + 2] = True
    far = np.ones((40, 48), bool)
    far[y - 9 : y + h + 9, x - 9 : x + w + 9] = False
    assert cal.polluted[near].all() and not cal.polluted[far].any()
    # an exposure spanning two patterns (codes 1 and 2) is neither: refused
    mixed = 0.5 * (_camera(stamp_frame_code(np.zeros((40, 48), np.uint8), 1, layout), rng)
                   + _camera(stamp_frame_code(np.zeros((40, 48), np.uint8), 2, layout), rng))
    with pytest.raises(FrameCodeError, match=r"frame code unreadable: nearest value \d is"):
        read_code(mixed, cal)
    with pytest.raises(FrameCodeError, match=r"frame of shape \(3, 3\) does not match"):
        read_code(np.zeros((3, 3)), cal)


def test_code_calibration_refuses_what_cannot_be_read():
    rng = np.random.default_rng(2)
    layout = FrameCodeLayout(bits=2, block_px=10, style="blocks", columns=2, origin=(14, 14))
    codes, background = _calibration(layout, rng)
    with pytest.raises(FrameCodeError, match=r"code_images must be \(2\*\*bits, rows, cols\)"):
        calibrate_code(codes[:3], background, 0)
    with pytest.raises(FrameCodeError, match=r"background frame \(2, 2\) differs"):
        calibrate_code(codes, background[:2, :2], 0)
    with pytest.raises(FrameCodeError, match="background_value 4 is not a code value 0..3"):
        calibrate_code(codes, background, 4)
    flat = np.full_like(codes, 20.0)
    with pytest.raises(FrameCodeError, match="no camera pixel sees the frame code clearly"):
        calibrate_code(flat, background, 0)
    repeated = codes.copy()
    repeated[2] = codes[1]  # the display showed value 1 twice
    with pytest.raises(FrameCodeError, match="frame code values 1 and 2 look alike"):
        calibrate_code(repeated, background, 0)
    # the camera sees only the first block (x < 20; the second starts at 24)
    with pytest.raises(FrameCodeError, match="frame code values [02] and [13] look alike to the "
                                             "camera .*: a block is out of view"):
        calibrate_code(codes[:, :, :20], background[:, :20], 0)
    # blocks far smaller than the blur: no pixel sees the code without the pattern around it
    tiny = FrameCodeLayout(bits=2, block_px=2, style="blocks", columns=2, origin=(20, 16))
    with pytest.raises(FrameCodeError, match="no camera pixel sees the frame code clearly"):
        calibrate_code(*_calibration(tiny, rng), 0)


# ---- the plan and config comparison -------------------------------------------------------------


def test_plan_events_lists_what_is_not_done_in_order():
    done = np.array([[True, True, False], [False, True, False]])
    assert plan_events(done) == [Event(0, 2), Event(1, 0), Event(1, 2)]
    assert plan_events(np.ones((2, 3), bool)) == []


def test_config_differences_name_every_leaf():
    a = {"patterns": {"period": 12, "steps": 4}, "depths_mm": [1.0, 2.0], "x": 1}
    b = {"patterns": {"period": 8, "steps": 4}, "depths_mm": [1.0, 3.0], "y": 2}
    assert config_differences(a, b) == [
        "depths_mm: stored [1.0, 2.0], now [1.0, 3.0]",
        "patterns.period: stored 12, now 8",
        "x: stored 1, now '(absent)'",
        "y: stored '(absent)', now 2",
    ]
    assert config_differences(a, a) == []


# ---- durability ---------------------------------------------------------------------------------


@pytest.mark.slow
def test_sigkill_then_resume_gives_the_frames_of_an_uninterrupted_run(reference, tmp_path):
    cfg = tmp_path / "small.toml"
    cfg.write_text(small_text())
    out = tmp_path / "run.zarr"
    proc = subprocess.Popen(
        [sys.executable, "-m", "station.cli", "acquire", str(cfg), "--out", str(out), "--quiet"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    total = reference["arrays"]["done"].size
    deadline = time.monotonic() + 60
    done = 0
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if (out / "done" / "zarr.json").exists():
                done = int(np.asarray(zarr.open_group(str(out), mode="r")["done"][...]).sum())
                if done >= 40:
                    break
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    before, _ = read_store(out)
    n_before = int(before["done"].sum())
    assert 40 <= n_before < total  # killed part way (in depth 0 or 1)
    # the killed run's flock died with it: the resume needs no --force
    assert main(["acquire", str(cfg), "--out", str(out), "--resume", "--quiet"]) == 0
    assert not (out / "writer.lock").exists()
    after, attrs = read_store(out)
    ref = reference["arrays"]
    assert after["done"].all()
    np.testing.assert_array_equal(after["frames"], ref["frames"])  # no frame lost or different
    np.testing.assert_array_equal(after[CODE_MASK], ref[CODE_MASK])
    # none written twice: frames done before the kill kept their timestamps
    kept = before["done"]
    np.testing.assert_array_equal(after["camera_timestamp_s"][kept],
                                  before["camera_timestamp_s"][kept])
    assert attrs["status"] == "complete" and (after["retries"] == 0).all()


@pytest.mark.slow
def test_ctrl_c_loses_only_the_frame_in_flight_and_resume_finishes(reference, tmp_path):
    out = tmp_path / "run.zarr"

    def interrupt(event, hw):
        if event == Event(1, 7):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        acquire(small_config(), out, progress=False, before_event=interrupt)
    arrays, attrs = read_store(out)
    n = reference["arrays"]["done"].shape[1]
    assert attrs["status"] == "interrupted" and int(arrays["done"].sum()) == n + 7
    summary = acquire(small_config(), out, resume=True, progress=False)
    assert summary["frames_written"] == n - 7
    np.testing.assert_array_equal(read_store(out)[0]["frames"], reference["arrays"]["frames"])


# ---- faults: caught, re-captured, recorded --------------------------------------------------------


@pytest.mark.slow
def test_repeated_pattern_is_caught_by_the_check_code_and_recaptured(reference, tmp_path):
    out = tmp_path / "run.zarr"

    def fault(event, hw):
        if event in (Event(0, 10), Event(1, 33)):
            hw.display.faults.repeat_previous = 1

    summary = acquire(small_config(), out, progress=False, before_event=fault)
    arrays, attrs = read_store(out)
    assert summary["retries"] == {"wrong check code": 2}
    assert attrs["retry_log"] == [
        {"depth": 0, "pattern": 10, "reasons": ["wrong check code: frame shows code 1, expected 2"]},
        {"depth": 1, "pattern": 33, "reasons": ["wrong check code: frame shows code 0, expected 1"]},
    ]
    assert arrays["retries"][0, 10] == 1 and arrays["retries"][1, 33] == 1
    assert arrays["retries"].sum() == 2
    # the re-captured frames are those of the right patterns
    np.testing.assert_array_equal(arrays["frames"], reference["arrays"]["frames"])


@pytest.mark.slow
def test_camera_timeout_and_stale_frames_are_retried_and_recorded(reference, tmp_path):
    out = tmp_path / "run.zarr"

    def fault(event, hw):
        if event == Event(0, 5):
            hw.camera.faults.timeout = 1
        if event == Event(0, 20):
            hw.camera.faults.stale = 2
        if event == Event(1, 3):
            hw.camera.faults.drop = 3  # lost frames are harmless: nothing to retry

    summary = acquire(small_config(), out, progress=False, before_event=fault)
    arrays, attrs = read_store(out)
    assert summary["retries"] == {"camera timeout": 1, "stale frame": 2}
    log = {(e["depth"], e["pattern"]): e["reasons"] for e in attrs["retry_log"]}
    assert list(log) == [(0, 5), (0, 20)]
    assert log[0, 5][0].startswith("camera timeout: FakeCamera: no frame within 0.050 s")
    assert all(r.startswith("stale frame: frame id") for r in log[0, 20]) and len(log[0, 20]) == 2
    assert arrays["retries"][0, 5] == 1 and arrays["retries"][0, 20] == 2
    np.testing.assert_array_equal(arrays["frames"], reference["arrays"]["frames"])


@pytest.mark.slow
def test_averaged_frames_store_the_rounded_mean_of_fresh_verified_frames(reference, tmp_path):
    """camera.average_frames = 4: every stored frame is the mean, rounded half up, of the four
    frames the camera delivered of its pattern (pixel-exact against a recording of them),
    the frames have noise of their own, and the first of each is the single frame of the
    fault-free run; an unreadable check code in the third frame re-shows the pattern and
    captures all four again."""
    out = tmp_path / "run.zarr"
    seen: dict[Event, list[np.ndarray]] = {}
    state: dict = {}
    faulty = Event(1, 7)

    def hook(event, hw):
        last = state.get("event")
        if last is not None and last.depth != event.depth:  # drop the check code's calibration
            del seen[last][7 if last == faulty else 4:]  # frames at the new depth
        state["event"], state["frames"] = event, seen.setdefault(event, [])
        if "wrapped" in state:
            return
        capture, state["wrapped"] = hw.camera.capture, True

        def recording(*args, **kwargs):
            if state["event"] == faulty and len(state["frames"]) == 2:
                hw.camera.faults.garbage = 1
            frame = capture(*args, **kwargs)
            state["frames"].append(frame.image.copy())
            return frame

        hw.camera.capture = recording

    config = small_config(**{"timeout_s = 2.0": "timeout_s = 0.05\naverage_frames = 4"})
    assert config.camera.average_frames == 4
    summary = acquire(config, out, progress=False, before_event=hook)
    arrays, attrs = read_store(out)
    assert attrs["config"]["camera"]["average_frames"] == 4
    assert summary["retries"] == {"unreadable check code": 1}
    assert arrays["retries"].sum() == 1 and arrays["retries"][1, 7] == 1
    ref = reference["arrays"]["frames"]
    assert len(seen) == ref.shape[0] * ref.shape[1]
    for event, frames in seen.items():
        assert len(frames) == (7 if event == faulty else 4)  # 2 good, the garbage, 4 again
        at = (event.depth, event.pattern)
        np.testing.assert_array_equal(frames[0], ref[at])
        stack = np.stack(frames[-4:]).astype(np.uint64)
        np.testing.assert_array_equal(arrays["frames"][at], (stack.sum(0) + 2) // 4)
        assert all((stack[k] != stack[k + 1]).mean() > 0.3 for k in range(3))


def test_a_frame_that_stays_bad_stops_the_run_and_keeps_what_is_done(tmp_path):
    out = tmp_path / "run.zarr"

    def fault(event, hw):
        if event == Event(0, 12):
            hw.camera.faults.timeout = 10

    config = small_config(**{"max_retries = 3 ": "max_retries = 2 "})
    with pytest.raises(AcquisitionError, match=r"frame \(depth 0, pattern 12\): no good frame in 3 "
                                               r"attempts: camera timeout: .*; camera timeout"):
        acquire(config, out, progress=False, before_event=fault)
    arrays, attrs = read_store(out)
    assert int(arrays["done"].sum()) == 12 and attrs["status"] == "failed"


def test_calibration_that_cannot_get_frames_stops_the_run(tmp_path):
    config = small_config(**{"max_retries = 3 ": "max_retries = 1 "})
    with open_hardware(config) as hw:
        hw.camera.faults.timeout = 10
        with pytest.raises(AcquisitionError, match=r"no good frame of calibration capture "
                                                   r"\(1, 0, 4\) in 2 attempts: FakeCamera: no "
                                                   r"frame within"):
            acquire(config, tmp_path / "run.zarr", progress=False, hw=hw)


def test_check_code_out_of_the_cameras_view_is_refused_at_its_depth(tmp_path):
    config = small_config(**{"origin_px = [92, 68]": "origin_px = [2, 2]"})
    with pytest.raises(AcquisitionError, match=r"check code at LCD \(2, 2, 16, 8\) \(x, y, w, h\) "
                                               r"cannot be read at depth 40.0 mm: no camera pixel "
                                               r"sees the frame code clearly.*move "
                                               r"frame_check.origin_px into the camera's view"):
        acquire(config, tmp_path / "run.zarr", progress=False)


@pytest.mark.slow
def test_saturated_frames_are_counted_and_the_check_code_can_be_off(tmp_path, caplog):
    config = small_config(**{"depths_mm = [40.0, 160.0]": "depths_mm = [160.0]",
                             "exposure_ms = 20.0": "exposure_ms = 30.0",
                             "enabled = true\nbits": "enabled = false\nbits"})
    summary = acquire(config, tmp_path / "run.zarr", progress=False)
    # full white at 1.5 x the reference exposure fills 128 % of the well: the white frame and
    # the Gray code stripes saturate; the Fourier patterns (at most full white) too where
    # they peak, so a good share of the frames is flagged
    assert summary["saturated_frames"] >= 10 and summary["code_mask_fraction"] == {}
    assert "pixels saturated; lower camera.exposure_ms" in caplog.text
    arrays, attrs = read_store(tmp_path / "run.zarr")
    assert arrays["done"].all() and not arrays[CODE_MASK].any() and attrs["frame_check"] is None


# ---- refusals before anything moves -----------------------------------------------------------


@pytest.mark.parametrize(("old", "new", "message"), [
    ("[camera]", "[camera]\nexposure = 3", r"field 'camera\.exposure': Extra inputs are not permitted"),
    ("depths_mm = [40.0,", "depths_mm = [-4.0,", r"depths_mm\[0\] = -4.0 is negative"),
    ("period = 4", "period = 3", r"field 'patterns\.period': Input should be greater than or equal to 4"),
    ("depths_mm = [40.0,", "depths_mm = [400.0,", r"depths_mm\[0\] = 400.0 is outside stage\.travel_mm"),
    ("bits = 2", "bits = 9", r"field 'frame_check\.bits': Input should be less than or equal to 6"),
])
def test_bad_configs_fail_before_the_stage_is_opened(tmp_path, monkeypatch, capsys, old, new, message):
    devices = []
    real = fake_hardware.FakeZaberDevice
    monkeypatch.setattr(fake_hardware, "FakeZaberDevice",
                        lambda **kw: devices.append(real(**kw)) or devices[-1])
    cfg = tmp_path / "bad.toml"
    cfg.write_text(small_text(**{old: new}))
    assert main(["acquire", str(cfg), "--out", str(tmp_path / "run.zarr"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert str(cfg) in err
    assert re.search(message, err), err
    assert devices == [] and not (tmp_path / "run.zarr").exists()


def test_config_errors_found_with_the_devices_open_come_before_any_move(tmp_path, monkeypatch):
    cases = [
        ({"origin_px = [92, 68]": "origin_px = [150, 68]"},
         (r"frame_check: frame code of 16x8 px at origin \(150, 68\) reaches \(166, 76\), "
          r"outside the 160x120 display"), None),
        ({}, r"depths_mm \[160.0\] outside the stage's travel \(0.0, 100.0\) mm",
         property(lambda self: (0.0, 100.0))),
    ]
    for edits, message, limits in cases:
        config = small_config(**edits)
        with open_fake_hardware(config) as fake, monkeypatch.context() as patch:
            if limits is not None:
                patch.setattr(ZaberStage, "limits_mm", limits)
            hw = Hardware(fake.stage, fake.lcd, fake.camera)
            with pytest.raises(AcquisitionError, match=message):
                acquire(config, tmp_path / "run.zarr", progress=False, hw=hw)
            sent = bytes(fake.device.received_bytes)
        assert b"home" not in sent and b"move" not in sent
        assert not (tmp_path / "run.zarr").exists()


def test_existing_store_needs_resume_and_resume_needs_a_store(tmp_path, reference):
    with pytest.raises(AcquisitionError, match=r"run\.zarr: already exists; pass --resume"):
        acquire(small_config(), reference["path"], progress=False)
    with pytest.raises(AcquisitionError, match=r"cannot resume: .*missing\.zarr: no such run store"):
        acquire(small_config(), tmp_path / "missing.zarr", resume=True, progress=False)


def test_resume_with_another_config_is_refused_naming_what_differs(reference, capsys, tmp_path):
    cfg = tmp_path / "other.toml"
    cfg.write_text(small_text(**{"exposure_ms = 20.0": "exposure_ms = 18.0",
                                 "gamma = 1.0 ": "gamma = 2.2 "}))
    assert main(["acquire", str(cfg), "--out", str(reference["path"]), "--resume"]) == 1
    err = capsys.readouterr().err
    assert "refusing to resume: the config differs from the run's: " \
           "camera.exposure_ms: stored 20.0, now 18.0; fake.panel.gamma: stored 1.0, now 2.2" in err


def test_resume_on_other_devices_is_refused(reference, tmp_path, monkeypatch):
    store = tmp_path / "run.zarr"
    config = small_config()

    def stop(event, hw):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        acquire(config, store, progress=False, before_event=stop)
    with open_hardware(config) as hw:
        lcd = type(hw.display)
        monkeypatch.setattr(lcd, "size", property(lambda self: (161, 120)))
        with pytest.raises(AcquisitionError, match=r"refusing to resume: devices .*'lcd_size': "
                                                   r"\(161, 120\)\} differ from the run's"):
            acquire(config, store, resume=True, progress=False, hw=hw)
        monkeypatch.setattr(lcd, "size", property(lambda self: (320, 120)))
        with pytest.raises(AcquisitionError, match="refusing to resume: .*pattern set differs"):
            acquire(config, store, resume=True, progress=False, hw=hw)


# ---- teardown -------------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_failed_cleanup_never_hides_the_original_error(tmp_path):
    config = small_config(**{"depths_mm = [40.0, 160.0]": "depths_mm = [160.0]"})
    with open_hardware(config) as hw:
        calls = {"stop": 0}
        real_stop = hw.stage.stop

        def lost(*args, **kwargs):
            raise DisplayError("display lost")

        def stop():
            calls["stop"] += 1
            real_stop()

        def fault(event, hw):
            if event == Event(0, 3):
                hw.display.show = lost
                hw.stage.stop = stop

        with pytest.raises(DisplayError, match="display lost") as info:
            acquire(config, tmp_path / "run.zarr", progress=False, hw=hw, before_event=fault)
        assert info.value.__notes__ == [
            "teardown: could not blank the display: DisplayError: display lost"]
        assert calls["stop"] == 1  # the other cleanup steps still ran

        # a cleanup failure after a good run is itself the error
        def late(event, hw):
            if event == Event(0, 52):
                shows = iter([True])
                real = type(hw.display).show.__get__(hw.display)
                hw.display.show = lambda *a, **k: real(*a, **k) if next(shows, False) else lost()

        del hw.display.show
        with pytest.raises(AcquisitionError, match="teardown: could not blank the display: "
                                                   "DisplayError: display lost"):
            acquire(config, tmp_path / "run2.zarr", progress=False, hw=hw, before_event=late)
        assert RunStore.open(tmp_path / "run2.zarr").is_complete()


def test_devices_that_fail_to_close_do_not_hide_the_runs_error(tmp_path, monkeypatch):
    config = small_config(**{"depths_mm = [40.0, 160.0]": "depths_mm = [160.0]"})
    real_close = FakeLCD.close

    def close(self):
        real_close(self)
        raise DisplayError("EGL context lost")

    def fault(event, hw):
        if event == Event(0, 2):
            raise AcquisitionError("the run's own error")

    monkeypatch.setattr(FakeLCD, "close", close)
    with pytest.raises(AcquisitionError, match="the run's own error") as info:
        acquire(config, tmp_path / "run.zarr", progress=False, before_event=fault)
    assert info.value.__notes__ == [
        "teardown: closing the devices failed: DisplayError('EGL context lost')"]


# ---- end to end -----------------------------------------------------------------------------------


@pytest.mark.slow
def test_fake_example_acquire_and_reconstruct_recover_the_true_ltc(tmp_path, capsys):
    cfg = tmp_path / "fake.toml"
    assert main(["config", "--example", "fake"]) == 0
    cfg.write_text(capsys.readouterr().out)
    run, ltc = tmp_path / "run.zarr", tmp_path / "ltc.zarr"
    t0 = time.perf_counter()
    assert main(["acquire", str(cfg), "--out", str(run), "--quiet"]) == 0
    t1 = time.perf_counter()
    assert main(["reconstruct", str(run), "--out", str(ltc), "--json"]) == 0
    t2 = time.perf_counter()
    capsys.readouterr()
    config = parse_config(cfg.read_text())
    bench = FakeBench(parse_fake_settings(config.fake).bench_config())
    g, r = zarr.open_group(str(ltc), mode="r"), zarr.open_group(str(run), mode="r")
    lines = []
    for d, z in enumerate(config.depths_mm):
        h, origin = np.asarray(g["ltc"][d]), np.asarray(g["origin"][d])
        mask = np.asarray(r[CODE_MASK][d])
        use = np.isfinite(h[..., 0, 0])
        assert mask.any() and not use[mask].any()  # reconstruction drops what saw the code
        assert use.mean() > 0.85  # few pixels lost to the check code and to darkness
        true = bench.true_centroids_lcd_px(z)[use]
        hu, ou = h[use], origin[use]
        p = hu.shape[-1]
        whole = np.stack([(hu.sum(1) * np.arange(p)).sum(1), (hu.sum(2) * np.arange(p)).sum(1)],
                         1) / hu.sum(axis=(1, 2))[:, None] + ou
        full = np.percentile(np.linalg.norm(whole - true, axis=1), 95)
        stats = window_stats(hu, np.asarray(g["noise"][d])[use])
        err = stats.centroid + ou - true
        near = np.percentile(np.linalg.norm(err, axis=1), 95)
        normalised = np.percentile(np.linalg.norm(err / stats.centroid_std, axis=1), 95)
        lines.append(f"z={z:g} mm: used {100 * use.mean():.1f} % of pixels (check code masks "
                     f"{100 * mask.mean():.1f} %), centroid p95 full window {full:.3f} px, "
                     f"window_stats {near:.3f} px (p95 |error / predicted std| {normalised:.2f})")
        # the pipeline's centroid: its predicted noise and no more (2-D normal: 2.45), far
        # better than the whole window
        assert near < full and normalised <= 3.0
    # the whole station: the lens derived from this run against the fake bench's truth
    assert main(["lens", str(ltc), "--out", str(tmp_path / "lens.npz"), "--json",
                 "--basic"]) == 0
    lens = json.loads(capsys.readouterr().out)
    assert "fake_truth" not in lens  # the station reports what it measured, nothing more
    truth = lens_truth(dict(zarr.open_group(str(ltc), mode="r").attrs["config"]))
    np.testing.assert_allclose(truth["optical_centre_mm"], bench.optical_centre_station_mm())
    assert truth["focus_distance_mm"] == bench.config.focus_distance_mm
    truth = {**truth, **optical_centre_error(lens, truth)}
    assert truth["optical_centre_error_norm_mm"] < 0.5
    lines.append(f"optical centre error {truth['optical_centre_error_norm_mm']:.3f} mm")
    with capsys.disabled():
        print(f"\nfake example end to end: acquire {t1 - t0:.1f} s, reconstruct {t2 - t1:.1f} s\n  "
              + "\n  ".join(lines))


@pytest.mark.slow
def test_every_frame_is_captured_after_the_latency_and_the_lcd_settle_time(tmp_path):
    config = small_config(**{"latency_frames = 0 ": "latency_frames = 1\nsettle_ms = 40.0 "})
    assert config.display.settle_ms == 40.0
    out = tmp_path / "run.zarr"
    acquire(config, out, progress=False)
    g = zarr.open_group(str(out), mode="r")
    waited = np.asarray(g["camera_timestamp_s"][...]) - np.asarray(g["swap_time_s"][...])
    settled = config.display.latency_frames / config.display.refresh_hz + 0.040
    assert config.display.settled_s == pytest.approx(settled)
    assert waited.min() >= settled  # the camera is never triggered before the LCD settled
