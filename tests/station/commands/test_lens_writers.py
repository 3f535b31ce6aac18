"""Two ``ltc lens`` runs to one ``--out``: the second is refused while the first holds the
output's lock, and an output that appears meanwhile (a writer that took no lock) is never
replaced at the final rename."""

from __future__ import annotations

import subprocess
import sys

import pytest

from fakes.bench import BenchConfig, FakeBench
from sim.optics import measured_lens
from station.cli import main
from tests.support.ltc_stores import write_true_ltc_store

HOLD = ("import sys, time; from sim.storage.lock import StoreLock\n"
        "with StoreLock.for_file(sys.argv[1]):\n    print('held', flush=True); time.sleep(60)\n")


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    bench = FakeBench(BenchConfig.small(lcd_size=(120, 96), lcd_distance_at_zero_mm=100.0,
                                        pupil_samples=150, subpixels=1))
    return write_true_ltc_store(tmp_path_factory.mktemp("lens") / "ltc.zarr", bench,
                                [0.0, 30.0, 60.0, 250.0, 290.0], period=24)


def lens(store, out) -> list[str]:
    return ["lens", str(store), "--out", str(out), "--samples", "8", "--grid-step", "8",
            "--workers", "1", "--quiet"]


@pytest.mark.slow
def test_a_second_lens_writer_is_refused_naming_the_first(store, tmp_path, capsys):
    out = tmp_path / "lens.npz"
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert main(lens(store, out)) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{out}: locked by another writer" in err[0], err
        assert f"PID {holder.pid}" in err[0] and "command `" in err[0], err
    finally:
        holder.kill()
        holder.wait()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".lens.npz.lock"]  # nothing written
    assert main(lens(store, out)) == 0  # the holder is gone: its lock file is free
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lens.npz"]


@pytest.mark.slow
def test_an_output_that_appears_meanwhile_is_not_replaced(store, tmp_path, capsys,
                                                          monkeypatch):
    out = tmp_path / "lens.npz"
    real = measured_lens.LensFileWriter.write_nodes

    def write_nodes(self, *args):
        if not out.exists():
            out.write_bytes(b"another writer's lens")
        return real(self, *args)
    monkeypatch.setattr(measured_lens.LensFileWriter, "write_nodes", write_nodes)
    assert main(lens(store, out)) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{out}: appeared while this output was written" in err[0], err
    assert out.read_bytes() == b"another writer's lens"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lens.npz"]  # no partial left
