"""Clouds as a lab brings them: a small clean cap of the 50.8 mm sphere measured with no
nominal diameter; a cloud of two objects compared with one object's CAD mesh; two clouds of
one rig compared pixel by pixel."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from sim.fpp.cloud import PointCloud
from sim.metrology.measure import (
    NotCredible,
    measure_against_mesh,
    measure_by_pixel,
    measure_sphere,
)

D = 50.8007


def cap(n: int, degrees: float, seed: int = 1) -> np.ndarray:
    """``n`` points of the sphere within ``degrees`` of its pole facing -z, 5 um noise."""
    rng = np.random.default_rng(seed)
    ct = rng.uniform(np.cos(np.radians(degrees)), 1, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    st = np.sqrt(1 - ct**2)
    p = D / 2 * np.stack([st * np.cos(ph), st * np.sin(ph), -ct], 1) + [3.0, 4.0, 760.0]
    return p + rng.normal(0, 0.005, p.shape)


@pytest.mark.parametrize("degrees", [30, 40, 70])
def test_a_small_cap_is_found_without_its_diameter(degrees):
    """A 424-point cap 30 or 40 degrees about its pole spans less than the diameter (35,
    45 mm): refused before as 'no sphere in the points'."""
    report, _, _ = measure_sphere(cap(424, degrees))
    assert report["diameter_mm"] == pytest.approx(D, abs=0.01)


def test_a_plane_is_still_no_sphere():
    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(-50, 50, (2000, 2)), rng.normal(0, 0.005, 2000)]
    with pytest.raises(ValueError, match="no sphere"):
        measure_sphere(p)


def test_cad_comparison_selects_the_part_and_refuses_a_diverged_icp(tmp_path):
    box = trimesh.creation.box((60.0, 40.0, 20.0))
    box.export(tmp_path / "part.ply")
    pts = trimesh.sample.sample_surface_even(box, 3000, seed=0)[0] + [0.3, -0.2, 0.1]
    other = trimesh.creation.icosphere(4, 25.0).vertices + [90.0, 0.0, 0.0]
    cloud = np.concatenate([pts, other])
    report, d = measure_against_mesh(cloud, tmp_path / "part.ply")
    assert report["points_selected"] == len(pts) and report["icp_converged"]
    assert abs(report["mean_mm"]) < 0.01 and report["rmse_mm"] < 0.02
    # with every point, ICP is pulled off the part: refused, not a number
    with pytest.raises(NotCredible, match="ICP did not converge onto the part"):
        measure_against_mesh(cloud, tmp_path / "part.ply", select=False)
    # a part that is not where the mesh is: refused naming the box
    with pytest.raises(NotCredible, match="inside the CAD part's bounding box"):
        measure_against_mesh(other + [200.0, 0, 0], tmp_path / "part.ply")


def test_two_clouds_of_one_rig_compared_by_pixel():
    """The same pixels, the second cloud 3 um further along each point's normal."""
    g = np.mgrid[0:20, 0:30].reshape(2, -1).T
    pts = np.c_[g[:, 1] * 1.0, g[:, 0] * 1.0, np.full(len(g), 700.0)]
    nrm = np.tile([0.0, 0.0, -1.0], (len(g), 1))
    fields = {"camera": np.zeros(len(g)), "u": g[:, 1] * 1.0, "v": g[:, 0] * 1.0}
    ref = PointCloud(pts, nrm, None, fields)
    moved = PointCloud(pts + [0.0, 0.0, -0.003], nrm, None, fields)
    report, _, d = measure_by_pixel(moved, ref)
    assert report["mean_mm"] == pytest.approx(0.003, abs=1e-9)
    assert report["points"] == 18 * 28  # the edge pixels are left out
    assert abs(report["mean_icp_mm"]) < 1e-6
    with pytest.raises(ValueError, match="compare by pixel needs clouds written by ltc scan"):
        measure_by_pixel(PointCloud(pts, nrm, None, {}), ref)
