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
