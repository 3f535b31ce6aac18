"""sim.fpp.stereo and sim.fpp.cloud: rectification, interpolation, row matching and triangulation
against analytic ground truth (a sphere seen through the default rig's calibration), camera
noise on rendered images, PLY round trips."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sim.fpp.cloud import read_ply, write_ply
from sim.fpp.decode import scan
from sim.fpp.stereo import (
    PointCloud,
    camera_projector_cloud,
    match_row,
    rectify_map,
    sample_image,
    stereo_cloud,
    stereo_rectification,
    triangulate,
)
from sim.metrology.spheres import fit_sphere
from sim.optics.lens import PinholeLens
from sim.optics.rig import DeviceCalibration, Rig, default_rig, look_at
from sim.render.fringe_patterns import PhaseShiftSet
from sim.render.images import CameraResponse, RenderSettings, render_views
from sim.render.scene import Scene, SphereObject

R_SPHERE = 50.8007 / 2


def crop(cam: DeviceCalibration, around_world: np.ndarray, size: tuple[int, int]) -> DeviceCalibration:
    """A ``size`` window of the sensor centred on a world point: same geometry, fewer pixels."""
    uv = cam.project(np.atleast_2d(around_world))[0]
    k = cam.K_array.copy()
    k[0, 2] -= np.round(uv[0] - (size[0] - 1) / 2)
    k[1, 2] -= np.round(uv[1] - (size[1] - 1) / 2)
    return cam.model_copy(update={"K": k.tolist(), "size": size})


def sphere_map(cam: DeviceCalibration, projector: DeviceCalibration, centre, radius, axis=0):
    """Analytic projector coordinate (H, W) of the sphere points a camera sees lit (NaN else)."""
    w, h = cam.size
    vv, uu = np.mgrid[0:h, 0:w]
    o, d = cam.pixel_rays(np.stack([uu.ravel(), vv.ravel()], 1).astype(float))
    oc = o - centre
    b = np.sum(oc * d, 1)
    disc = b * b - (np.sum(oc * oc, 1) - radius**2)
    t = -b - np.sqrt(np.maximum(disc, 0))
    p = o + t[:, None] * d
    lit = (disc > 0) & (np.sum((p - centre) * (projector.centre_world - p), 1) > 0)
    uvp = projector.project(p)
    return np.where(lit, uvp[:, axis], np.nan).reshape(h, w)


@pytest.fixture(scope="module")
def sphere_pair():
    rig = default_rig()  # with lens distortion on cameras and projector
    c = np.array([3.0, -2.0, 5.0])
    cams = [crop(k, c, (360, 360)) for k in rig.cameras]
    maps = [sphere_map(k, rig.projector, c, R_SPHERE) for k in cams]
    return cams, rig.projector, c, maps


# ---------------------------------------------------------------- building blocks


def test_rectify_map_matches_opencv(sphere_pair):
    cams, _, _, maps = sphere_pair
    rect = stereo_rectification(cams[0], cams[1], np.isfinite(maps[0]), np.isfinite(maps[1]))
    mu, mv = rectify_map(cams[0], rect.R1, rect.P1, rect.cols1, rect.rows)
    p = rect.P1.copy()
    p[0, 2] -= rect.cols1[0]
    p[1, 2] -= rect.rows[0]  # OpenCV's map starts at rectified pixel (0, 0)
    size = (rect.cols1[1] - rect.cols1[0] + 1, rect.rows[1] - rect.rows[0] + 1)
    cu, cv = cv2.initUndistortRectifyMap(cams[0].K_array, cams[0].dist_array, rect.R1, p, size, cv2.CV_32FC1)
    assert mu.shape == cu.shape
    np.testing.assert_allclose(mu, cu, atol=2e-4)  # float32 rounding of OpenCV's map
    np.testing.assert_allclose(mv, cv, atol=2e-4)


def test_sample_image_is_exact_for_polynomials():
    yy, xx = np.mgrid[0:20, 0:30].astype(float)
    cubic = 0.01 * xx**3 - 0.2 * xx**2 * yy + 0.03 * yy**3 + xx * yy + 2
    plane = 3 * xx - 2 * yy + 1
    rng = np.random.default_rng(0)
    u, v = rng.uniform(1, 27, 200), rng.uniform(1, 17, 200)
    np.testing.assert_allclose(sample_image(cubic, u, v, 3),
                               0.01 * u**3 - 0.2 * u**2 * v + 0.03 * v**3 + u * v + 2, rtol=1e-11)
    np.testing.assert_allclose(sample_image(plane, u, v, 1), 3 * u - 2 * v + 1, rtol=1e-12)
    holed = plane.copy()
    holed[10, 10] = np.nan
    got = sample_image(holed, np.array([9.5, 11.5, 12.2, 29.5]), np.array([9.5, 10.5, 10.5, 5.0]), 3)
    assert np.isnan(got[0]) and np.isnan(got[1])  # the hole is inside both 4x4 stencils
    assert got[2] == pytest.approx(3 * 12.2 - 2 * 10.5 + 1) and np.isnan(got[3])  # outside
    with pytest.raises(ValueError, match="order must be 1 or 3, got 2"):
        sample_image(plane, u, v, 2)


def test_triangulate_matches_opencv(sphere_pair):
    cams, _, c, _ = sphere_pair
    rng = np.random.default_rng(3)
    pts = c + rng.normal(0, 20, (500, 3))
    p = [k.K_array @ np.concatenate([k.R_array, k.T_array[:, None]], axis=1) for k in cams]
    xy = [(pts @ pp[:, :3].T + pp[:, 3])[:, :2] / (pts @ pp[2, :3] + pp[2, 3])[:, None] for pp in p]
    np.testing.assert_allclose(triangulate(p[0], p[1], xy[0], xy[1]), pts, atol=1e-8)
    noisy = [x + rng.normal(0, 0.3, x.shape) for x in xy]
    h = cv2.triangulatePoints(p[0], p[1], noisy[0].T, noisy[1].T)
    ours = triangulate(p[0], p[1], noisy[0], noisy[1])
    assert np.median(np.linalg.norm(ours - (h[:3] / h[3]).T, axis=1)) < 1e-3  # both ~0.1 mm off


def test_match_row_finds_every_crossing():
    right = np.array([np.nan, 0.0, 1.0, 2.0, 3.0, np.nan, 9.0, 7.0, 5.0, 3.0, 1.0])
    left = np.array([0.5, 2.25, 6.0, np.nan, 3.0])
    runs = match_row(left, right, order=1)
    found = {(int(j), float(x)) for jl, xr in runs for j, x in zip(jl, xr, strict=True)}
    # rising run 1..4: 0.5 -> 1.5, 2.25 -> 3.25, 3 -> 4; falling 6..10: 2.25 -> 9.375, 6 -> 7.5, 3 -> 9
    assert found == {(0, 1.5), (1, 3.25), (4, 4.0), (1, 9.375), (2, 7.5), (4, 9.0)}
    assert match_row(np.full(3, np.nan), right) == []
    assert match_row(left, np.full(5, np.nan)) == []


def test_match_row_cubic_is_exact_on_a_cubic_row():
    x = np.arange(40, dtype=float)
    def f(t):
        return 0.001 * t**3 + 0.02 * t**2 + 0.5 * t  # increasing

    targets = np.array([5.3, 17.77, 30.01])
    ((jl, xr),) = match_row(f(targets), f(x), order=3)
    np.testing.assert_array_equal(jl, [0, 1, 2])
    np.testing.assert_allclose(xr, targets, atol=1e-9)


# ---------------------------------------------------------------- analytic sphere


@pytest.mark.slow
def test_stereo_cloud_of_an_analytic_sphere_is_exact(sphere_pair):
    cams, proj, c, maps = sphere_pair
    cloud = stereo_cloud(maps[0], maps[1], cams[0], cams[1], projector=proj,
                         quality1=np.ones((360, 360)), quality2=np.ones((360, 360)))
    r = np.linalg.norm(cloud.points - c, axis=1) - R_SPHERE
    assert len(r) > 0.9 * min(np.isfinite(m).sum() for m in maps)
    assert np.median(np.abs(r)) < 1e-5 and np.sqrt(np.mean(r * r)) < 1e-3  # grazing rim: larger
    fit = fit_sphere(cloud.points)
    assert abs(fit.diameter - 2 * R_SPHERE) < 5e-5 and fit.rms < 5e-5
    radial = (cloud.points - c) / np.linalg.norm(cloud.points - c, axis=1, keepdims=True)
    cosine = np.sum(cloud.normals * radial, axis=1)
    assert np.mean(np.isfinite(cosine)) > 0.999  # NaN: points without a row or column neighbour
    assert np.nanmedian(cosine) > 0.9999 and np.nanmin(cosine) > 0  # outward, facing the camera
    np.testing.assert_allclose(cloud.quality, 1.0)
    # both directions: every point names its reference camera and pixel
    assert set(np.unique(cloud.fields["camera"])) == {0.0, 1.0}
    for k in (0, 1):
        mine = cloud.fields["camera"] == k
        uv = np.stack([cloud.fields["u"][mine], cloud.fields["v"][mine]], axis=1)
        np.testing.assert_allclose(cams[k].project(cloud.points[mine]), uv, atol=1e-6)
    # the sub-pixel match comes from the local phase model, not from the interpolation
    linear = stereo_cloud(maps[0], maps[1], cams[0], cams[1], projector=proj, order=1)
    assert abs(fit_sphere(linear.points).diameter - fit.diameter) < 1e-7


@pytest.mark.slow
def test_ambiguous_matches_resolved_by_the_projector(sphere_pair):
    cams, proj, c, maps = sphere_pair
    right = maps[1].copy()
    right[:, 300:355] = np.where(np.isnan(right[:, 300:355]), maps[1][:, 100:155], right[:, 300:355])
    plain = stereo_cloud(maps[0], maps[1], cams[0], cams[1])
    with_proj = stereo_cloud(maps[0], right, cams[0], cams[1], projector=proj)
    without = stereo_cloud(maps[0], right, cams[0], cams[1])
    assert len(without.points) < len(plain.points) - 1000  # doubled rows are dropped
    assert abs(len(with_proj.points) - len(plain.points)) < 0.01 * len(plain.points)
    r = np.linalg.norm(with_proj.points - c, axis=1) - R_SPHERE
    assert np.abs(r).max() < 0.02


def test_camera_projector_cloud_is_exact_with_distortion(sphere_pair):
    cams, proj, c, _ = sphere_pair
    for axis, k in (("u", 0), ("v", 1)):
        coord = sphere_map(cams[0], proj, c, R_SPHERE, axis=k)
        pts, uv = camera_projector_cloud(coord, cams[0], proj, axis)
        assert len(pts) == np.isfinite(coord).sum()
        r = np.linalg.norm(pts - c, axis=1) - R_SPHERE
        assert np.abs(r).max() < 1e-7
        np.testing.assert_allclose(cams[0].project(pts), uv, atol=1e-7)


def test_stereo_errors(sphere_pair):
    cams, proj, _, maps = sphere_pair
    with pytest.raises(ValueError, match=r"'left': projector-coordinate map has shape \(10, 10\)"):
        stereo_cloud(np.zeros((10, 10)), maps[1], cams[0], cams[1])
    with pytest.raises(ValueError, match="'left': no valid pixels to match"):
        stereo_cloud(np.full((360, 360), np.nan), maps[1], cams[0], cams[1])
    with pytest.raises(ValueError, match="found no pixel with the same projector coordinate"):
        stereo_cloud(maps[0], maps[1] + 5000.0, cams[0], cams[1])
    with pytest.raises(ValueError, match=r"'left': phase map is 10 x 10 pixels"):
        stereo_rectification(cams[0], cams[1], np.ones((10, 10), bool), np.isfinite(maps[1]))
    with pytest.raises(ValueError, match="axis must be 'u' or 'v', got 'w'"):
        camera_projector_cloud(maps[0], cams[0], proj, "w")
    with pytest.raises(ValueError, match=r"'left': projector-coordinate map has shape \(3, 3\)"):
        camera_projector_cloud(np.zeros((3, 3)), cams[0], proj)
    r, t = look_at(np.array([0.0, -200.0, -740.0]), np.zeros(3))
    above = cams[1].model_copy(update={"R": r.tolist(), "T": t.tolist(), "dist": [0.0] * 5})
    with pytest.raises(ValueError, match="displaced vertically"):
        stereo_rectification(cams[0], above, np.isfinite(maps[0]), np.isfinite(maps[1]))
    far = cams[1].model_copy(update={"K": (cams[1].K_array + [[0, 0, 0], [0, 0, 5000], [0, 0, 0]]).tolist()})
    with pytest.raises(ValueError, match="share no epipolar lines"):
        stereo_rectification(cams[0], far, np.isfinite(maps[0]), np.isfinite(maps[1]))


def test_reconstruct_errors():
    rig = Rig(cameras=[crop(k, np.zeros(3), (40, 30)) for k in default_rig().cameras],
              projector=default_rig().projector)
    rng = np.random.default_rng(0)
    ps_v = PhaseShiftSet(periods_px=[1080.0, 16.0], steps=4, direction="v")
    d = 2 * np.pi * np.arange(4) / 4
    one = 100 + 50 * np.cos(rng.uniform(0, 7, (30, 40))[None] - d[:, None, None])
    stack = np.concatenate([one, one])  # fringes along v only
    with pytest.raises(ValueError, match="stereo needs the image stacks of 2 cameras, got 1"):
        scan([stack], ps_v, rig)
    with pytest.raises(ValueError, match="stereo matching needs fringes along 'u'"):
        scan([stack, stack], ps_v, rig)
    with pytest.raises(ValueError, match="camera must be 0 or 1, got 2"):
        scan([stack, stack], ps_v, rig, camera=2)
    with pytest.raises(ValueError, match="camera 0 has 8 images, camera 1 has 7: the stacks must match"):
        scan([stack, stack[:7]], ps_v, rig)
    pts = scan([stack], ps_v, rig, camera=0)  # one stack is enough for camera-projector
    assert np.isfinite(pts.points).all()


# ---------------------------------------------------------------- rendered, with camera noise


@pytest.mark.slow
def test_camera_noise_degrades_the_sphere_gracefully():
    """Shot noise, 5 e- read noise, 8-bit images (the default camera, 80 % of full well at
    white): the per-point noise grows to ~13 um, the diameter stays within a few um."""
    base = default_rig(distortion=False)
    rig = Rig(cameras=[crop(k, np.zeros(3), (320, 320)) for k in base.cameras], projector=base.projector)
    ps = PhaseShiftSet(periods_px=[1920.0, 120.0, 16.0], steps=4)
    geom = Scene(objects=[SphereObject()]).trace_geometry()
    settings = RenderSettings(camera=CameraResponse(shot_noise=True, read_noise_e=5.0))
    res = render_views(geom, rig, [PinholeLens()] * 2, ps.images(rig.projector.size), settings,
                       np.random.default_rng(7))
    cloud = scan([c.images for c in res.cameras], ps, rig)
    fit = fit_sphere(cloud.points)
    assert fit.inliers.sum() > 40000
    assert abs(fit.diameter - 2 * R_SPHERE) < 0.005
    assert 0.005 < fit.rms < 0.025
    assert np.linalg.norm(fit.centre) < 0.005


# ---------------------------------------------------------------- PLY


def test_ply_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(100, 3)) * 100 + [0, 0, 760]
    n = rng.normal(size=(100, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    q = rng.uniform(0, 255, 100)
    write_ply(tmp_path / "a.ply", PointCloud(pts, n, q))
    back = read_ply(tmp_path / "a.ply")
    np.testing.assert_array_equal(back.points, pts)  # double precision, exact
    np.testing.assert_allclose(back.normals, n, rtol=1e-6)
    np.testing.assert_allclose(back.quality, q, rtol=1e-6)
    header = (tmp_path / "a.ply").read_bytes().split(b"end_header")[0].decode()
    assert "property float nx" in header and "property float scalar_quality" in header
    write_ply(tmp_path / "b.ply", PointCloud(pts))
    b = read_ply(tmp_path / "b.ply")
    assert b.normals is None and b.quality is None and b.fields == {}
    ascii_ply = (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                 b"property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                 b"end_header\n1 2 3\n4 5 6\n3 0 1 1\n")
    (tmp_path / "c.ply").write_bytes(ascii_ply)
    np.testing.assert_array_equal(read_ply(tmp_path / "c.ply").points, [[1, 2, 3], [4, 5, 6]])


@pytest.mark.slow
def test_scanned_ply_carries_scalar_fields_and_normals(tmp_path):
    """A scan's PLY: ``x y z``, ``nx ny nz`` and ``scalar_<name>`` per-point extras (the names
    CloudCompare shows as scalar fields), read back as they were written."""
    rig = Rig(cameras=[crop(k, np.zeros(3), (96, 80)) for k in default_rig(distortion=False).cameras],
              projector=default_rig(distortion=False).projector)
    ps = PhaseShiftSet(periods_px=[1920.0, 120.0, 16.0], steps=4)
    geom = Scene(objects=[SphereObject()]).trace_geometry()
    settings = RenderSettings(camera=CameraResponse(shot_noise=True, read_noise_e=5.0, bit_depth=12))
    res = render_views(geom, rig, [PinholeLens()] * 2, ps.images(rig.projector.size), settings,
                       np.random.default_rng(2))
    for camera in (None, 0):
        cloud = scan([c.images for c in res.cameras], ps, rig, camera=camera)
        write_ply(tmp_path / "s.ply", cloud)
        header = (tmp_path / "s.ply").read_bytes().split(b"end_header")[0].decode()
        for name in ("x", "y", "z", "nx", "ny", "nz", "scalar_quality", "scalar_modulation", "scalar_camera",
                     "scalar_u", "scalar_v", "scalar_phase_error", "scalar_uncertainty_mm"):
            assert f" {name}\n" in header
        back = read_ply(tmp_path / "s.ply")
        for name, values in cloud.fields.items():
            np.testing.assert_allclose(back.fields[name], values, rtol=1e-6)
        # the propagated uncertainty is the size of the real error: a few to tens of um
        r = np.abs(np.linalg.norm(cloud.points, axis=1) - R_SPHERE)
        u = cloud.fields["uncertainty_mm"]
        assert 0.3 < np.sqrt(np.mean(r * r)) / np.sqrt(np.mean(u * u)) < 1.5
        assert 0 < np.median(cloud.quality) <= 1.0
        pe = cloud.fields["phase_error"]  # NaN where the 3 x 3 stencil leaves the image
        assert np.mean(np.isfinite(pe)) > 0.9 and np.all(pe[np.isfinite(pe)] >= 0)


@pytest.mark.parametrize(
    "content, message",
    [
        (b"hello\n", "not a PLY file"),
        (b"ply\nformat weird 1.0\n", "unknown PLY format 'weird'"),
        (b"ply\nformat ascii 1.0\nelement face 1\nend_header\n", "first PLY element must be 'vertex'"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n",
         "needs properties x, y and z"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar int x\n", "list property 'x'"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\n", "unknown PLY type 'quad'"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\n", "no end_header"),
        (b"ply\nelement vertex 1\nend_header\n", "lacks a format line"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
         b"property float z\nend_header\n" + bytes(12), "ends after 1 of 2 vertices"),
        ((b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
          b"end_header\n1 2 3\n4 5\n"), "vertex row 1 has 2 values, the header declares 3"),
        ((b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
          b"end_header\n1 2\n4 5\n"), "vertex row 0 has 2 values, the header declares 3"),
    ],
)
def test_read_ply_errors(tmp_path, content, message):
    (tmp_path / "bad.ply").write_bytes(content)
    with pytest.raises(ValueError, match=message):
        read_ply(tmp_path / "bad.ply")


def test_ply_write_and_missing_file_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        read_ply(tmp_path / "nope.ply")
    with pytest.raises(ValueError, match=r"points must be \(n, 3\)"):
        write_ply(tmp_path / "x.ply", PointCloud(np.zeros((3, 2))))
    with pytest.raises(ValueError, match="normals have shape"):
        write_ply(tmp_path / "x.ply", PointCloud(np.zeros((3, 3)), np.zeros((2, 3))))
    with pytest.raises(ValueError, match="2 quality values for 3 points"):
        write_ply(tmp_path / "x.ply", PointCloud(np.zeros((3, 3)), None, np.zeros(2)))
