"""At small size: the synthetic bench's true centroids are recovered;
a local Dask cluster, worker processes and a single process give the same LTC store bit for
bit; a SIGKILLed reconstruction finished with ``--resume`` equals an uninterrupted one; the
lens derivation refuses an LTC store with an incomplete depth."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from fakes.synthetic import SyntheticBench, parse_synthetic_settings
from station.api import acquire, load_config
from station.cli import main as cli_main
from station.lens.centroids import window_stats
from station.ltc.store import open_ltc_store
from station.ltc.tiles import reconstruct

CONFIG = """
backend = "fake"
depths_mm = [60.0, 160.0]
[stage]
travel_mm = [0.0, 300.0]
[display]
latency_frames = 0
[camera]
exposure_ms = 20.0
matrix = [[640.0, 0.0, 23.5], [0.0, 640.0, 15.5], [0.0, 0.0, 1.0]]
[patterns]
period = 12
steps = 4
[frame_check]
enabled = false
[fake]
model = "synthetic"
seed = 1
[fake.synthetic]
lcd_size = [96, 64]
camera_size = [48, 32]
pixel_pitch_um = 25.0
focal_length_mm = 16.0
focus_distance_mm = 250.0
lcd_distance_at_zero_mm = 150.0
sigma_focus_px = 1.2
radial_stretch = 0.2
"""
ARRAYS = ("ltc", "origin", "gain", "noise", "lcd_xy", "tile_done", "tile_stats")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("full_scale")
    (root / "syn.toml").write_text(CONFIG)
    acquire(load_config(root / "syn.toml"), root / "run.zarr", progress=False)
    return root


def same_store(a: Path, b: Path) -> None:
    ga, gb = open_ltc_store(a), open_ltc_store(b)
    for name in ARRAYS:
        x, y = np.asarray(ga[name]), np.asarray(gb[name])
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), f"{name} differs"
    assert ga.attrs["depths_complete"] == gb.attrs["depths_complete"] == [True, True]


@pytest.fixture(scope="module")
def serial(run):
    reconstruct(run / "run.zarr", run / "serial.zarr", tile_px=16, progress=False, workers=1)
    return run / "serial.zarr"


@pytest.mark.slow
def test_synthetic_bench_centroids_are_recovered(run, serial):
    cfg = load_config(run / "syn.toml")
    bench = SyntheticBench(parse_synthetic_settings(cfg.fake).synthetic)
    g = open_ltc_store(serial)
    errs = []
    for i, z in enumerate(cfg.depths_mm):
        truth, _ = bench.true_moments(z)
        ltc = np.asarray(g["ltc"][i], dtype=np.float64).reshape(-1, 12, 12)
        st = window_stats(ltc, np.asarray(g["noise"][i], dtype=np.float64).ravel())
        got = st.centroid + np.asarray(g["origin"][i]).reshape(-1, 2)
        errs.append(np.hypot(*(got - truth.reshape(-1, 2)).T))
    err = np.concatenate(errs)
    p50, p95 = np.percentile(err, [50, 95])
    print(f"\nsynthetic bench: centroid error vs truth p50 {p50:.4f}, p95 {p95:.4f} LCD px")
    assert np.isfinite(err).all()
    assert p50 < 0.1 and p95 < 0.2  # noise-limited: noise-free it is 0.005 / 0.014 px


@pytest.mark.slow
def test_dask_and_worker_processes_equal_single_process(run, serial):
    reconstruct(run / "run.zarr", run / "procs.zarr", tile_px=16, progress=False, workers=2)
    same_store(serial, run / "procs.zarr")
    reconstruct(run / "run.zarr", run / "dask.zarr", tile_px=16, progress=False, workers=2,
                dask=True)
    same_store(serial, run / "dask.zarr")


def test_sigkilled_reconstruction_resumes_bit_identically(run, serial):
    out = run / "killed.zarr"
    cmd = [sys.executable, "-c", "import sys; from station.cli import main; "
           "sys.exit(main(sys.argv[1:]))", "reconstruct", str(run / "run.zarr"), "--out",
           str(out), "--tile", "16", "--workers", "1", "--quiet"]
    proc = subprocess.Popen(cmd, cwd=Path(__file__).resolve().parents[3])
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:  # kill once some, not all, tiles are recorded done
        try:
            done = np.asarray(zarr.open_group(str(out), mode="r")["tile_done"][...])
        except Exception:
            done = np.zeros(1, bool)
        if done.sum() >= 2:
            break
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    g = open_ltc_store(out)
    assert not np.asarray(g["tile_done"][...]).all()
    assert cli_main(["lens", str(out), "--out", str(run / "lens.npz"), "--quiet"]) == 1
    assert cli_main(["reconstruct", str(run / "run.zarr"), "--out", str(out), "--tile", "16",
                     "--resume", "--workers", "1", "--quiet"]) == 0
    same_store(serial, out)


def test_lens_refuses_an_incomplete_store_in_one_line(run, serial, capsys, tmp_path):
    import shutil

    bad = tmp_path / "bad.zarr"
    shutil.copytree(serial, bad)
    g = zarr.open_group(str(bad), mode="r+")
    g.attrs["depths_complete"] = [True, False]
    g["tile_done"][1, 0, 0] = False
    assert cli_main(["lens", str(bad), "--out", str(tmp_path / "l.npz"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "depth 1 (z = 160 mm) is incomplete" in err[0] and "--resume" in err[0]
    assert not (tmp_path / "l.npz").exists()
