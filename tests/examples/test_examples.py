"""The example scripts a lab operator starts from run as documented and do what they say."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import zarr

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


def run_example(name: str, *args: str, timeout: float = 600) -> str:
    proc = subprocess.run([sys.executable, str(EXAMPLES / name), *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


@pytest.mark.slow
def test_drive_fake_bench_homes_moves_shows_captures_and_saves(tmp_path):
    out = run_example("drive_fake_bench.py", str(tmp_path))
    assert "homed: stage at 0.000 mm" in out
    assert "moved: stage at 40.000 mm (asked 40.0 mm)" in out
    assert "captured: frame 0, 64 x 48 uint16, 12 bits" in out
    image = cv2.imread(str(tmp_path / "frame.png"), cv2.IMREAD_UNCHANGED)
    meta = json.loads((tmp_path / "frame.json").read_text())
    assert image.shape == (48, 64) and image.dtype == np.uint16
    # the left half of the LCD is white: the camera (not mirrored) sees its left half bright
    assert meta["mean_left"] > 20 * meta["mean_right"]
    assert np.isclose(image[:, :32].mean(), meta["mean_left"])


@pytest.mark.slow
def test_virtual_scan_measures_the_sphere_of_the_example_scene(tmp_path):
    ply = tmp_path / "sphere.ply"
    out = run_example("virtual_scan.py", str(EXAMPLES / "sphere_scene.toml"), str(ply))
    assert "rendered: 2 cameras" in out and f"wrote: {ply}" in out
    err_um = float(out.split("error ")[1].split(" um")[0])
    # 410 x 217 cameras (about 0.5 mm per pixel on the sphere), f/4 defocus, shot noise: the
    # stereo diameter is within 0.5 % of nominal (a 31 px sphere: noise-limited;
    # examples/standard_sphere.toml is the scene that measures it to microns)
    assert abs(err_um) < 250.0, out
    # the API and the command line measure the written cloud alike
    cli = subprocess.run([sys.executable, "-m", "station.cli", "measure", str(ply), "--sphere",
                          "--diameter", "50.8007", "--json"], capture_output=True, text=True,
                         cwd=ROOT, check=True)
    assert abs(1e3 * json.loads(cli.stdout)["diameter_error_mm"] - err_um) < 0.06


@pytest.mark.slow
def test_the_readme_first_scan_measures_the_standard_sphere_to_microns(tmp_path):
    """The README's first scan, its three commands as typed there: the 50.8007 mm sphere in
    focus, 1229 x 650 cameras with shot noise, measures within a few micrometres."""
    ltc = [sys.executable, "-m", "station.cli"]
    render, ply = tmp_path / "sphere", tmp_path / "sphere.ply"
    rig = "examples/standard_sphere_rig.yaml"
    for args in (["render", "examples/standard_sphere.toml", "--out", str(render), "--quiet"],
                 ["scan", str(render), "--rig", rig, "--out", str(ply)]):
        subprocess.run(ltc + args, cwd=ROOT, check=True, capture_output=True, timeout=600)
    out = subprocess.run(ltc + ["measure", str(ply), "--sphere", "--diameter", "50.8007", "--json"],
                         cwd=ROOT, check=True, capture_output=True, text=True).stdout
    m = json.loads(out)
    # three noise seeds gave +1.8, -0.5, -1.2 um; the fit RMS is the camera noise (~21 um)
    assert abs(m["diameter_error_mm"]) < 0.005, m
    assert m["fit_rms_mm"] < 0.03 and np.linalg.norm(m["centre_mm"]) < 0.005, m


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> dict:
    """The unattended sequence example, SIGKILLed during its acquisition, then run again: the
    dead run's lock died with it (flock), so the second run continues where it stopped."""
    seq = tmp_path_factory.mktemp("sequence") / "seq"
    cmd = [sys.executable, str(EXAMPLES / "unattended_sequence.py"), str(seq)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    deadline = time.monotonic() + 300
    try:
        while True:  # kill it once the acquisition has written some frames
            assert time.monotonic() < deadline and proc.poll() is None, "sequence never acquired"
            done = seq / "run.zarr" / "done"
            if done.exists():
                try:
                    if 10 < int(np.asarray(zarr.open_group(str(seq / "run.zarr"),
                                                           mode="r")["done"][:]).sum()):
                        break
                except (KeyError, ValueError, FileNotFoundError):
                    pass
            time.sleep(0.2)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    killed = json.loads((seq / "summary.json").read_text())
    again = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert again.returncode == 0, again.stderr[-2000:]
    return {"seq": seq, "killed_summary": killed, "out": again.stdout}


@pytest.mark.slow
def test_unattended_sequence_resumes_after_a_kill_and_finds_the_true_optical_centre(sequence):
    from fakes.truth import lens_truth

    seq, out = sequence["seq"], sequence["out"]
    assert sequence["killed_summary"]["steps"]["check"]["status"] == "done"
    assert sequence["killed_summary"]["steps"]["acquire"]["status"] == "running"
    summary = json.loads((seq / "summary.json").read_text())
    assert summary["status"] == "complete"
    assert summary["steps"]["acquire"]["result"]["resumed"] is True
    assert 0 < summary["steps"]["acquire"]["result"]["frames_written"] < \
        summary["steps"]["acquire"]["result"]["frames_total"]
    assert all(summary["steps"][s]["status"] == "done"
               for s in ("check", "align", "acquire", "reconstruct", "lens"))
    assert "lens: done" in out and (seq / "lens.npz").is_file()
    truth = lens_truth(zarr.open_group(str(seq / "ltc.zarr"), mode="r").attrs["config"])
    found = np.array(summary["steps"]["lens"]["result"]["optical_centre_mm"])
    # the demo's figure on the same fake bench: 0.091 mm
    assert np.linalg.norm(found - truth["optical_centre_mm"]) < 0.15
    log = (seq / "run.log").read_text()
    assert "check: done in an earlier run, skipped" in log and "sequence" in log


@pytest.mark.slow
def test_measured_vs_gaussian_compares_the_two_scanners(sequence, tmp_path):
    import sim
    from sim.optics import centre_moments

    lens = sequence["seq"] / "lens.npz"
    out = run_example("measured_vs_gaussian.py", str(lens), str(tmp_path))
    summary = json.loads((tmp_path / "summary.json").read_text())
    measured = sim.MeasuredLens.load(lens)
    # the Gaussian model is the measured lens's: its variance is the measured second moment
    # at the optical centre (docs/optics.md, section 4)
    _, cov = centre_moments(measured)
    assert summary["gaussian_sigma_mm"] ** 2 == pytest.approx(0.5 * np.trace(cov), rel=1e-9)
    focus, defocus = summary["positions"]
    for row in (focus, defocus):
        assert row["measured"]["points"] > 100 and row["gaussian"]["points"] > 100
        assert (tmp_path / f"{row['position'].replace(' ', '_')}_measured.ply").is_file()
    # the two models part where the blur is large: further apart out of focus than in focus
    assert abs(defocus["gaussian_vs_measured"]["mean_um"]) > \
        abs(focus["gaussian_vs_measured"]["mean_um"])
    assert "Gaussian cloud vs measured" in out
