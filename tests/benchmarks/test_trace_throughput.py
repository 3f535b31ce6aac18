"""The tracing-throughput benchmark (``benchmarks/trace_throughput.py``) on a tiny scene: the raw
side replays exactly the Embree queries ours makes, the counts add up, and its errors."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from sim.optics.lens import PinholeLens
from sim.optics.rig import small_rig
from sim.render.scene import PlaneObject, Pose, Scene, SphereObject

ROOT = Path(__file__).resolve().parents[2]


def _load_benchmark():
    spec = importlib.util.spec_from_file_location("trace_throughput_benchmark",
                                                  ROOT / "benchmarks" / "trace_throughput.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


B = _load_benchmark()


def test_tiny_run_counts_the_rays_it_times(tmp_path):
    out = tmp_path / "r.json"
    s = B.main(["--scale", "0.06", "--repeats", "2", "--samples", "3", "--band-fraction", "0.25",
                "--json", str(out)])
    assert out.is_file()
    pin, thin = s["cases"]
    assert pin["primary"] == pin["pixels"] == 123 * 65  # one ray per pixel
    assert thin["primary"] == thin["pixels"] * 4  # 3 lens rays and the chief ray
    for c in (pin, thin):
        assert 0 < c["shadow"] <= c["primary"]
        assert len(c["times"]["ours"][0]) == len(c["times"]["raw"][0]) == 2
        assert c["fraction"] == pytest.approx(c["raw_wall_s"] / c["ours_wall_s"])
    assert "| pinhole |" in B.report_markdown(s) and "| thin |" in B.report_markdown(s)


def test_recorded_queries_are_the_primary_and_shadow_rays():
    rig = small_rig(0.03, distortion=False)
    cam = rig.cameras[0]
    geom = Scene(objects=[SphereObject(), PlaneObject(pose=Pose(t=[0, 0, 60.0]))]).trace_geometry()
    pix = np.arange(cam.width * cam.height)
    from sim.render.trace import trace_camera

    queries = B.record_queries(geom, lambda: trace_camera(geom, cam, rig.projector, PinholeLens(),
                                                          pixels=pix))
    counts = B.summarise_queries(queries)
    B.check_primaries(queries, cam, PinholeLens(), pix)
    assert counts["primary"] == len(pix) and counts["calls"] >= 2
    tr = trace_camera(geom, cam, rig.projector, PinholeLens())
    assert counts["shadow"] >= tr.lit.sum() > 0  # a shadow ray for every lit pixel, at least
    assert geom.__dict__["embree"] is not None and not isinstance(geom.embree, B.RecordingScene)
    with pytest.raises(RuntimeError, match="primary rays recorded, camera_rays gives"):
        B.check_primaries(queries[1:], cam, PinholeLens(), pix)
    q0 = queries[0]
    moved = [(q0[0] + np.float32(1.0), q0[1], q0[2])] + list(queries[1:])
    with pytest.raises(RuntimeError, match="recorded primary origins differ from camera_rays"):
        B.check_primaries(moved, cam, PinholeLens(), pix)
    with pytest.raises(RuntimeError, match="a primary query without output=1"):
        B.summarise_queries([(q0[0], q0[1], {})])


def test_bad_cases_and_the_results_file_rewritten_whole(tmp_path):
    with pytest.raises(ValueError, match=r"--cases: unknown case\(s\) \['fisheye'\]"):
        B.main(["--cases", "pinhole,fisheye"])
    path = B.write_results(B.__file__, B.TITLE, "| old |\n", command="cmd", results_dir=tmp_path)
    assert path == tmp_path / "trace_throughput.md"
    path = B.write_results(B.__file__, B.TITLE, "| new |\n", results_dir=tmp_path)
    assert path.read_text() == f"# {B.TITLE}\n\n| new |\n"  # the whole file, nothing kept
    assert [p.name for p in tmp_path.iterdir()] == ["trace_throughput.md"]  # no temporary left
