"""sim.render.trace against analytic optics: plane homography, exact spheres, shadows, lens rays."""

import cv2
import numpy as np
import pytest

from sim.optics.lens import AberratedLens, PinholeLens, hit_plane
from sim.optics.projection import pixel_to_normalized, project_points
from sim.optics.rig import DeviceCalibration, small_rig
from sim.render import trace
from sim.render.scene import PlaneObject, Pose, Scene, SphereObject
from sim.render.trace import TraceGeometry, normalized_grid, trace_camera

PLANE_R = cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0]
PLANE_T = np.array([5.0, -3.0, 40.0])


def _plane_geometry(albedo=0.6):
    plane = PlaneObject(size_mm=(3000.0, 3000.0), albedo=albedo, pose=Pose(R=PLANE_R, t=PLANE_T))
    return Scene(objects=[plane]).trace_geometry()


def _ray_plane(origins, dirs, normal, point):
    s = ((point - origins) @ normal) / (dirs @ normal)
    return origins + s[:, None] * dirs


def _check_plane(rig, tr, projected):
    cam, proj = rig.cameras[0], rig.projector
    w, h = cam.size
    n = PLANE_R[:, 2]
    o, d = cam.pixel_rays(np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2))
    x = _ray_plane(o, d, n, PLANE_T)
    uv_p = projected(x)
    lit = tr.weight[:, 0] > 0
    assert lit.sum() > 0.3 * w * h
    err = np.abs(tr.proj_uv[lit, 0] - uv_p[lit])
    assert err.max() < 1e-3, err.max()
    # every pixel whose analytic projector coordinate is well inside the image is lit
    pw, ph = proj.size
    inside = ((uv_p[:, 0] > -0.499) & (uv_p[:, 0] < pw - 0.501)
              & (uv_p[:, 1] > -0.499) & (uv_p[:, 1] < ph - 0.501))
    border = ((uv_p[:, 0] > -0.501) & (uv_p[:, 0] < pw - 0.499)
              & (uv_p[:, 1] > -0.501) & (uv_p[:, 1] < ph - 0.499))
    assert np.all(lit[inside]) and not np.any(lit & ~border)
    # depth and N.L weight
    np.testing.assert_allclose(tr.depth, cam.to_device(x)[:, 2], rtol=1e-12)
    L = proj.centre_world - x
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    np.testing.assert_allclose(tr.weight[lit, 0], 0.6 * np.abs(L[lit] @ n), rtol=1e-5)
    np.testing.assert_allclose(tr.projector_map().reshape(-1, 2)[lit], uv_p[lit], atol=1e-9)


def test_pinhole_plane_matches_the_homography():
    rig = small_rig(0.05, distortion=False)
    cam, proj = rig.cameras[0], rig.projector
    tr = trace_camera(_plane_geometry(), cam, proj, PinholeLens())
    # homography of the plane n.X = n.t: camera pixel -> projector pixel, no shared code path
    n = PLANE_R[:, 2]
    Rc, Tc, Rp, Tp = cam.R_array, cam.T_array, proj.R_array, proj.T_array

    def homography(x_world):
        del x_world
        uv = np.stack(np.meshgrid(np.arange(cam.width), np.arange(cam.height)), -1).reshape(-1, 2)
        ray = np.linalg.solve(cam.K_array, np.concatenate([uv, np.ones((len(uv), 1))], 1).T)  # cam frame
        d_w = Rc.T @ ray
        c_w = -Rc.T @ Tc
        s = (n @ PLANE_T - n @ c_w) / (n @ d_w)
        xw = c_w[:, None] + s * d_w
        p = proj.K_array @ (Rp @ xw + Tp[:, None])
        return (p[:2] / p[2]).T

    _check_plane(rig, tr, homography)


def test_distorted_rig_plane_matches_projection():
    rig = small_rig(0.05, distortion=True)
    tr = trace_camera(_plane_geometry(), rig.cameras[0], rig.projector, PinholeLens())
    _check_plane(rig, tr, rig.projector.project)


def _segment_hits_sphere(x, c_p, centre, r):
    """True where the segment x -> c_p passes within r of centre."""
    seg = c_p - x
    s = np.clip(((centre - x) * seg).sum(1) / (seg * seg).sum(1), 0, 1)
    return np.linalg.norm(x + s[:, None] * seg - centre, axis=1) < r


def test_sphere_shadow_on_plane_matches_the_analytic_region():
    rig = small_rig(0.1)
    cam, proj = rig.cameras[0], rig.projector
    r = 50.8007 / 2
    scene = Scene(objects=[SphereObject(), PlaneObject(size_mm=(3000.0, 3000.0), pose=Pose(t=[0, 0, 60.0]))])
    tr = trace_camera(scene.trace_geometry(), cam, proj, PinholeLens())
    w, h = cam.size
    o, d = cam.pixel_rays(np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2))
    b = (o * d).sum(1)
    disc = b * b - ((o * o).sum(1) - r * r)
    on_sphere = disc > 0
    t = np.where(on_sphere, -b - np.sqrt(np.maximum(disc, 0)), (60.0 - o[:, 2]) / d[:, 2])
    x = o + t[:, None] * d
    normal = np.where(on_sphere[:, None], x / r, [0.0, 0.0, -1.0])
    L = proj.centre_world - x
    uv = proj.project(x)
    pw, ph = proj.size
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= pw - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= ph - 0.5)
    shadow = ~on_sphere & _segment_hits_sphere(x, proj.centre_world, np.zeros(3), r)
    lit = inside & ((normal * L).sum(1) > 0) & ~shadow
    assert np.sum(shadow & inside) > 100  # the test sees a real shadow
    lit_img, got = lit.reshape(h, w), tr.lit_map()
    kernel = np.ones((3, 3), np.uint8)
    boundary = cv2.dilate(lit_img.astype(np.uint8), kernel) != cv2.erode(lit_img.astype(np.uint8), kernel)
    wrong = got != lit_img
    assert wrong.sum() <= 0.01 * w * h and not np.any(wrong & ~boundary)
    np.testing.assert_array_equal(tr.weight[:, 0] > 0, tr.lit)  # albedo > 0 everywhere
    # exact depth on the sphere and the plane (away from the silhouette)
    sil = cv2.dilate(on_sphere.reshape(h, w).astype(np.uint8), kernel) != cv2.erode(
        on_sphere.reshape(h, w).astype(np.uint8), kernel)
    ok = ~sil.ravel()
    np.testing.assert_allclose(tr.depth[ok], cam.to_device(x)[ok, 2], atol=1e-9)
    np.testing.assert_array_equal(tr.object_id[ok], np.where(on_sphere, 0, 1)[ok])


def test_projector_coordinates_equal_opencv_projection():
    proj = small_rig(0.5).projector
    p = trace._Projector.of(proj)
    rng = np.random.default_rng(1)
    x = np.stack([rng.uniform(-300, 300, 4000), rng.uniform(-200, 200, 4000), rng.uniform(-100, 200, 4000)])
    x = np.concatenate([x, [[0.0], [0.0], [-900.0]]], axis=1)  # behind the projector
    u, v = p.coordinates(x)
    ref = project_points(x.T, proj.K_array, proj.dist_array, proj.R_array, proj.T_array)
    ok = ~np.isnan(u)
    assert 0.2 < ok.mean() < 0.95 and np.isnan(u[-1])
    np.testing.assert_allclose(np.stack([u, v], 1)[ok], ref[ok], atol=1e-9)
    w, h = proj.size
    assert np.all((ref[~ok, 0] < -0.5) | (ref[~ok, 0] > w - 0.5) | (ref[~ok, 1] < -0.5)
                  | (ref[~ok, 1] > h - 0.5) | (np.arange(len(u))[~ok] == len(u) - 1))


def _coaxial(size_cam=(41, 41), size_proj=(64, 64), f_cam=1000.0, f_proj=500.0):
    def dev(name, size, f):
        K = [[f, 0, (size[0] - 1) / 2], [0, f, (size[1] - 1) / 2], [0, 0, 1]]
        return DeviceCalibration(name=name, K=K, dist=np.zeros(5), R=np.eye(3), T=np.zeros(3), size=size)
    return dev("cam", size_cam, f_cam), dev("proj", size_proj, f_proj)


def test_lens_rays_are_the_lens_bundle_unchanged():
    cam, proj = _coaxial()
    lens = AberratedLens(pupil_diameter_mm=20.0, focus_distance_mm=400.0, vignetting_shift_mm=30.0,
                         vignetting_radius_ratio=0.8, spherical_mm=6.0, coma_mm=3.0, samples=32)
    geom = Scene(objects=[PlaneObject(size_mm=(2000.0, 2000.0), albedo=0.5, pose=Pose(t=[0, 0, 600.0]))]
                 ).trace_geometry()
    pixels = np.array([0, 20, 40 * 41 + 3, 20 * 41 + 20, 41 * 41 - 1])
    tr = trace_camera(geom, cam, proj, lens, pixels=pixels)
    uv = np.stack([pixels % 41, pixels // 41], 1).astype(float)
    b = lens.bundle(pixel_to_normalized(uv, cam.K_array), uv)
    xy = hit_plane(b.origins, b.directions, 600.0)  # (n, K, 2) mm
    want_uv = xy / 600.0 * 500.0 + 31.5
    cos = 600.0 / np.sqrt(np.sum(xy**2, axis=-1) + 600.0**2)  # N = -z, L towards the origin
    want_w = b.weights * 0.5 * cos
    assert np.any(b.weights == 0) and np.any(b.weights > 0)  # vignetting cut some rays
    live = b.weights > 0
    np.testing.assert_allclose(tr.proj_uv[live], want_uv[live], atol=1e-3)
    np.testing.assert_allclose(tr.weight, want_w, rtol=1e-5, atol=1e-9)
    assert np.all(np.isnan(tr.proj_uv[~live]))
    np.testing.assert_allclose(tr.depth, 600.0, rtol=1e-12)
    np.testing.assert_allclose(tr.proj_chief, (uv - 20.0) / 1000.0 * 500.0 + 31.5, atol=1e-9)


def test_interpolated_normals_and_two_sided_shading():
    # one triangle in z = 100 with distinct vertex normals, camera rays along +z
    v = np.array([[-50.0, -50.0, 100.0], [50.0, -50.0, 100.0], [0.0, 50.0, 100.0]])
    vn = np.array([[0.0, 0.0, -1.0], [0.6, 0.0, -0.8], [0.0, -0.6, -0.8]])
    geom = TraceGeometry(v, np.array([[0, 1, 2]]), vn, np.array([0.5]), np.array([0]))
    cam, proj = _coaxial(f_cam=100.0)  # camera and projector centres at the origin
    pixels = np.array([22 * 41 + 20, 16 * 41 + 23])  # through (0, 2, 100) and (3, -4, 100)
    r = trace_camera(geom, cam, proj, PinholeLens(), pixels=pixels)
    uv = np.stack([pixels % 41, pixels // 41], 1).astype(float)
    xy = pixel_to_normalized(uv, cam.K_array)
    for i in range(2):
        x = r.depth[i] * np.array([xy[i, 0], xy[i, 1], 1.0])
        # barycentrics of x in the triangle, then the interpolated normal
        A = np.stack([v[1] - v[0], v[2] - v[0]], 1)[:2]
        bu, bv = np.linalg.solve(A, x[:2] - v[0, :2])
        n = (1 - bu - bv) * vn[0] + bu * vn[1] + bv * vn[2]
        n /= np.linalg.norm(n)
        L = -x / np.linalg.norm(x)
        assert r.weight[i, 0] == pytest.approx(0.5 * n @ L, rel=1e-6)
    # the camera behind the triangle (at z = 200, looking along -z), the projector in front of
    # it: dark
    behind = DeviceCalibration(name="behind", K=cam.K_array, dist=np.zeros(5),
                               R=np.diag([1.0, -1.0, -1.0]), T=[0.0, 0.0, 200.0], size=cam.size)
    r2 = trace_camera(geom, behind, proj, PinholeLens(), pixels=np.array([20 * 41 + 20]))
    assert r2.weight[0, 0] == 0.0 and not r2.lit[0] and r2.object_id[0] == 0


def test_threads_and_pixel_subsets_give_the_same_transport():
    rig = small_rig(0.05)
    geom = Scene(objects=[SphereObject(), PlaneObject(pose=Pose(t=[0, 0, 60.0]))]).trace_geometry()
    lens = AberratedLens(pupil_diameter_mm=8.0, focus_distance_mm=760.0, samples=5)
    a = trace_camera(geom, rig.cameras[1], rig.projector, lens, threads=1)
    b = trace_camera(geom, rig.cameras[1], rig.projector, lens, threads=2)
    np.testing.assert_array_equal(a.weight, b.weight)
    np.testing.assert_array_equal(a.proj_uv, b.proj_uv)
    assert a.rays == b.rays == 6 * a.depth.size
    sub = np.arange(0, a.depth.size, 7)
    c = trace_camera(geom, rig.cameras[1], rig.projector, lens, pixels=sub)
    np.testing.assert_array_equal(c.weight, a.weight[sub])
    dm = c.depth_map().ravel()
    np.testing.assert_array_equal(dm[sub], a.depth[sub])
    rest = np.setdiff1d(np.arange(a.depth.size), sub)
    assert np.all(np.isnan(dm[rest])) and np.all(c.object_map().ravel()[rest] == -1)
    assert not c.lit_map().ravel()[rest].any() and np.all(np.isnan(c.projector_map().reshape(-1, 2)[rest]))


def test_normalized_grid_matches_undistortion():
    cam = small_rig(0.03).cameras[0]
    grid = normalized_grid(cam)
    w, h = cam.size
    uv = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2).astype(float)
    np.testing.assert_allclose(grid, cam.normalized(uv), atol=1e-14)
    assert normalized_grid(cam) is grid
    assert normalized_grid(small_rig(0.03, distortion=False).cameras[0]) is None


@pytest.mark.parametrize("kw, match", [
    ({"faces": np.zeros((0, 3), int)}, r"needs vertices \(V, 3\) and faces \(F>0, 3\)"),
    ({"vertices": np.array([[0.0, 0, 0], [1, 0, 0], [0, np.inf, 0]])}, "vertices must be finite"),
    ({"faces": np.array([[0, 1, 3]])}, r"face indices must be in \[0, 3\)"),
    ({"face_albedo": np.zeros(2)}, "face_albedo must have 1 rows"),
])
def test_trace_geometry_rejects_bad_arrays(kw, match):
    args = {"vertices": np.eye(3), "faces": np.array([[0, 1, 2]]), "vertex_normals": np.eye(3),
                "face_albedo": np.ones(1), "face_object": np.zeros(1, int)}
    args.update(kw)
    with pytest.raises(ValueError, match=match):
        TraceGeometry(**args)


def test_trace_camera_rejects_bad_pixels():
    cam, proj = _coaxial()
    with pytest.raises(ValueError, match=r"pixels must be flat indices in \[0, 1681\) of camera 'cam'"):
        trace_camera(_plane_geometry(), cam, proj, PinholeLens(), pixels=np.array([1681]))


def test_camera_rays_are_the_rays_traced():
    rig = small_rig(0.03)
    lens = AberratedLens(pupil_diameter_mm=8.0, focus_distance_mm=760.0, samples=4,
                         vignetting_shift_mm=10.0, vignetting_radius_ratio=0.7)
    pix = np.arange(0, 123 * 65, 97)
    o, d = trace.camera_rays(rig.cameras[0], lens, pix)
    tr = trace_camera(Scene(objects=[SphereObject()]).trace_geometry(), rig.cameras[0], rig.projector,
                      lens, pixels=pix)
    cam = rig.cameras[0]
    uv = np.stack([pix % cam.width, pix // cam.width], 1).astype(float)
    live = lens.bundle(cam.normalized(uv), uv).weights > 0
    assert 0 < live.sum() < live.size  # vignetting removed some rays
    assert len(o) == len(d) == tr.rays == live.sum() + len(pix)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    # the last len(pix) rays are the chief rays: from the camera centre through the pixels
    np.testing.assert_allclose(o[-len(pix):], np.broadcast_to(cam.centre_world, (len(pix), 3)), atol=1e-9)
    np.testing.assert_allclose(d[-len(pix):], cam.pixel_rays(uv)[1], atol=1e-12)
