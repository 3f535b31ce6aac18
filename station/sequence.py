"""The unattended station sequence (``ltc run``): check, gamma (if asked), alignment report,
acquisition at every depth, LTC reconstruction and lens derivation, one step after another
into one folder, resumable at any step.

The folder ``out`` holds ``config.toml`` (the config the sequence was started with),
``run.log`` (every step's start, end and outcome, appended across re-runs), ``summary.json``
(rewritten atomically after every step), and each step's output: ``check/``, ``lut.npy``,
``align.json``, ``run.zarr``, ``ltc.zarr``, ``lens.npz`` and ``figures/``.

Re-running on the same folder skips the steps recorded as done whose outputs exist and
continues with the first one that is not: the acquisition resumes frame by frame
(``acquire(resume=True)``), the reconstruction and the lens are rebuilt whole (each is
written under a temporary name and renamed into place when complete, so a killed step
leaves no half output under the final name). One sequence writes a folder at a time
(``writer.lock``, as the stores'). A different config refuses to continue, except
one that differs only in the lens step's settings (``[sequence]`` ``lens_samples``,
``lens_grid_step``, ``lens_pixel_samples``, ``lens_settings``): then the lens is derived again
from the LTC store, and nothing before it is redone (``config.toml`` takes the new config).
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import tomli_w

from sim.storage.durable import durable_file, publish, write_json
from sim.storage.lock import LOCK_NAME, StoreLock
from station.acquisition.config import StationConfig, load_config, parse_config
from station.errors import StationError, UsageError, describe_os_error

STEPS = ("check", "gamma", "align", "acquire", "reconstruct", "lens")
LENS_FIELDS = ("lens_samples", "lens_grid_step", "lens_pixel_samples", "lens_settings")
log = logging.getLogger("station.sequence")


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()


@dataclass
class StepRecord:
    """One step's outcome in ``summary.json``: ``status`` ("running", "done", "skipped",
    "failed", "interrupted", "outdated"), UTC times (ISO 8601), ``seconds`` (wall clock),
    the step's ``result`` (its JSON-able summary), ``error`` and ``reason`` lines; None:
    not recorded (left out of the JSON)."""

    status: str
    started: str | None = None
    ended: str | None = None
    seconds: float | None = None
    result: dict[str, Any] | None = None
    error: str | None = None
    reason: str | None = None

    def to_json(self) -> dict[str, Any]:
        """The recorded fields."""
        return {k: v for k, v in asdict(self).items() if v is not None}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> StepRecord:
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


@dataclass
class SequenceSummary:
    """The sequence folder's ``summary.json``: the config file, every step's record (in
    ``STEPS`` order as run), the overall ``status`` ("complete", "running STEP", "failed at
    STEP", "interrupted at STEP") and when it was last ``updated`` (UTC, ISO 8601)."""

    config: str
    steps: dict[str, StepRecord] = field(default_factory=dict)
    status: str | None = None
    updated: str | None = None

    def to_json(self) -> dict[str, Any]:
        """The JSON object of ``summary.json`` (docs/formats.md)."""
        out: dict[str, Any] = {"config": self.config,
                               "steps": {k: v.to_json() for k, v in self.steps.items()}}
        if self.updated is not None:
            out["updated"] = self.updated
        if self.status is not None:
            out["status"] = self.status
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> SequenceSummary:
        return cls(config=str(data["config"]),
                   steps={k: StepRecord.from_json(v) for k, v in data.get("steps", {}).items()},
                   status=data.get("status"), updated=data.get("updated"))


class Sequence:
    """One sequence folder: its config, its summary, and the steps still to do."""

    def __init__(self, config: StationConfig | str | Path, out: str | Path, *,
                 progress: bool = True, force: bool = False):
        self.out = Path(out)
        self.progress = progress
        self.force = force
        self.config_path = self.out / "config.toml"
        self.summary_path = self.out / "summary.json"
        text = _config_text(config)
        self.notes: list[str] = []
        changed: list[str] | None = []
        if self.config_path.exists():
            before = self.config_path.read_text(encoding="utf-8")
            changed = _lens_settings_changed(before, text) if before != text else []
            if changed is None:
                raise UsageError(f"{self.out} holds a sequence started with another config "
                                 f"({self.config_path}); use a new --out, or the same config "
                                 "(only the lens step's [sequence] lens_* settings may "
                                 "change: the lens is then derived again)")
        elif self.out.exists() and any(p.name != LOCK_NAME for p in self.out.iterdir()):
            raise UsageError(f"--out {self.out} exists and is not a sequence folder; choose a "
                             "new folder")
        self.out.mkdir(parents=True, exist_ok=True)
        self.config = parse_config(text, str(self.config_path))
        self._text, self._changed = text, changed
        self.summary = self._read_summary()

    def _read_summary(self) -> SequenceSummary:
        if not self.summary_path.exists():
            return SequenceSummary(config=str(self.config_path))
        try:
            return SequenceSummary.from_json(json.loads(self.summary_path.read_text()))
        except (ValueError, KeyError, TypeError) as exc:
            raise StationError(f"{self.summary_path}: unreadable ({exc}); delete it to run "
                               "every step again") from exc

    def _take_config(self) -> None:
        """Under the folder's lock: the summary as it is now; the config kept beside the
        outputs; with changed lens settings, the lens marked outdated first, then the new
        config written (a kill between the two leaves the same change to find again)."""
        self.summary = self._read_summary()
        if self._changed:  # only ever found against an existing config.toml
            note = (f"lens settings changed ({', '.join(self._changed)}): the lens is derived "
                    "again from the LTC store")
            self._record("lens", status="outdated", reason=note)
            self.notes.append(note)
        if self._changed or not self.config_path.exists():
            with durable_file(self.config_path) as f:
                f.write(self._text)

    def outputs(self, step: str) -> list[Path]:
        """The files a step leaves behind when it is done."""
        o = self.out
        return {"check": [o / "check"], "gamma": [o / "lut.npy"], "align": [o / "align.json"],
                "acquire": [o / "run.zarr"], "reconstruct": [o / "ltc.zarr"],
                "lens": [o / "lens.npz"]}[step]

    def done(self, step: str) -> bool:
        """Whether ``step`` is recorded as done and its outputs exist."""
        rec = self.summary.steps.get(step)
        return (rec is not None and rec.status == "done"
                and all(p.exists() for p in self.outputs(step)))

    def wanted(self, step: str) -> bool:
        """Whether the config asks for ``step``."""
        s = self.config.sequence
        return {"gamma": s.gamma, "align": s.align}.get(step, True)

    def _record(self, step: str, status: str, **values: Any) -> None:
        rec = self.summary.steps.setdefault(step, StepRecord(status=status))
        rec.status = status
        for name, value in values.items():
            setattr(rec, name, value)
        self.summary.updated = _now()
        self._write_summary()

    def _write_summary(self) -> None:
        write_json(self.summary_path, self.summary.to_json())

    def run(self) -> SequenceSummary:
        """Run every step not yet done; returns the summary (``status`` "complete" or the
        step that failed). Raises the failing step's error after recording it. One sequence
        per folder at a time: a second is refused, naming the holder (``writer.lock``; a
        killed run's lock is free, :mod:`sim.storage.lock`)."""
        with StoreLock(self.out, force=self.force):
            self._take_config()
            return self._run_steps()

    def _run_steps(self) -> SequenceSummary:
        handler = logging.FileHandler(self.out / "run.log", encoding="utf-8")
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s %(message)s"))
        log.addHandler(handler)
        log.setLevel(logging.INFO)
        # every device exchange (stage commands and replies, swaps, captures) at DEBUG
        devices = logging.getLogger("drivers")
        devices_level = devices.level
        devices.addHandler(handler)
        devices.setLevel(logging.DEBUG)
        try:
            for note in self.notes:
                log.info("%s", note)
            log.info("sequence %s: start (steps done: %s)", self.out,
                     [s for s in STEPS if self.done(s)] or "none")
            for step in STEPS:
                if not self.wanted(step):
                    self._record(step, status="skipped", reason="not asked for by [sequence]")
                    continue
                if self.done(step):
                    log.info("%s: done in an earlier run, skipped", step)
                    continue
                self._step(step)
            self.summary.status = "complete"
            self._write_summary()
            log.info("sequence %s: complete", self.out)
            return self.summary
        finally:
            log.removeHandler(handler)
            devices.removeHandler(handler)
            devices.setLevel(devices_level)
            handler.close()

    def _step(self, step: str) -> None:
        log.info("%s: start", step)
        self._record(step, status="running", started=_now())
        self.summary.status = f"running {step}"
        t0 = time.perf_counter()
        try:
            result = getattr(self, f"_{step}")()
        except BaseException as exc:
            status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
            self.summary.status = f"{status} at {step}"
            # an OSError as the one line the CLI prints: the path, what went wrong, what to do
            error = (describe_os_error(exc) if isinstance(exc, OSError)
                     else str(exc) or type(exc).__name__)
            self._record(step, status=status, error=error,
                         seconds=round(time.perf_counter() - t0, 3))
            log.error("%s: %s: %s", step, status, error)
            raise
        self._record(step, status="done", ended=_now(),
                     seconds=round(time.perf_counter() - t0, 3), result=result)
        log.info("%s: done in %.1f s", step, time.perf_counter() - t0)

    def _check(self) -> dict:
        from station.acquisition.check import run_check

        report = run_check(self.config, self.out / "check")
        if not report["ok"]:
            failed = [s["name"] + (f" ({s['error']})" if s["error"] else "")
                      for s in report["steps"] if not s["ok"]]
            raise StationError(f"bench check failed: {'; '.join(failed) or 'no steps ran'}; "
                               f"see {self.out / 'check'}")
        return {"ok": True, "contact_sheet": report.get("contact_sheet")}

    def _gamma(self) -> dict:
        from station.acquisition.gamma import measure_lut, save_lut

        result = measure_lut(self.config)
        save_lut(self.out / "lut.npy", result["lut"])
        return {"gamma_fit": result["gamma_fit"], "lut": str(self.out / "lut.npy")}

    def _run_config(self) -> StationConfig:
        """The config the acquisition runs with: the sequence's own LUT when it measured one."""
        if self.config.sequence.gamma:
            display = self.config.display.model_copy(
                update={"lut_path": str(self.out / "lut.npy")})
            return self.config.model_copy(update={"display": display})
        return self.config

    def _align(self) -> dict:
        from station.acquisition.align import run_align

        report = run_align(self._run_config())
        write_json(self.out / "align.json", report)
        return {"report": str(self.out / "align.json"),
                **{k: report[k] for k in ("tilt_deg",) if k in report}}

    def _acquire(self) -> dict:
        from station.acquisition.acquire import acquire

        run = self.out / "run.zarr"
        return acquire(self._run_config(), run, resume=run.exists(), progress=self.progress,
                       force=self.force)

    def _reconstruct(self) -> dict:
        from station.ltc.tiles import reconstruct

        return _atomic(self.out / "ltc.zarr", lambda tmp: reconstruct(
            self.out / "run.zarr", tmp, progress=self.progress))

    def _lens(self) -> dict:
        from station.api import derive_lens, lens_config

        s = self.config.sequence
        given = {"samples": s.lens_samples, "grid_step": s.lens_grid_step,
                 "pixel_samples": s.lens_pixel_samples}
        config = lens_config(**{k: v for k, v in given.items() if v is not None},
                             **s.lens_settings)
        figures = self.out / "figures"
        _remove(figures)
        # written as the nodes are derived (temporary name, then renamed into place)
        result = derive_lens(self.out / "ltc.zarr", config, figures=figures,
                             progress=self.progress, out=self.out / "lens.npz")
        summary = result.summary().to_json()
        return {k: summary[k] for k in ("optical_centre_mm", "focus_distance_mm",
                                        "pixels_usable", "pixels", "notes")}


def _atomic(final: Path, write: Callable[[Path], dict | None], suffix: str = "") -> dict:
    """Write an output under a temporary name, then put it in place of any old one
    (:func:`sim.storage.durable.publish`); the result names ``final`` wherever the writer
    named the temporary path."""
    tmp = final.with_name(final.stem + ".partial" + (suffix or final.suffix))
    _remove(tmp)
    result = write(tmp)
    publish(tmp, final, replace=True)
    if not isinstance(result, dict):
        return {"out": str(final)}
    return {k: str(final) if isinstance(v, str) and v == str(tmp) else v
            for k, v in result.items()}


def _lens_settings_changed(before: str, now: str) -> list[str] | None:
    """The ``[sequence]`` lens fields in which two config texts differ, or None when they
    differ anywhere else too (or the earlier text no longer parses)."""
    try:
        a, b = (parse_config(t, "config.toml").model_dump(mode="json") for t in (before, now))
    except (StationError, ValueError):
        return None
    changed = [f for f in LENS_FIELDS if a["sequence"].get(f) != b["sequence"].get(f)]
    for d in (a, b):
        for f in LENS_FIELDS:
            d["sequence"].pop(f, None)
    return changed if a == b else None


def _config_text(config: StationConfig | str | Path) -> str:
    """The config as TOML text to keep beside the outputs (a file's own text when given)."""
    if isinstance(config, (str, Path)):
        path = Path(config)
        load_config(path)  # validate first: errors name the file and field
        return path.read_text(encoding="utf-8")
    return tomli_w.dumps(config.model_dump(mode="json", exclude_none=True))


def run_sequence(config: StationConfig | str | Path, out: str | Path, *,
                 progress: bool = True, force: bool = False) -> SequenceSummary:
    """Run (or continue) the whole station sequence into the folder ``out``; see the module
    docstring. ``force`` takes over the run store's writer lock left by a killed run (never a
    live writer's). Returns the summary (``SequenceSummary``; ``out/summary.json``)."""
    return Sequence(config, out, progress=progress, force=force).run()
