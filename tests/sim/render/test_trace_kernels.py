"""The compiled tracer (sim.render.trace_kernels) and the fast lens bundles against their definitions:
pixel coordinates, lens-ray geometry, chunking, and lenses whose samples differ per pixel."""

import numpy as np
import pytest

from sim.optics.lens import (
    AberratedLens,
    GaussianLens,
    PinholeLens,
    RayBundle,
    hit_plane,
    sunflower_disk,
)
from sim.optics.projection import pixel_to_normalized, project_points
from sim.optics.rig import DeviceCalibration, small_rig
from sim.render import trace
from sim.render.scene import PlaneObject, Pose, Scene, SphereObject
from sim.render.trace import trace_camera
from sim.render.trace_kernels import pixel_coordinates


def _device(name, size, f, skew=0.0):
    w, h = size
    K = [[f, skew, (w - 1) / 2 + 0.3], [0, 1.01 * f, (h - 1) / 2 - 0.2], [0, 0, 1]]
    return DeviceCalibration(name=name, K=K, dist=np.zeros(5), R=np.eye(3), T=np.zeros(3),
                             size=size)


@pytest.mark.parametrize("size", [(1923, 17), (65535, 65535)])
def test_pixel_coordinates_match_pixel_to_normalized(size):
    cam = _device("cam", size, 1500.0, skew=0.7)
    w, h = size
    rng = np.random.default_rng(3)
    pix = np.concatenate([[0, w - 1, w, w * h - 1, w * (h - 1)], rng.integers(0, w * h, 5000)])
    uv, xy = np.empty((len(pix), 2)), np.empty((len(pix), 2))
    pixel_coordinates(pix, trace._intrinsics(cam), uv, xy)
    np.testing.assert_array_equal(uv, np.stack([pix % w, pix // w], 1))  # exact, > 2^32 pixels too
    ref = pixel_to_normalized(uv, cam.K_array)
    np.testing.assert_allclose(xy, ref, rtol=1e-14, atol=1e-16)


def test_camera_rays_of_an_undistorted_pinhole_are_the_pixel_rays():
    cam = small_rig(0.03, distortion=False).cameras[0]
    pix = np.arange(0, cam.width * cam.height, 7)
    o, d = trace.camera_rays(cam, PinholeLens(), pix)
    uv = np.stack([pix % cam.width, pix // cam.width], 1).astype(float)
    ref_o, ref_d = cam.pixel_rays(uv)
    np.testing.assert_allclose(o, ref_o, atol=1e-9)
    np.testing.assert_allclose(d, ref_d, atol=1e-15)


def test_projector_coordinates_without_distortion_equal_the_projection():
    proj = _device("proj", (64, 48), 80.0, skew=0.5)
    p = trace._Projector.of(proj)
    rng = np.random.default_rng(2)
    x = np.stack([rng.uniform(-60, 60, 3000), rng.uniform(-40, 40, 3000),
                  rng.uniform(50, 100, 3000)])
    u, v = p.coordinates(x)
    ref = project_points(x.T, proj.K_array, None, proj.R_array, proj.T_array)
    ok = ~np.isnan(u)
    assert 0.2 < ok.mean() < 0.9
    np.testing.assert_allclose(np.stack([u, v], 1)[ok], ref[ok], atol=1e-9)
    assert np.all(np.any((ref[~ok] < -0.5) | (ref[~ok] > np.array([63.5, 47.5])), axis=1))


@pytest.mark.parametrize("lens", [
    AberratedLens(pupil_diameter_mm=8.0, focus_distance_mm=760.0, samples=5),
    AberratedLens(pupil_diameter_mm=8.0, focus_distance_mm=700.0, vignetting_shift_mm=40.0,
                  vignetting_radius_ratio=0.7, samples=6),
    PinholeLens(),
])
def test_chunking_does_not_change_the_transport(lens, monkeypatch):
    rig = small_rig(0.05)
    geom = Scene(objects=[SphereObject(), PlaneObject(pose=Pose(t=[0, 0, 60.0]))]).trace_geometry()
    whole = trace_camera(geom, rig.cameras[0], rig.projector, lens)  # chunks of > 1 shading block
    monkeypatch.setattr(trace, "CHUNK_RAYS", 700)  # many small chunks
    parts = trace_camera(geom, rig.cameras[0], rig.projector, lens, threads=2)
    assert whole.rays == parts.rays
    for name in ("proj_uv", "weight", "depth", "proj_chief", "lit", "object_id"):
        np.testing.assert_array_equal(getattr(parts, name), getattr(whole, name))
    assert np.any(whole.lit) and np.any(~whole.lit & (whole.object_id >= 0))  # lit and shadowed


class _OffsetLens:
    """A lens whose aperture samples move with the pixel (like a measured lens): sample k of
    a pixel starts at ``(k - 1, 0.01 u, 0)`` mm and aims at the in-focus point at 300 mm;
    sample 0 is blocked."""

    def bundle(self, xy_n, uv=None):
        n, k = len(xy_n), 3
        o = np.zeros((n, k, 3))
        o[..., 0] = np.arange(k) - 1.0
        o[..., 1] = 0.01 * uv[:, :1]
        aim = np.concatenate([xy_n * 300.0, np.full((n, 1), 300.0)], 1)[:, None, :]
        d = aim - o
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        w = np.tile([0.0, 0.25, 0.5], (n, 1))
        return RayBundle(o, d, w)


def test_lens_samples_that_differ_per_pixel_hit_where_the_bundle_says():
    f, size = 1000.0, (41, 41)
    K = [[f, 0, 20.0], [0, f, 20.0], [0, 0, 1]]
    cam = DeviceCalibration(name="cam", K=K, dist=np.zeros(5), R=np.eye(3), T=np.zeros(3),
                            size=size)
    proj = DeviceCalibration(name="proj", K=[[500.0, 0, 31.5], [0, 500.0, 31.5], [0, 0, 1]],
                             dist=np.zeros(5), R=np.eye(3), T=np.zeros(3), size=(64, 64))
    plane = PlaneObject(size_mm=(2000.0, 2000.0), albedo=0.5, pose=Pose(t=[0, 0, 600.0]))
    geom = Scene(objects=[plane]).trace_geometry()
    lens = _OffsetLens()
    pixels = np.array([0, 20, 40 * 41 + 3, 20 * 41 + 20, 41 * 41 - 1])
    tr = trace_camera(geom, cam, proj, lens, pixels=pixels)
    uv = np.stack([pixels % 41, pixels // 41], 1).astype(float)
    b = lens.bundle(pixel_to_normalized(uv, cam.K_array), uv)
    xy = hit_plane(b.origins, b.directions, 600.0)
    cos = 600.0 / np.sqrt(np.sum(xy**2, axis=-1) + 600.0**2)
    np.testing.assert_allclose(tr.proj_uv[:, 1:], (xy / 600.0 * 500.0 + 31.5)[:, 1:], atol=1e-3)
    np.testing.assert_allclose(tr.weight, b.weights * 0.5 * cos, rtol=1e-5, atol=1e-9)
    assert np.all(np.isnan(tr.proj_uv[:, 0])) and tr.rays == 3 * len(pixels)
    np.testing.assert_allclose(tr.depth, 600.0, rtol=1e-12)


@pytest.mark.parametrize("lens", [
    AberratedLens(pupil_diameter_mm=6.0, focus_distance_mm=500.0, spherical_mm=4.0, coma_mm=2.0,
                  samples=33),
    AberratedLens(pupil_diameter_mm=6.0, focus_distance_mm=500.0, vignetting_shift_mm=25.0,
                  samples=33),
])
def test_cached_pupil_rule_gives_the_bundle_of_fresh_samples(lens):
    xy = np.array([[0.0, 0.0], [0.12, -0.05], [-0.2, 0.1]])
    a = lens.bundle(xy)
    b = lens.bundle_from_pupil(xy, sunflower_disk(lens.samples))  # a copy: computed anew
    for name in ("origins", "directions", "weights"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not a.origins.flags.writeable and a.weights.flags.writeable
    np.testing.assert_allclose(np.linalg.norm(a.directions, axis=-1), 1.0, atol=1e-15)


def test_transmission_takes_shared_or_per_pixel_pupil_points():
    lens = AberratedLens(pupil_diameter_mm=8.0, focus_distance_mm=500.0, vignetting_shift_mm=20.0,
                         vignetting_radius_ratio=0.9, samples=50)
    xy = np.array([[0.0, 0.0], [0.1, 0.05]])
    pts = sunflower_disk(50) * 4.0
    shared = lens.transmission(xy, pts)
    np.testing.assert_array_equal(shared, lens.transmission(xy, np.broadcast_to(pts, (2, 50, 2))))
    centred = AberratedLens(pupil_diameter_mm=8.0, focus_distance_mm=500.0,
                            vignetting_radius_ratio=0.9, samples=50)
    inside = np.sum(pts**2, axis=1) <= 3.6**2
    np.testing.assert_array_equal(centred.transmission(xy, pts), np.tile(inside, (2, 1)))
    assert 0 < shared[1].sum() < shared[0].sum() == inside.sum()


def test_gaussian_and_pinhole_bundles_share_their_origins():
    xy = np.array([[0.02, -0.01], [0.3, 0.2]])
    g = GaussianLens(sigma_mm=1.5, focus_distance_mm=600.0, samples=7).bundle(xy)
    np.testing.assert_array_equal(g.origins[0], g.origins[1])
    hits = hit_plane(g.origins, g.directions, 600.0)
    np.testing.assert_allclose(hits, np.broadcast_to((xy * 600.0)[:, None], hits.shape), atol=1e-9)
    p = PinholeLens().bundle(xy)
    np.testing.assert_array_equal(p.origins, 0.0)
    np.testing.assert_allclose(p.directions[:, 0, :2] / p.directions[:, 0, 2:], xy, atol=1e-15)
