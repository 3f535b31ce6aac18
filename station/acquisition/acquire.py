"""The acquisition engine: a run is a declarative plan of events (depth, pattern) carried out
on the bench and written to a run store frame by frame (docs/hardware.md, "Resumable runs").

For each depth with frames to take: move and settle; calibrate the check code (a capture of
every code value, so the code reads through any blur; camera pixels that see the code are
masked in ``code_mask``). For each pattern: show it with the code ``pattern % 2**bits``
stamped in, wait the display latency, capture, reject a frame that timed out, is stale or
shows the wrong code (re-capture, at most ``acquire.max_retries`` times, each retry logged
and counted), count saturated pixels, write the frame and its metadata, mark it done.

Capture and storage overlap: the engine hands each frame to a :class:`FrameWriter`
(``station.acquisition.frame_writer``), through a bounded queue (a few frames), whose three
threads encode, store and commit successive frames at once while the next frame is captured.
Durability comes from the run store: a frame is done only once it and its metadata are on
disk (fsync), so a killed run loses at most the frames in flight (queued or being written),
and ``resume=True`` takes up the first frame not done, refusing a store made with another
config. A writer error (a full disk, say) stops the run at the next frame with one
:class:`AcquisitionError` naming the frame; frames written before it stay done. The run holds
the store's writer lock (:class:`sim.storage.lock.StoreLock`) throughout; a store is
created atomically (:meth:`RunStore.create`). Teardown (blank display,
stop the stage after a failure, close the devices, record the run's status) always runs; a
failed cleanup is logged and attached to the run's error as a note, never raised in its
place (after a run that went well, it is the error).

On the fake bench the camera seeds its noise by itself from the scene of each capture (what
the LCD shows and where the stage is), so a run interrupted and resumed ends with the same
frames as one that was not; the engine treats every camera alike.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import logging
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from drivers.errors import CameraError, CameraTimeout, DeviceSettingError
from drivers.frame_code import (
    CodeCalibration,
    FrameCodeError,
    FrameCodeLayout,
    calibrate_code,
    frame_code_rect,
    read_code,
    stamp_frame_code,
)
from drivers.interfaces import Frame, ShownFrame
from sim.storage.lock import StoreLock
from station.acquisition.backend import Hardware, load_lut, open_hardware
from station.acquisition.config import StationConfig
from station.acquisition.frame_writer import (
    WRITER_QUEUE_FRAMES,
    AcquisitionError,
    FrameWriter,
)
from station.acquisition.patterns import StationPatternPlan, apply_lut
from station.acquisition.run_store import FrameMeta, RunStore, RunStoreError

log = logging.getLogger(__name__)
CODE_FAILURES = ("unreadable check code", "wrong check code")  # the pattern is shown again


@dataclass(frozen=True)
class Event:
    """One frame of the plan: pattern ``pattern`` at depth ``depth`` (indices)."""

    depth: int
    pattern: int


def plan_events(done: np.ndarray) -> list[Event]:
    """The events still to do, in plan order (depth by depth, pattern by pattern), from the
    completion mask ``done`` (depths, patterns) bool."""
    return [Event(int(d), int(p)) for d, p in np.argwhere(~np.asarray(done, dtype=bool))]


def pattern_plan(config: StationConfig, lcd_size: tuple[int, int]) -> StationPatternPlan:
    """The pattern plan of one depth for the configured patterns on an LCD of (w, h) pixels."""
    p = config.patterns
    return StationPatternPlan.for_lcd(lcd_size, p.period, p.steps, offset=p.offset,
                                      amplitude=p.amplitude)


def config_differences(stored: object, current: object, path: str = "") -> list[str]:
    """Where two JSON-like configs differ: ``"field.sub: stored X, now Y"`` per leaf."""
    if isinstance(stored, dict) and isinstance(current, dict):
        out = []
        for key in sorted(set(stored) | set(current), key=str):
            sub = f"{path}.{key}" if path else str(key)
            if key not in stored or key not in current:
                out.append(f"{sub}: stored {stored.get(key, '(absent)')!r}, "
                           f"now {current.get(key, '(absent)')!r}")
            else:
                out += config_differences(stored[key], current[key], sub)
        return out
    return [] if stored == current else [f"{path or '(config)'}: stored {stored!r}, now {current!r}"]


def run_record(config: StationConfig, lut: np.ndarray | None) -> dict:
    """What a run store keeps of the config: the config itself and the display LUT in use."""
    return {**config.model_dump(mode="json", exclude={"sequence"}),
            "display_lut": None if lut is None else [int(v) for v in lut]}


class Acquisition:
    """The engine: :meth:`setup`, then :meth:`setup_depth` and :meth:`run_event` per event,
    and :meth:`teardown`, on opened hardware and an open run store."""

    def __init__(self, config: StationConfig, hw: Hardware, store: RunStore,
                 lut: np.ndarray | None, writer: FrameWriter | None = None) -> None:
        self.config, self.hw, self.store, self.lut = config, hw, store, lut
        self.writer = FrameWriter(store, 0) if writer is None else writer
        self.plan = store.plan
        self.layout = config.frame_check.layout(store.lcd_size) if config.frame_check.enabled \
            else None
        self.calibration: CodeCalibration | None = None
        self.stage_mm = (float("nan"), float("nan"))
        self.last_frame_id: int | None = None
        self.retries: Counter[str] = Counter()
        self.saturated_frames = 0
        self.mask_fraction: dict[int, float] = {}

    # ---- setup --------------------------------------------------------------------------
    def setup(self) -> None:
        """Identity LUT on the display (the plan applies the LUT), exposure, homed stage."""
        if self.config.display.frame_code:
            log.warning("display.frame_code is on: the display driver also draws its strip code "
                        "in the LCD's top-left corner, changing every frame; camera pixels that "
                        "see that corner are not masked. Set it to false: [frame_check] verifies "
                        "the frames")
        self.hw.display.set_lut(None)
        self.hw.camera.exposure_ms = self.config.camera.exposure_ms
        if not self.hw.stage.is_homed:
            log.info("homing the stage")
            self.hw.stage.home()

    def setup_depth(self, depth: int, first_pattern: int) -> None:
        """Move to the depth, then calibrate the check code there and record its mask."""
        target = self.store.depths_mm[depth]
        measured = self.hw.stage.move_to(target)
        self.stage_mm = (target, measured)
        if self.layout is None:
            return
        attempts = self.config.acquire.max_retries + 1
        for attempt in range(attempts):
            try:
                self.calibration = self._calibrate(depth, first_pattern, self.layout)
                break
            except FrameCodeError as exc:
                if attempt + 1 == attempts:
                    raise AcquisitionError(
                        f"check code at LCD {frame_code_rect(self.layout, self.store.lcd_size)} "
                        f"(x, y, w, h) cannot be read at depth {target} mm: {exc}; move "
                        "frame_check.origin_px into the camera's view (see `ltc align`) or "
                        "enlarge frame_check.block_px") from exc
                self._retry("code calibration", f"depth {depth}", attempt, str(exc))
        assert self.calibration is not None  # the loop above calibrated (max_retries >= 0)
        mask = self.calibration.polluted
        self.writer.submit(f"the code mask of depth {depth}", self.store.add_code_mask, depth,
                           mask)
        self.mask_fraction[depth] = float(mask.mean())

    def _calibrate(self, depth: int, first_pattern: int,
                   layout: FrameCodeLayout) -> CodeCalibration:
        """Capture the code (drawn with ``layout``, the engine's) on a white display, then
        every code value on a black one; leave a frame whose code is not the first pattern's
        on screen, so a display that repeats it is caught."""
        size = self.store.lcd_size
        dark = np.broadcast_to(apply_lut(np.zeros((1, 1)), self.lut), size[::-1])
        light = np.broadcast_to(apply_lut(np.ones((1, 1)), self.lut), size[::-1])
        values = 2**layout.bits
        background = self._capture_still(stamp_frame_code(light, 0, layout),
                                         (1, depth, values))
        frames = [self._capture_still(stamp_frame_code(dark, v, layout), (1, depth, v))
                  for v in range(values)]
        self._show(stamp_frame_code(dark, (first_pattern - 1) % values, layout))
        fc = self.config.frame_check
        return calibrate_code(np.stack(frames), background, 0, leak_max=fc.leak_max,
                              pollution=fc.pollution)

    def _capture_still(self, image: np.ndarray, key: tuple[int, ...]) -> np.ndarray:
        """Show ``image`` and return a good camera frame of it (camera trouble retried)."""
        shown = self._show(image)
        for attempt in range(self.config.acquire.max_retries + 1):
            frame, why = self._capture(shown)
            if frame is not None:
                return frame.image
            assert why is not None  # _capture gives a frame or the reason there is none
            self._retry(why[0], f"calibration capture {key}", attempt, why[1])
        assert why is not None  # every attempt (max_retries >= 0) failed with a reason
        raise AcquisitionError(f"no good frame of calibration capture {key} in "
                               f"{self.config.acquire.max_retries + 1} attempts: {why[1]}")

    # ---- one event ----------------------------------------------------------------------
    def run_event(self, event: Event) -> None:
        """Show, capture, verify, write one frame; retries are bounded, logged and recorded."""
        d, p = event.depth, event.pattern
        image = self.plan.image(p, self.store.lcd_size, self.lut)
        code = None
        if self.layout is not None:
            code = p % 2**self.layout.bits
            image = stamp_frame_code(image, code, self.layout)
        max_retries = self.config.acquire.max_retries
        reasons: list[str] = []
        shown = None
        for attempt in range(max_retries + 1):
            if shown is None:
                shown = self._show(image)
            frame, peak, why = self._capture_pattern(shown, code)
            if why is None:
                break
            if why[0] in CODE_FAILURES:
                shown = None  # show the pattern again
            reasons.append(f"{why[0]}: {why[1]}")
            self._retry(why[0], f"frame (depth {d}, pattern {p})", attempt, why[1])
        else:
            raise AcquisitionError(f"frame (depth {d}, pattern {p}): no good frame in "
                                   f"{max_retries + 1} attempts: {'; '.join(reasons)}")
        # _capture_pattern gives a frame and its peak when it gives no reason
        assert frame is not None and peak is not None
        self._check_saturation(event, peak)
        target, measured = self.stage_mm
        meta = FrameMeta(stage_target_mm=target, stage_measured_mm=measured,
                         swap_index=shown.index, swap_time_s=shown.swap_time,
                         camera_timestamp_s=frame.timestamp, frame_id=frame.frame_id,
                         exposure_ms=frame.exposure_ms, retries=len(reasons))
        self.writer.submit_frame(f"frame (depth {d}, pattern {p})", d, p, frame.image, meta)
        if reasons:
            self.writer.submit(f"the retry log of frame (depth {d}, pattern {p})",
                               self.store.log_retries, d, p, reasons)

    def _show(self, image: np.ndarray) -> ShownFrame:
        return self.hw.show_settled(image, self.config.display.settled_s)

    def _capture_pattern(self, shown: ShownFrame, code: int | None
                         ) -> tuple[Frame | None, np.ndarray | None, tuple[str, str] | None]:
        """``camera.average_frames`` fresh frames of the pattern on screen, each verified
        when the check code is on: (frame, peak, None) with the frames' mean rounded to whole
        ADU (half up) as the image, the last frame's timestamp and counter, and ``peak`` the
        per-pixel maximum over the frames (for the saturation count); or (None, None, (kind,
        detail)) for the first frame that is not good (the attempt is retried whole)."""
        n = self.config.camera.average_frames
        total: np.ndarray | None = None  # the frames' sum, uint64
        peak: np.ndarray | None = None
        frame: Frame | None = None
        for _ in range(n):
            frame, why = self._capture(shown)
            if frame is not None and code is not None:
                why = self._verify(frame, code)
            if why is not None:
                return None, None, why
            assert frame is not None  # _capture gives a frame or the reason there is none
            if n == 1:
                return frame, frame.image, None
            if total is None or peak is None:  # the first frame (both are set together)
                total, peak = frame.image.astype(np.uint64), frame.image.copy()
            else:
                total += frame.image
                np.maximum(peak, frame.image, out=peak)
        assert frame is not None and total is not None  # average_frames >= 1
        mean = ((total + n // 2) // n).astype(frame.image.dtype)
        return replace(frame, image=mean), peak, None

    def _capture(self, shown: ShownFrame) -> tuple[Frame | None, tuple[str, str] | None]:
        """One capture: (frame, None) when it is fresh (taken after ``shown`` went on screen,
        with a new frame counter), else (None, (kind, detail))."""
        try:
            frame = self.hw.camera.capture(self.config.camera.timeout_s)
        except CameraTimeout as exc:
            return None, ("camera timeout", str(exc))
        except CameraError as exc:
            return None, ("camera error", str(exc))
        if self.last_frame_id is not None and frame.frame_id <= self.last_frame_id:
            return None, ("stale frame", f"frame id {frame.frame_id} after {self.last_frame_id}")
        if frame.timestamp < shown.swap_time:
            ago = shown.swap_time - frame.timestamp
            return None, ("stale frame", f"taken {ago:.3f} s before the pattern was shown")
        self.last_frame_id = frame.frame_id
        return frame, None

    def _verify(self, frame: Frame, code: int) -> tuple[str, str] | None:
        """None when the frame shows check code ``code``, else (kind, detail)."""
        # frames are verified only with the check code on, after setup_depth calibrated it
        assert self.calibration is not None
        try:
            seen = read_code(frame.image, self.calibration,
                             min_margin=self.config.frame_check.min_margin)
        except FrameCodeError as exc:
            return CODE_FAILURES[0], str(exc)
        if seen != code:
            return CODE_FAILURES[1], f"frame shows code {seen}, expected {code}"
        return None

    def _retry(self, kind: str, what: str, attempt: int, detail: str) -> None:
        self.retries[kind] += 1
        log.warning("%s: attempt %d failed, %s (%s)", what, attempt + 1, kind, detail)

    def _check_saturation(self, event: Event, image: np.ndarray) -> None:
        c = self.config
        full = 2**self.store.bit_depth - 1
        saturated = image >= c.camera.saturation_fraction * full
        if self.calibration is not None:
            saturated &= ~self.calibration.polluted
        n = int(np.count_nonzero(saturated))
        if n > c.acquire.saturation_warn_fraction * image.size:
            self.saturated_frames += 1
            log.warning("frame (depth %d, pattern %d): %d pixels saturated; lower "
                        "camera.exposure_ms", event.depth, event.pattern, n)

    # ---- teardown -----------------------------------------------------------------------
    def teardown(self, failed: bool) -> list[str]:
        """Blank the display and, after a failure, stop the stage; return the cleanup errors
        (logged, never raised: the caller decides)."""
        errors = []
        steps: list[tuple[str, Callable[[], object]]] = [
            ("blank the display", lambda: self.hw.display.show(
                np.zeros(self.store.lcd_size[::-1], np.uint8)))]
        if failed:
            steps.append(("stop the stage", self.hw.stage.stop))
        for name, step in steps:
            try:
                step()
            except Exception as exc:  # noqa: BLE001 - collected, logged and reported to the caller
                log.error("teardown: could not %s: %s", name, exc)
                errors.append(f"teardown: could not {name}: {type(exc).__name__}: {exc}")
        return errors


def acquire(
    config: StationConfig,
    out: str | Path,
    *,
    resume: bool = False,
    progress: bool = True,
    hw: Hardware | None = None,
    before_event: Callable[[Event, Hardware], None] | None = None,
    force: bool = False,
    writer_queue: int = WRITER_QUEUE_FRAMES,
) -> dict:
    """Run (or with ``resume`` finish) the acquisition of ``config`` into the run store ``out``.

    hw : opened hardware to use (left open); by default the config's backend is opened and
        closed here. before_event : called before each event (e.g. to trigger a fake's fault).
    force : accepted with ``resume`` (a lock left by a process that is gone is free anyway:
        :mod:`sim.storage.lock`).
    writer_queue : frames captured ahead of the store writer's thread (0: write serially).
    Returns a JSON-able summary. Raises :class:`AcquisitionError` (or the device's error)
    when the run cannot start or go on; frames already done stay done. A store locked by
    another writer is refused (:class:`sim.storage.lock.StoreLockedError`).
    """
    out = Path(out)
    lut = load_lut(config.display.lut_path) if config.display.lut_path else None
    record = run_record(config, lut)
    store = None
    with contextlib.ExitStack() as locks:
        if resume:
            if out.is_dir():
                locks.enter_context(StoreLock(out, force=force))
            store = _open_for_resume(out, record)
        elif out.exists():
            raise AcquisitionError(f"{out}: already exists; pass --resume to finish that run, "
                                   "or choose a new --out")
        return _acquire(config, out, store, record, lut, locks, progress, hw, before_event,
                        writer_queue, resume)


def _acquire(config: StationConfig, out: Path, store: RunStore | None, record: dict,
             lut: np.ndarray | None, locks: contextlib.ExitStack, progress: bool,
             hw: Hardware | None, before_event: Callable[[Event, Hardware], None] | None,
             writer_queue: int, resume: bool) -> dict:
    t0 = time.perf_counter()
    with _hardware(config, hw) as devices:
        created = store is None
        store = _check_and_create(config, devices, out, store, record, lut)
        if created:
            locks.enter_context(StoreLock(out))
        writer = FrameWriter(store, writer_queue)
        engine = Acquisition(config, devices, store, lut, writer)
        todo = plan_events(store.done())
        status = "failed"
        error: BaseException | None = None
        try:
            engine.setup()
            _run_events(engine, todo, progress, before_event)
            writer.close()
            status = "complete"
        except KeyboardInterrupt as exc:
            status, error = "interrupted", exc
            raise
        except BaseException as exc:
            error = exc
            raise
        finally:
            try:
                writer.close()  # the frames captured so far are written (a no-op when done)
            except AcquisitionError as exc:
                if error is None:
                    raise
                error.add_note(str(exc))
            cleanup = engine.teardown(failed=error is not None)
            try:
                store.set_status(status, end_time=_now())
            except OSError as exc:
                cleanup.append(f"teardown: could not record the run status: {exc}")
            if cleanup and error is not None:
                for note in cleanup:
                    error.add_note(note)
            elif cleanup:
                raise AcquisitionError("; ".join(cleanup))
    seconds = time.perf_counter() - t0
    return {
        "run": str(out), "status": status, "resumed": resume, "frames_written": len(todo),
        "frames_recaptured": store.recaptured,
        "frames_total": int(store.done().size), "depths_mm": store.depths_mm,
        "patterns_per_depth": store.n_patterns, "retries": dict(engine.retries),
        "saturated_frames": engine.saturated_frames,
        "code_mask_fraction": {str(store.depths_mm[d]): f for d, f in engine.mask_fraction.items()},
        "seconds": round(seconds, 3), "frames_per_second": round(len(todo) / max(seconds, 1e-9), 2),
    }


def _run_events(engine: Acquisition, todo: Sequence[Event], progress: bool,
                before_event: Callable[[Event, Hardware], None] | None) -> None:
    n = engine.store.n_patterns
    depth = None
    with tqdm(total=len(todo), desc="acquire", unit="frame", disable=not progress) as bar:
        for event in todo:
            if event.depth != depth:
                depth = event.depth
                bar.set_postfix_str(f"depth {engine.store.depths_mm[depth]:g} mm: calibrating",
                                    refresh=False)
                engine.setup_depth(depth, event.pattern)
            bar.set_postfix_str(f"depth {engine.store.depths_mm[depth]:g} mm "
                                f"({depth + 1}/{engine.store.n_depths}), frame "
                                f"{event.pattern + 1}/{n}", refresh=False)
            if before_event is not None:
                before_event(event, engine.hw)
            engine.run_event(event)
            bar.update(1)


def _open_for_resume(out: Path, record: dict) -> RunStore:
    try:
        store = RunStore.open(out, mode="r+")
    except RunStoreError as exc:
        raise AcquisitionError(f"cannot resume: {exc}") from exc
    diffs = config_differences(store.config, record)
    if diffs:
        raise AcquisitionError(f"{out}: refusing to resume: the config differs from the run's: "
                               + "; ".join(diffs))
    damaged = store.damaged_frames()  # every done frame read back against its checksums
    if damaged:
        which = ", ".join(f"(depth {d}, pattern {p})" for d, p, _ in damaged[:20])
        more = f" and {len(damaged) - 20} more" if len(damaged) > 20 else ""
        log.warning("%s: %d done frame(s) are damaged and will be recaptured: %s%s "
                    "(first: %s)", out, len(damaged), which, more, damaged[0][2])
        store.mark_not_done([(d, p) for d, p, _ in damaged])
    store.recaptured = [[d, p] for d, p, _ in damaged]
    return store


def _check_and_create(config: StationConfig, hw: Hardware, out: Path, store: RunStore | None,
                      record: dict, lut: np.ndarray | None) -> RunStore:
    """Check the config against the opened devices (before anything moves); create the store."""
    lcd_w, lcd_h = hw.display.size
    lcd_size = (lcd_w, lcd_h)
    plan = pattern_plan(config, lcd_size)
    if config.frame_check.enabled:
        try:
            frame_code_rect(config.frame_check.layout(lcd_size), lcd_size)
        except DeviceSettingError as exc:
            raise AcquisitionError(f"frame_check: {exc}") from exc
    lo, hi = hw.stage.limits_mm
    outside = [z for z in config.depths_mm if not lo <= z <= hi]
    if outside:
        raise AcquisitionError(f"depths_mm {outside} outside the stage's travel ({lo}, {hi}) mm")
    if store is None:
        layout = config.frame_check.layout(lcd_size) if config.frame_check.enabled else None
        frame_check = None if layout is None else {
            "rect_xywh": list(frame_code_rect(layout, lcd_size)), "bits": layout.bits,
            "block_px": layout.block_px, "columns": layout.grid[1]}
        try:  # atomic: a run killed here leaves no store, or one --resume takes up
            return RunStore.create(
                out, config=record, plan=plan, depths_mm=config.depths_mm,
                camera_size=hw.camera.size, bit_depth=hw.camera.bit_depth, lcd_size=lcd_size,
                lcd_pitch_mm=config.display.pitch_mm, display_lut=lut, start_time=_now(),
                attrs={"frame_check": frame_check, "status": "running"})
        except RunStoreError as exc:
            raise AcquisitionError(f"cannot create the run store: {exc}") from exc
    try:
        store.require_same_config(record, plan)
    except RunStoreError as exc:
        raise AcquisitionError(f"refusing to resume: {exc}") from exc
    found = {"camera_size": tuple(hw.camera.size), "bit_depth": hw.camera.bit_depth,
             "lcd_size": lcd_size}
    stored = {"camera_size": store.camera_size, "bit_depth": store.bit_depth,
              "lcd_size": store.lcd_size}
    if found != stored:
        raise AcquisitionError(f"{out}: refusing to resume: devices {found} differ from the "
                               f"run's {stored}")
    store.set_status("running")
    return store


@contextlib.contextmanager
def _hardware(config: StationConfig, hw: Hardware | None) -> Iterator[Hardware]:
    """The given hardware, or the config's, opened here and closed so that an error while
    closing is attached to (never replaces) an error of the run."""
    if hw is not None:
        yield hw
        return
    cm = open_hardware(config)
    opened = cm.__enter__()
    try:
        yield opened
    except BaseException as exc:
        try:
            cm.__exit__(type(exc), exc, exc.__traceback__)
        except Exception as close_exc:  # noqa: BLE001 - attached to the original error
            log.error("teardown: closing the devices failed: %s", close_exc)
            exc.add_note(f"teardown: closing the devices failed: {close_exc!r}")
        raise
    cm.__exit__(None, None, None)


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat()
