"""``ltc reconstruct`` never mixes two runs and never shares its store: ``--resume`` compares
the run store's identity (not its path string), and the LTC store's writer lock refuses a
second writer (``--force`` or ``--resume``) with one line naming the holder."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from sim.storage.lock import StoreLock, StoreLockedError
from station.acquisition.run_store import RunStore
from station.cli import main
from station.ltc import tiles
from station.ltc.store import open_ltc_store
from tests.support.configs import small_fake_config_text


def one_depth_text() -> str:
    return small_fake_config_text()


@pytest.fixture
def run(tmp_path, capsys):
    cfg = tmp_path / "one.toml"
    cfg.write_text(one_depth_text())
    assert main(["acquire", str(cfg), "--out", str(tmp_path / "run.zarr"), "--quiet"]) == 0
    capsys.readouterr()
    return cfg, tmp_path / "run.zarr"


def reconstruct(run_path, out, *extra) -> list[str]:
    return ["reconstruct", str(run_path), "--out", str(out), "--workers", "1", "--quiet",
            *extra]


def undo_last_tile(out):
    """Leave the store as a reconstruction killed before its last tile was recorded."""
    g = open_ltc_store(out, mode="r+")
    done = g["tile_done"][...]
    done[0, -1, -1] = False
    g["tile_done"][...] = done
    flags = list(g.attrs["depths_complete"])
    flags[0] = False
    g.attrs["depths_complete"] = flags


def test_resume_accepts_the_same_run_by_another_path_and_refuses_a_new_run(run, tmp_path,
                                                                           capsys):
    cfg, run_path = run
    out = tmp_path / "ltc.zarr"
    os.chdir(tmp_path)
    assert main(reconstruct("run.zarr", out)) == 0  # a relative path
    undo_last_tile(out)
    assert main(reconstruct(run_path.resolve(), out, "--resume")) == 0, capsys.readouterr().err
    assert open_ltc_store(out).attrs["run_id"] == RunStore.open(run_path).identity()
    undo_last_tile(out)
    old_id = RunStore.open(run_path).identity()
    assert main(["acquire", str(cfg), "--out", str(run_path), "--force", "--quiet"]) == 0
    new_id = RunStore.open(run_path).identity()
    capsys.readouterr()
    assert main(reconstruct(run_path, out, "--resume")) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and old_id in err[0] and new_id in err[0] and old_id != new_id, err
    assert "cannot resume it from another run" in err[0]
    assert not open_ltc_store(out)["tile_done"][0, -1, -1]  # nothing of the new run mixed in


HOLD = ("import sys, time; from sim.storage.lock import StoreLock\n"
        "with StoreLock(sys.argv[1]):\n    print('held', flush=True); time.sleep(60)\n")


def test_a_second_writer_is_refused_naming_the_holder(run, tmp_path, capsys):
    _, run_path = run
    out = tmp_path / "ltc.zarr"
    assert main(reconstruct(run_path, out)) == 0
    undo_last_tile(out)
    files = sorted(p.relative_to(out) for p in out.rglob("*"))
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        capsys.readouterr()
        for extra in (("--force",), ("--resume",)):
            assert main(reconstruct(run_path, out, *extra)) == 1
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and f"{out}: locked by another writer" in err[0], err
            assert f"PID {holder.pid}" in err[0] and "command `" in err[0], err
    finally:
        holder.kill()
        holder.wait()
    left = sorted(p.relative_to(out) for p in out.rglob("*") if p.name != "writer.lock")
    assert left == files  # nothing deleted (the killed holder's lock file stays, unheld)
    assert main(reconstruct(run_path, out, "--resume")) == 0  # the holder is gone


def test_the_reconstruction_holds_the_lock_while_it_computes(run, tmp_path, monkeypatch):
    _, run_path = run
    out = tmp_path / "ltc.zarr"
    seen = []
    real = tiles.run_ordered

    def run_ordered(*args, **kwargs):
        with pytest.raises(StoreLockedError, match=f"PID {os.getpid()}") as exc:
            StoreLock(out).acquire()
        seen.append(str(exc.value))
        return real(*args, **kwargs)
    monkeypatch.setattr(tiles, "run_ordered", run_ordered)
    assert main(reconstruct(run_path, out)) == 0
    assert len(seen) == 1 and "reconstruct" in seen[0]
    assert not (out / "writer.lock").exists()
