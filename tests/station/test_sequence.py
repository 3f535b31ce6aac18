"""station.sequence: what a failed step leaves in the summary and the log."""

from __future__ import annotations

import errno
import json
import os

import pytest

from station.experiment.run import ExperimentConfig, build_rig, station_config
from station.sequence import Sequence


def test_a_step_on_a_full_disk_records_one_line_naming_the_file_and_what_to_do(tmp_path,
                                                                               monkeypatch):
    cfg = ExperimentConfig()
    config = station_config(cfg, build_rig(cfg), 0)
    where = tmp_path / "seq" / "check" / "contact.png"

    def full(self):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(where))

    monkeypatch.setattr(Sequence, "_check", full)
    with pytest.raises(OSError):
        Sequence(config, tmp_path / "seq", progress=False).run()
    summary = json.loads((tmp_path / "seq" / "summary.json").read_text())
    assert summary["status"] == "failed at check"
    error = summary["steps"]["check"]["error"]
    assert error == f"{where}: no space left on device; free some space, then run the " \
                    "command again (with --resume where it has one)"
    assert f"check: failed: {error}" in (tmp_path / "seq" / "run.log").read_text()


def test_a_durable_file_appears_whole_or_not_at_all(tmp_path):
    from station.sequence import durable_file

    path = tmp_path / "a.bin"
    with pytest.raises(RuntimeError):
        with durable_file(path, "wb") as f:
            f.write(b"half")
            raise RuntimeError("killed mid-write")
    assert list(tmp_path.iterdir()) == []  # neither the file nor its temporary
    with durable_file(path, "wb") as f:
        f.write(b"whole")
    assert path.read_bytes() == b"whole" and list(tmp_path.iterdir()) == [path]


def test_a_changed_lens_setting_derives_the_lens_again_and_nothing_else(tmp_path,
                                                                         monkeypatch):
    """Only the lens step's [sequence] settings may change on a finished folder: the lens is
    derived again (with the new settings), no earlier step runs; any other change is refused."""
    from station.errors import UsageError

    cfg = ExperimentConfig()
    config = station_config(cfg, build_rig(cfg), 0)
    ran = []

    def fake(step):
        def run(self):
            ran.append((step, self.config.sequence.lens_samples))
            for p in self.outputs(step):
                p.mkdir() if p.suffix == "" else p.write_text(step)
            return {}
        return run

    for step in ("check", "acquire", "reconstruct", "lens"):
        monkeypatch.setattr(Sequence, f"_{step}", fake(step))
    out = tmp_path / "seq"
    Sequence(config, out, progress=False).run()
    assert [s for s, _ in ran] == ["check", "acquire", "reconstruct", "lens"]
    ran.clear()
    Sequence(config, out, progress=False).run()
    assert ran == []  # the same config: everything done
    k = config.sequence.lens_samples * 2
    more = config.model_copy(update={"sequence": config.sequence.model_copy(
        update={"lens_samples": k, "lens_settings": {"aperture_cells": 64}})})
    Sequence(more, out, progress=False).run()
    assert ran == [("lens", k)]
    assert f"lens_samples = {k}" in (out / "config.toml").read_text()
    log = (out / "run.log").read_text()
    assert "lens settings changed (lens_samples, lens_settings): the lens is derived again" in log
    ran.clear()
    Sequence(more, out, progress=False).run()
    assert ran == []
    other = more.model_copy(update={"depths_mm": [50.0, 90.0, 130.0]})
    with pytest.raises(UsageError, match="another config"):
        Sequence(other, out, progress=False)
    assert f"lens_samples = {k}" in (out / "config.toml").read_text()


def test_a_second_writer_of_a_sequence_folder_is_refused_naming_the_holder(tmp_path):
    """Two sequences on one folder (a script started twice, or a worker process that
    re-ran its parent's script) would interleave their summaries: the second is refused."""
    from sim.storage.lock import StoreLock, StoreLockedError

    cfg = ExperimentConfig()
    config = station_config(cfg, build_rig(cfg), 0)
    out = tmp_path / "seq"
    out.mkdir()
    with StoreLock(out):
        with pytest.raises(StoreLockedError, match=f"locked by another writer .*PID {os.getpid()}"):
            Sequence(config, out, progress=False).run()
    assert sorted(p.name for p in out.iterdir()) == []  # nothing written under another's lock


def test_a_renamed_output_is_recorded_under_its_final_path(tmp_path):
    """A step written under a temporary name and renamed into place (the LTC store) records
    the final path, never the temporary one."""
    from station.sequence import _atomic

    final = tmp_path / "ltc.zarr"

    def write(tmp):
        tmp.mkdir()
        return {"run": str(tmp_path / "run.zarr"), "out": str(tmp), "pixels": 12}

    got = _atomic(final, write)
    assert got == {"run": str(tmp_path / "run.zarr"), "out": str(final), "pixels": 12}
    assert final.is_dir() and not (tmp_path / "ltc.partial.zarr").exists()


def test_the_summary_round_trips_through_its_json(tmp_path, monkeypatch):
    """``summary.json`` is ``SequenceSummary.to_json()``: every step's record, the status,
    read back equal."""
    from station.sequence import SequenceSummary

    cfg = ExperimentConfig()
    config = station_config(cfg, build_rig(cfg), 0)

    def fake(step):
        def run(self):
            for p in self.outputs(step):
                p.mkdir() if p.suffix == "" else p.write_text(step)
            return {"step": step}
        return run

    for step in ("check", "acquire", "reconstruct", "lens"):
        monkeypatch.setattr(Sequence, f"_{step}", fake(step))
    out = tmp_path / "seq"
    summary = Sequence(config, out, progress=False).run()
    data = json.loads((out / "summary.json").read_text())
    assert data == summary.to_json()
    assert SequenceSummary.from_json(data) == summary
    assert summary.status == "complete" and summary.steps["lens"].result == {"step": "lens"}
    assert data["steps"]["align"] == {"status": "skipped", "reason": "not asked for by [sequence]"}
