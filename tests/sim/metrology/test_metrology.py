"""sim.metrology.spheres and sim.metrology.compare against analytic point sets: spheres with known noise,
a known ball bar, known rigid transforms, meshes with known offsets."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from matplotlib.image import imread
from scipy.spatial.transform import Rotation

from sim.metrology.compare import (
    RigidTransform,
    compare_clouds,
    distance_colormap_png,
    estimate_normals,
    icp,
    mesh_signed_distance,
    signed_distance_to_cloud,
)
from sim.metrology.measure import NotCredible, measure_ballbar, measure_sphere
from sim.metrology.spheres import (
    find_sphere_unknown,
    find_spheres,
    fit_sphere,
    fit_sphere_algebraic,
    measure_ball_bar,
)

R_SPHERE = 50.8007 / 2


def cap(rng, n, centre, radius, noise=0.0, view=(0.0, 0.0, -1.0), half_angle_deg=75.0):
    """Points on the part of a sphere seen from direction ``view``, radial noise ``noise`` mm."""
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v[v @ np.asarray(view) > np.cos(np.radians(half_angle_deg))]
    return np.asarray(centre) + v * (radius + rng.normal(0, noise, (len(v), 1)))


def ellipsoid(rng, n, axes=(30.0, 20.0, 12.0)):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    p = v * axes
    nrm = p / np.square(axes)
    return p, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


# ---------------------------------------------------------------- spheres


def test_algebraic_fit_is_exact_on_noise_free_points():
    rng = np.random.default_rng(0)
    c = np.array([12.0, -40.0, 760.0])
    p = cap(rng, 500, c, R_SPHERE)
    centre, r = fit_sphere_algebraic(p)
    np.testing.assert_allclose(centre, c, atol=1e-9)
    assert r == pytest.approx(R_SPHERE, abs=1e-9)


def test_sphere_fit_with_noise_and_outliers():
    rng = np.random.default_rng(1)
    c = np.array([5.0, 3.0, 760.0])
    sigma = 0.005
    p = cap(rng, 40000, c, R_SPHERE, noise=sigma)
    n = len(p)
    p[:100] += rng.normal(0, 2.0, (100, 3))  # 0.4 % gross outliers
    fit = fit_sphere(p)
    assert abs(fit.diameter - 2 * R_SPHERE) < 1.5e-3  # 5x the 0.29 um spread of 30 seeded trials
    assert np.linalg.norm(fit.centre - c) < 5e-4
    assert fit.rms == pytest.approx(sigma, rel=0.05)  # 3-sigma clipping trims ~1.5 %
    assert 5 * sigma < fit.pv < 8 * sigma
    assert not fit.inliers[:100].any() or fit.inliers[:100].mean() < 0.1
    d = fit.as_dict()
    assert d["diameter_mm"] == pytest.approx(fit.diameter) and d["points"] == n


def test_sphere_fit_errors():
    with pytest.raises(ValueError, match=r"must be an \(n, 3\) array"):
        fit_sphere(np.zeros((10, 2)))
    with pytest.raises(ValueError, match="at least 4 are needed"):
        fit_sphere(np.zeros((3, 3)))
    flat = np.random.default_rng(2).normal(size=(50, 3)) * [1, 1, 0]
    with pytest.raises(ValueError, match="degenerate"):
        fit_sphere_algebraic(flat)
    with pytest.raises(ValueError, match="fewer than 4 points"):
        fit_sphere(np.array([[0, 0, 1.0], [0, 1, 0], [1, 0, 0], [0, 0, -1], [5, 5, 5]]), reject_sigma=0.0)


def test_ball_bar_in_clutter():
    """Two balls 209.8219 mm apart among a plane of clutter: length to the fit's precision."""
    rng = np.random.default_rng(3)
    length, r = 209.8219, 38.1 / 2
    axis = np.array([np.cos(0.3), 0.1, np.sin(0.3)])
    axis /= np.linalg.norm(axis)
    mid = np.array([10.0, -5.0, 760.0])
    ca, cb = mid - axis * length / 2, mid + axis * length / 2
    plane = np.column_stack([rng.uniform(-200, 200, 20000), rng.uniform(-100, 100, 20000),
                             np.full(20000, 840.0)])
    pts = np.concatenate([cap(rng, 30000, ca, r, 0.003), cap(rng, 30000, cb, r, 0.003), plane])
    bar = measure_ball_bar(rng.permutation(pts), r)
    assert bar.length == pytest.approx(length, abs=5e-4)
    got = sorted([bar.spheres[0].centre, bar.spheres[1].centre], key=lambda c: c[0])
    np.testing.assert_allclose(got, sorted([ca, cb], key=lambda c: c[0]), atol=5e-4)
    assert all(s.diameter == pytest.approx(2 * r, abs=1e-3) for s in bar.spheres)
    assert bar.as_dict()["length_mm"] == pytest.approx(bar.length)


def test_find_spheres_errors():
    rng = np.random.default_rng(4)
    pts = cap(rng, 3000, [0, 0, 0], 10.0)
    with pytest.raises(ValueError, match="no candidate sphere of radius 25 mm"):
        find_spheres(pts, 1, 25.0)
    with pytest.raises(ValueError, match="radius_mm must be > 0"):
        find_spheres(pts, 1, 0.0)
    with pytest.raises(ValueError, match="only 1 of 2 spheres found: points ran out"):
        find_spheres(pts, 2, 10.0)
    plane = np.column_stack([rng.uniform(-50, 50, (3000, 2)), np.full(3000, 40.0)])
    with pytest.raises(ValueError, match="sphere 2 of 2: no candidate sphere"):
        find_spheres(np.concatenate([pts, plane]), 2, 10.0)


@pytest.mark.slow
def test_sphere_found_without_a_radius_prior_among_a_plane():
    """RANSAC with no radius prior finds the sphere (not the larger plane behind it), and the
    result is the one found with the nominal radius."""
    rng = np.random.default_rng(8)
    plane = np.column_stack([rng.uniform(-250, 250, 60000), rng.uniform(-200, 200, 60000),
                             80.0 + rng.normal(0, 0.005, 60000)])
    pts = rng.permutation(np.concatenate([cap(rng, 3000, [1.0, -2.0, 0.0], R_SPHERE, 0.005), plane]))
    free = find_sphere_unknown(pts)
    assert free.diameter == pytest.approx(2 * R_SPHERE, abs=2e-3)
    np.testing.assert_allclose(free.centre, [1.0, -2.0, 0.0], atol=2e-3)
    prior = find_spheres(pts, 1, R_SPHERE)[0]
    assert abs(prior.diameter - free.diameter) < 1e-9
    with pytest.raises(ValueError, match="no sphere in the points"):
        find_sphere_unknown(plane)


@pytest.mark.slow
def test_measure_refuses_a_fit_far_from_the_nominal():
    rng = np.random.default_rng(9)
    pts = cap(rng, 3000, [0, 0, 0], R_SPHERE, 0.002)
    report, near, d = measure_sphere(pts, 2 * R_SPHERE)
    assert abs(report["diameter_error_mm"]) < 1e-3 and len(near) == len(pts)
    np.testing.assert_allclose(d, np.linalg.norm(near - report["centre_mm"], axis=1)
                               - report["diameter_mm"] / 2)
    with pytest.raises(NotCredible, match=r"nominal diameter 25\.4 mm .*not the radius"):
        measure_sphere(pts, 25.4)  # the radius typed for the diameter
    with pytest.raises(NotCredible, match="tolerance 1 %"):
        measure_sphere(pts, 2 * R_SPHERE * 1.015, tolerance=0.01)
    assert measure_sphere(pts, 2 * R_SPHERE * 1.015)[0]["diameter_error_mm"] < 0
    with pytest.raises(NotCredible, match="no two balls of nominal diameter 50.8007 mm"):
        measure_ballbar(pts, 2 * R_SPHERE)


# ---------------------------------------------------------------- clouds and meshes


def test_icp_recovers_a_known_rigid_transform():
    rng = np.random.default_rng(5)
    target, tn = ellipsoid(rng, 20000)
    source, _ = ellipsoid(rng, 20000)  # a different sampling of the same surface
    r0 = Rotation.from_rotvec([0.03, -0.04, 0.05]).as_matrix()
    t0 = np.array([0.8, -0.5, 0.3])
    moved = source @ r0.T + t0
    tf, n_it = icp(moved, target, tn)
    assert n_it < 20
    np.testing.assert_allclose(tf.R @ r0, np.eye(3), atol=5e-5)
    np.testing.assert_allclose(tf.apply(t0), 0, atol=5e-4)  # undoes the shift
    res = compare_clouds(moved, target, tn)
    assert abs(res.mean) < 2e-5 and res.rmse < 5e-4
    assert res.as_dict()["icp_iterations"] == res.iterations


def test_compare_clouds_without_alignment_measures_a_known_offset():
    """Points 10 um outside the surface: mean +0.010 mm; inside: negative."""
    rng = np.random.default_rng(6)
    ref, rn = ellipsoid(rng, 20000)
    pts, pn = ellipsoid(rng, 5000)
    out = compare_clouds(pts + 0.01 * pn, ref, rn, align=False)
    assert out.mean == pytest.approx(0.01, abs=3e-5) and out.rmse == pytest.approx(0.01, abs=3e-5)
    assert signed_distance_to_cloud(pts - 0.02 * pn, ref, rn).mean() == pytest.approx(-0.02, abs=3e-5)
    # on a sphere the local quadric is exact to 4th order: every point right to 0.1 um
    ref, rn = ellipsoid(rng, 20000, (25.0, 25.0, 25.0))
    pts, pn = ellipsoid(rng, 2000, (25.0, 25.0, 25.0))
    np.testing.assert_allclose(signed_distance_to_cloud(pts - 0.02 * pn, ref, rn), -0.02, atol=1e-4)


def test_estimated_normals_point_outward():
    rng = np.random.default_rng(7)
    p, n_true = ellipsoid(rng, 8000)
    n = estimate_normals(p)
    assert np.mean(np.sum(n * n_true, axis=1) > 0.99) > 0.99


def test_icp_errors():
    rng = np.random.default_rng(8)
    a, an = ellipsoid(rng, 500)
    with pytest.raises(ValueError, match="only 0 pairs closer than 0.1 mm"):
        icp(a + 100.0, a, an, max_distance_mm=0.1)
    with pytest.raises(ValueError, match="source cloud has 2 finite points"):
        icp(a[:2], a, an)
    with pytest.raises(ValueError,
                       match=r"target cloud must be an \(n, 3\) array of points, got shape \(500, 2\)"):
        icp(a, a[:, :2], an)
    with pytest.raises(ValueError, match=r"reference normals have shape \(3, 3\)"):
        signed_distance_to_cloud(a, a, an[:3])


def test_mesh_signed_distance_box_and_sphere():
    box = trimesh.creation.box(extents=(40.0, 30.0, 20.0))
    pts = np.array([[0, 0, 10.05], [0, 0, 9.97], [25.0, 0, 0], [0, 14.0, 0], [23.0, 18.0, 0]])
    want = [0.05, -0.03, 5.0, -1.0, np.hypot(3.0, 3.0)]
    np.testing.assert_allclose(mesh_signed_distance(pts, box), want, atol=1e-12)
    rng = np.random.default_rng(9)
    ico = trimesh.creation.icosphere(5, radius=R_SPHERE)
    p = cap(rng, 3000, [0, 0, 0], R_SPHERE + 0.02, half_angle_deg=180)
    d = mesh_signed_distance(p, ico)
    sagitta = R_SPHERE * (1 - np.cos(np.radians(63.4 / 2**5)))  # largest chord depth, icosphere 5
    assert np.all((d >= 0.02 - 1e-9) & (d <= 0.02 + 2 * sagitta))
    with pytest.raises(ValueError, match="reference mesh has no triangles"):
        mesh_signed_distance(p, trimesh.Trimesh(np.zeros((3, 3)), np.zeros((0, 3), int)))


def test_mesh_signed_distance_with_large_triangles():
    """Two huge triangles (a 1 m square): subdivided internally, distances unchanged."""
    v = np.array([[-500, -500, 0], [500, -500, 0], [500, 500, 0], [-500, 500, 0.0]])
    sq = trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)
    rng = np.random.default_rng(10)
    p = np.column_stack([rng.uniform(-400, 400, (200, 2)), rng.uniform(-5, 5, 200)])
    np.testing.assert_allclose(mesh_signed_distance(p, sq), p[:, 2], atol=1e-9)


def test_colormap_png_shows_both_signs(tmp_path):
    rng = np.random.default_rng(11)
    p = np.column_stack([rng.uniform(-10, 10, (4000, 2)), np.zeros(4000)])
    d = np.where(p[:, 0] > 0, 0.02, -0.02)
    out = tmp_path / "map.png"
    lim = distance_colormap_png(p, d, out)
    assert lim == pytest.approx(0.02)
    img = imread(out)[..., :3]
    assert img.shape[:2] == (500, 600)
    reds = np.sum((img[..., 0] > 0.6) & (img[..., 2] < 0.3))
    blues = np.sum((img[..., 2] > 0.6) & (img[..., 0] < 0.3))
    assert reds > 1000 and blues > 1000  # the +0.02 half red, the -0.02 half blue (coolwarm)
    with pytest.raises(ValueError, match="4000 points but 3 distances"):
        distance_colormap_png(p, d[:3], out)


def test_rigid_transform_apply():
    tf = RigidTransform(Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix(), np.array([1.0, 2, 3]))
    np.testing.assert_allclose(tf.apply(np.array([[1.0, 0, 0]])), [[1, 3, 3]], atol=1e-12)
