"""sim.render.images and ``ltc render``: projector and camera response, gather, blur disk, writers, CLI."""

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import zarr

from sim.render.fringe_patterns import PhaseShiftSet
from sim.optics.lens import AberratedLens, PinholeLens
from sim.render.pattern_stack import ALONG_U, ALONG_V, FULL, PatternStack
from sim.fpp.phase import wrapped_phase
from sim.render.images import (
    CameraResponse,
    ProjectorResponse,
    RenderSettings,
    camera_response,
    gather,
    gather_into,
    project_patterns,
    render,
    render_camera,
    render_views,
    write_png,
    write_zarr,
)
from sim.optics.rig import DeviceCalibration, small_rig
from sim.render.scene import PlaneObject, Pose, Scene, SphereObject
from sim.render.trace import trace_camera
from station.cli import main

EXAMPLE = Path(__file__).resolve().parents[3] / "examples" / "sphere_scene.toml"
EXACT = RenderSettings(projector=ProjectorResponse(input_bits=None),
                       camera=CameraResponse(exposure_e=10000.0, bit_depth=16, quantize=False))


def _device(name, size, f):
    K = [[f, 0, (size[0] - 1) / 2], [0, f, (size[1] - 1) / 2], [0, 0, 1]]
    return DeviceCalibration(name=name, K=K, dist=np.zeros(5), R=np.eye(3), T=np.zeros(3), size=size)


def _plane(z=600.0, albedo=1.0):
    return Scene(objects=[PlaneObject(size_mm=(3000.0, 3000.0), albedo=albedo, pose=Pose(t=[0, 0, z]))]
                 ).trace_geometry()


def test_projector_response():
    p = np.array([[[0.0, 0.301, 0.5, 1.0]]], np.float32)
    out = project_patterns(p, ProjectorResponse(input_bits=None, gamma=2.2, black_level=0.1)).images()
    np.testing.assert_allclose(out, 0.1 + 0.9 * p.astype(np.float64) ** 2.2, rtol=1e-6)
    q = project_patterns(p, ProjectorResponse(input_bits=8)).images()
    np.testing.assert_allclose(q, [[[0.0, 77 / 255, 128 / 255, 1.0]]], rtol=1e-6)
    dot = np.zeros((1, 41, 41), np.float32)
    dot[0, 20, 20] = 1.0
    b = project_patterns(dot, ProjectorResponse(input_bits=None, defocus_sigma_px=1.5)).images()[0]
    x = np.arange(41) - 20
    assert b.sum() == pytest.approx(1.0, rel=1e-5)
    assert (b.sum(0) * x**2).sum() == pytest.approx(1.5**2, rel=0.01)  # variance along u
    with pytest.raises(ValueError, match=r"pattern images must be \(n, H, W\)"):
        project_patterns(np.zeros((4, 4)), ProjectorResponse())
    with pytest.raises(ValueError, match=r"pattern values must lie in \[0, 1\], got \[1.5, 1.5\]"):
        project_patterns(np.full((1, 2, 2), 1.5), ProjectorResponse())
    nan = np.zeros((2, 2, 3), np.float32)
    nan[1, 1, 1] = np.nan
    with pytest.raises(ValueError, match=r"pattern values must lie in \[0, 1\], got \[nan, nan\]"):
        project_patterns(nan, ProjectorResponse())


@pytest.mark.parametrize("projector", [
    ProjectorResponse(input_bits=8, gamma=2.2, black_level=0.05),
    ProjectorResponse(input_bits=None, defocus_sigma_px=1.3),
    ProjectorResponse(input_bits=10, gamma=1.8, defocus_sigma_px=0.7),
])
def test_projector_response_of_profiles_equals_that_of_full_images(projector):
    """Fringes kept as row or column profiles are projected to the same light as the full
    images (the blur of a constant axis, edges replicated, changes nothing)."""
    wp, hp = 40, 23
    fringes = PhaseShiftSet(periods_px=[7.0, 40.0], steps=3, direction="both").images((wp, hp))
    rng = np.random.default_rng(5)
    pats = np.concatenate([fringes, rng.random((2, hp, wp)).astype(np.float32)])
    stack = project_patterns(pats, projector)
    assert list(stack.form) == [ALONG_U] * 6 + [ALONG_V] * 6 + [FULL] * 2
    forced = PatternStack((wp, hp), np.full(len(pats), FULL, np.int8), np.arange(len(pats)),
                          pats, np.zeros((0, wp), np.float32), np.zeros((0, hp), np.float32))
    np.testing.assert_allclose(stack.images(), project_patterns(forced, projector).images(),
                               rtol=0, atol=2e-7)


def test_gather_reproduces_linear_patterns():
    rig = small_rig(0.05, distortion=True)
    cam, proj = rig.cameras[0], rig.projector
    geom = Scene(objects=[PlaneObject(size_mm=(3000.0, 3000.0), pose=Pose(t=[0, 0, 30.0]))]).trace_geometry()
    tr = trace_camera(geom, cam, proj, PinholeLens())
    pw, ph = proj.size
    u, v = np.meshgrid(np.arange(pw, dtype=np.float32), np.arange(ph, dtype=np.float32))
    pats = np.stack([u / (pw - 1), v / (ph - 1), np.ones_like(u)])
    rad = gather(tr, pats).T
    uv = tr.proj_uv[:, 0].astype(np.float64)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] <= pw - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= ph - 1) & (rad[:, 2] > 0)
    assert ok.sum() > 1000
    np.testing.assert_allclose(rad[ok, 2], tr.weight[ok, 0], rtol=1e-6)
    np.testing.assert_allclose(rad[ok, 0] / rad[ok, 2], uv[ok, 0] / (pw - 1), atol=1e-5)
    np.testing.assert_allclose(rad[ok, 1] / rad[ok, 2], uv[ok, 1] / (ph - 1), atol=1e-5)
    with pytest.raises(ValueError, match=r"pattern images must be \(n, H, W\), got shape \(12, 1\)"):
        gather(tr, np.zeros((12, 1), np.float32))
    with pytest.raises(ValueError, match=r"projected patterns are 5 x 4 px, expected the transport's "
                                         r"96 x 54 projector"):
        gather(tr, np.zeros((3, 4, 5), np.float32))
    n_px = tr.camera_size[0] * tr.camera_size[1]
    with pytest.raises(ValueError, match=rf"gather_into out: expected a C-contiguous float32 \(3, {n_px}\) "
                                         rf"array, got float64 \(3, {n_px}\)"):
        gather_into(tr, pats, np.zeros((3, n_px)))


def _bilinear_reference(img, u, v):
    """Bilinear sample of img (H, W) at (u, v), float64, pixel centres at integers, taps clamped."""
    h, w = img.shape
    iu, iv = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - iu, v - iv
    a, b = np.clip(iu, 0, w - 1), np.clip(iu + 1, 0, w - 1)
    c, d = np.clip(iv, 0, h - 1), np.clip(iv + 1, 0, h - 1)
    return ((1 - fu) * (1 - fv) * img[c, a] + fu * (1 - fv) * img[c, b]
            + (1 - fu) * fv * img[d, a] + fu * fv * img[d, b])


def _patterns(kind, rng, npat, hp, wp):
    """Random pattern images varying along u only, v only, both, or a mix of all three."""
    full = rng.random((npat, hp, wp))
    u = np.broadcast_to(rng.random((npat, 1, wp)), full.shape)
    v = np.broadcast_to(rng.random((npat, hp, 1)), full.shape)
    mix = np.concatenate([u[:2], v[:2], full[:2]])
    return {"full": full, "u": u, "v": v, "mix": mix}[kind].astype(np.float32)


@pytest.mark.parametrize("threads, kind, k, order", [
    (1, "full", 5, "any"), (3, "full", 5, "any"), (1, "u", 5, "any"), (3, "v", 5, "any"),
    (3, "mix", 5, "any"), (1, "mix", 1, "any"), (3, "mix", 1, "any"), (3, "mix", 1, "run"),
    (1, "full", 1, "run")])
def test_gather_is_the_weighted_bilinear_sum_of_every_ray(threads, kind, k, order):
    """Several rays per pixel (or one), rays of weight 0 with NaN coordinates, taps off every
    edge, pixels in any order (or one run of consecutive pixels), written in place, patterns
    kept as row or column profiles or full images: against a float64 bilinear reference on the
    full images."""
    from sim.render.trace import Transport

    rng = np.random.default_rng(3)
    wp, hp, n, npat = 13, 7, 500, 6
    uv = np.stack([rng.uniform(-2, wp + 1, (n, k)), rng.uniform(-2, hp + 1, (n, k))], -1)
    weight = rng.uniform(0, 1, (n, k))
    weight[rng.random((n, k)) < 0.3] = 0.0
    uv[weight == 0] = np.nan
    pixels = rng.permutation(40 * 30)[:n] if order == "any" else np.arange(333, 333 + n)
    tr = Transport((40, 30), (wp, hp), pixels, uv.astype(np.float32), weight.astype(np.float32),
                   np.zeros(n), np.zeros((n, 2)), np.ones(n, bool), np.zeros(n, np.int32))
    pats = _patterns(kind, rng, npat, hp, wp)
    assert list(PatternStack.from_images(pats).form) == {
        "full": [FULL] * 6, "u": [ALONG_U] * 6, "v": [ALONG_V] * 6,
        "mix": [ALONG_U] * 2 + [ALONG_V] * 2 + [FULL] * 2}[kind]
    u32, v32 = (np.nan_to_num(uv[..., i].astype(np.float32)).astype(float) for i in (0, 1))
    ref = np.stack([np.sum(weight.astype(np.float32) * _bilinear_reference(p.astype(float), u32, v32),
                           axis=1) for p in pats])
    np.testing.assert_allclose(gather(tr, pats, threads=threads), ref, rtol=2e-6, atol=1e-6)
    out = np.full((npat, 40 * 30), -1.0, np.float32)
    gather_into(tr, pats, out, threads=threads)
    np.testing.assert_allclose(out[:, pixels], ref, rtol=2e-6, atol=1e-6)
    untouched = np.setdiff1d(np.arange(40 * 30), pixels)
    assert np.all(out[:, untouched] == -1.0)


@pytest.mark.parametrize("bits, quantize", [(8, True), (12, True), (16, False)])
def test_noise_free_render_is_the_camera_response_of_the_gathered_radiance(bits, quantize):
    """The fused gather-and-digitise path equals gather then camera_response, value for value,
    on a whole frame and on a subset of pixels (the others get the response to radiance 0)."""
    rig = small_rig(0.05)
    geom = Scene(objects=[SphereObject(), PlaneObject(pose=Pose(t=[0, 0, 60.0]))]).trace_geometry()
    settings = RenderSettings(camera=CameraResponse(exposure_e=9000.0, bit_depth=bits,
                                                    black_level_dn=2.0, quantize=quantize))
    pats = PhaseShiftSet(periods_px=[16.0], steps=3).images(rig.projector.size)
    cam = rig.cameras[0]
    w, h = cam.size
    for pix in (None, np.arange(0, w * h, 3)):
        tr = trace_camera(geom, cam, rig.projector, PinholeLens(), pixels=pix)
        rad = np.zeros((len(pats), w * h), np.float32)
        rad[:, tr.pixels] = gather(tr, project_patterns(pats, settings.projector))
        want = camera_response(rad.reshape(-1, h, w), settings.camera)
        got = render(tr, pats, settings)
        assert got.dtype == want.dtype and got.shape == want.shape == (3, h, w)
        np.testing.assert_array_equal(got, want)
    assert len(np.unique(got)) > 20


def test_rendered_fringes_decode_to_the_true_projector_coordinate():
    rig = small_rig(0.05)
    geom = Scene(objects=[SphereObject(), PlaneObject(pose=Pose(t=[0, 0, 60.0]))]).trace_geometry()
    tr = trace_camera(geom, rig.cameras[1], rig.projector, PinholeLens())
    ps = PhaseShiftSet(periods_px=[16.0], steps=4)
    imgs = render(tr, ps.images(rig.projector.size), EXACT)
    assert imgs.shape == (4, 108, 205) and imgs.dtype == np.float32
    lit = tr.lit_map()
    truth = tr.projector_map()[..., 0]
    inner = lit & (truth > 0) & (truth < rig.projector.size[0] - 1)
    assert inner.sum() > 2000
    phase = wrapped_phase(imgs).phase
    err = np.angle(np.exp(1j * (phase - 2 * np.pi * truth / 16.0)))[inner] * 16.0 / (2 * np.pi)
    assert np.abs(err).max() < 0.01  # projector px; bilinear interpolation of the fringes
    assert np.all(imgs[:, ~lit] == 0)


@pytest.mark.parametrize("z", [300.0, 600.0])
def test_thin_lens_blur_disk_matches_geometry(z):
    """One bright projector pixel on a plane in front of or behind the focus at 400 mm."""
    cam, proj = _device("cam", (45, 45), 1000.0), _device("proj", (64, 64), 500.0)
    lens = AberratedLens(pupil_diameter_mm=20.0, focus_distance_mm=400.0, samples=64)
    tr = trace_camera(_plane(z), cam, proj, lens)
    dot = np.zeros((1, 64, 64), np.float32)
    dot[0, 32, 32] = 1.0
    img = gather(tr, project_patterns(dot, EXACT.projector))[0].reshape(45, 45)
    assert img[0].max() == img[-1].max() == img[:, 0].max() == img[:, -1].max() == 0  # all inside
    y, x = np.mgrid[:45, :45]
    m = img.sum()
    cx, cy = (img * x).sum() / m, (img * y).sum() / m
    r2 = (img * ((x - cx) ** 2 + (y - cy) ** 2)).sum() / m
    # the bright pixel is a bilinear tent of half-width one projector pixel = 2 camera pixels
    # (coaxial, f 500 vs 1000 px): variance 2^2 / 6 per axis; a uniform disk of radius R has
    # <r^2> = R^2 / 2 (and so has the Vogel-spiral aperture sampling, exactly)
    diameter = 2 * np.sqrt(2 * (r2 - 2 * 2.0**2 / 6))
    expected = 20.0 * abs(z - 400.0) / 400.0 * 1000.0 / z  # mm in object space -> px at depth z
    assert diameter == pytest.approx(expected, rel=0.02)


def test_camera_response_exact_chain():
    rad = np.array([0.0, 0.5, 2.0, -0.1])
    cam8 = CameraResponse(exposure_e=8000.0, full_well_e=10000.0)
    np.testing.assert_array_equal(camera_response(rad, cam8), np.array([0, 102, 255, 0], np.uint8))
    cam12 = CameraResponse(exposure_e=8000.0, bit_depth=12, black_level_dn=10.0, gain=0.5)
    out = camera_response(rad, cam12)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, [10, round(4000 * 0.5 * 4095 / 10000 + 10), 2058, 10])


def test_camera_response_matches_the_float32_chain_rounding_half_to_even():
    rad = np.concatenate([np.linspace(-0.2, 1.3, 100_001), np.arange(0, 256) / 204.0,
                          np.array([0.5 / 204, 2.5 / 204, np.inf])]).astype(np.float32)
    for cam in (CameraResponse(exposure_e=8160.0, full_well_e=10000.0, gain=1.25),
                CameraResponse(exposure_e=5000.0, bit_depth=12, black_level_dn=3.5),
                CameraResponse(exposure_e=5000.0, bit_depth=16, quantize=False)):
        e = np.minimum(np.maximum(rad * np.float32(cam.exposure_e), np.float32(0)),
                       np.float32(cam.full_well_e))
        dn = np.clip(e * np.float32(cam.dn_per_e) + np.float32(cam.black_level_dn), 0, cam.max_dn)
        want = np.rint(dn).astype(np.uint8 if cam.bit_depth == 8 else np.uint16) if cam.quantize else dn
        got = camera_response(rad.reshape(3, -1), cam, threads=2)
        assert got.dtype == want.dtype and got.shape == (3, len(rad) // 3)
        np.testing.assert_array_equal(got.reshape(-1), want)


def test_camera_noise_statistics():
    cam = CameraResponse(exposure_e=10000.0, full_well_e=20000.0, bit_depth=16, quantize=False,
                         shot_noise=True, read_noise_e=20.0)
    rng = np.random.default_rng(7)
    dn = camera_response(np.full(400_000, 0.25), cam, rng).astype(np.float64)
    k = cam.dn_per_e
    assert dn.mean() == pytest.approx(2500 * k, rel=2e-3)
    assert dn.var() == pytest.approx((2500 + 20.0**2) * k**2, rel=0.02)
    with pytest.raises(ValueError, match="rng is required when shot_noise or read_noise_e is on"):
        camera_response(np.zeros(3), cam)


@pytest.mark.parametrize("bits, dtype, top", [(8, np.uint8, 255), (12, np.uint16, 4095), (16, np.uint16, 65535)])
def test_png_round_trip(tmp_path, bits, dtype, top):
    img = (np.arange(12 * 7).reshape(7, 12) * (top // 83)).astype(dtype)
    img[0, 0] = top
    write_png(tmp_path / "a.png", img, bits)
    back = cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED)
    assert back.dtype == dtype
    np.testing.assert_array_equal(back, img)


def test_png_errors(tmp_path):
    with pytest.raises(ValueError, match="bit_depth must be 8, 12 or 16, got 10"):
        write_png(tmp_path / "a.png", np.zeros((2, 2), np.uint16), 10)
    with pytest.raises(ValueError, match=r"expected a 2-D uint16 image with values < 2\^12"):
        write_png(tmp_path / "a.png", np.full((2, 2), 5000, np.uint16), 12)
    with pytest.raises(ValueError, match=r"expected a 2-D uint8 image"):
        write_png(tmp_path / "a.png", np.zeros((2, 2), np.uint16), 8)
    with pytest.raises(FileNotFoundError) as info:  # Python's own error, naming the file
        write_png(tmp_path / "no_dir" / "a.png", np.zeros((2, 2), np.uint8), 8)
    assert info.value.filename == str(tmp_path / "no_dir" / "a.png")


def _small_views(**kw):
    rig = small_rig(0.03)
    geom = Scene(objects=[SphereObject(), PlaneObject(pose=Pose(t=[0, 0, 60.0]))]).trace_geometry()
    pats = PhaseShiftSet(periods_px=[8.0], steps=3).images(rig.projector.size)
    return rig, geom, pats, render_views(geom, rig, [PinholeLens(), PinholeLens()], pats, RenderSettings(),
                                         **kw)


def test_render_views_and_zarr_round_trip(tmp_path):
    rig, geom, pats, res = _small_views()
    assert [c.name for c in res.cameras] == ["left", "right"]
    for c, cam in zip(res.cameras, rig.cameras):
        tr = trace_camera(geom, cam, rig.projector, PinholeLens())
        np.testing.assert_array_equal(c.images, render(tr, pats, RenderSettings()))
        np.testing.assert_array_equal(c.depth, tr.depth_map())
        assert c.n_rays == cam.width * cam.height and set(c.timings) == {"trace_s", "gather_s", "response_s"}
    write_zarr(tmp_path / "r.zarr", res, {"note": "x"}, radiance=True)
    root = zarr.open_group(str(tmp_path / "r.zarr"), mode="r")
    assert root.attrs["note"] == "x" and root["camera_1"].attrs["name"] == "right"
    c = res.cameras[1]
    for key in ("images", "radiance", "depth", "projector_map", "lit", "object_id"):
        np.testing.assert_array_equal(root[f"camera_1/{key}"][...], getattr(c, key))


def test_render_views_errors():
    rig, geom, pats, _ = _small_views()
    with pytest.raises(ValueError, match="scene: 1 lenses for 2 cameras"):
        render_views(geom, rig, [PinholeLens()], pats, RenderSettings())
    with pytest.raises(ValueError, match=r"scene: pattern images are 5 x 5 px, the projector is 58 x 32"):
        render_views(geom, rig, [PinholeLens()] * 2, np.zeros((3, 5, 5)), RenderSettings())


def test_render_camera_into_an_earlier_result_overwrites_every_field():
    """A render into an earlier result (another scene, other patterns) equals a fresh render,
    field for field, in the earlier result's own memory."""
    rig, geom, pats, _ = _small_views()
    other = Scene(objects=[PlaneObject(pose=Pose(t=[5.0, 0, 45.0]))]).trace_geometry()
    cam = CameraResponse(shot_noise=True, read_noise_e=3.0)
    proj = project_patterns(pats, ProjectorResponse())
    first = render_camera(geom, rig, 1, PinholeLens(), proj, cam, np.random.default_rng(1))
    held = {key: getattr(first, key) for key in ("images", "radiance", "depth", "projector_map",
                                                  "lit", "object_id")}
    proj2 = project_patterns(pats[::-1].copy(), ProjectorResponse())
    lens = AberratedLens(pupil_diameter_mm=4.0, focus_distance_mm=600.0, samples=5)
    fresh = render_camera(other, rig, 1, lens, proj2, cam, np.random.default_rng(2))
    again = render_camera(other, rig, 1, lens, proj2, cam, np.random.default_rng(2), out=first)
    assert again is first and again.n_rays == fresh.n_rays
    for key, arr in held.items():
        assert getattr(again, key) is arr
        np.testing.assert_array_equal(arr, getattr(fresh, key), err_msg=key)
    assert not np.array_equal(held["depth"], render_camera(geom, rig, 1, PinholeLens(), proj, cam,
                                                           np.random.default_rng(1)).depth)


def test_render_camera_rejects_an_out_of_another_shape():
    rig, geom, pats, _ = _small_views()
    proj = project_patterns(pats, ProjectorResponse())
    res = render_camera(geom, rig, 0, PinholeLens(), proj, CameraResponse(), None)
    with pytest.raises(ValueError, match=r"field 'images' of camera 'left': expected a C-contiguous "
                                         r"uint8 \(2, 65, 123\) array, got uint8 \(3, 65, 123\)"):
        render_camera(geom, rig, 0, PinholeLens(), project_patterns(pats[:2], ProjectorResponse()),
                      CameraResponse(), None, out=res)
    with pytest.raises(ValueError, match=r"field 'images' .* expected a C-contiguous uint16"):
        render_camera(geom, rig, 0, PinholeLens(), proj, CameraResponse(bit_depth=12), None, out=res)
    with pytest.raises(ValueError, match=r"holds camera 'left', not 'right'"):
        render_camera(geom, rig, 1, PinholeLens(), proj, CameraResponse(), None, out=res)
    with pytest.raises(ValueError, match=r"camera_response out: expected a C-contiguous float32 "
                                         r"\(2, 3\) array, got float32 \(3, 2\)"):
        camera_response(np.zeros((2, 3)), CameraResponse(quantize=False),
                        out=np.zeros((2, 3), np.float32).T)


def test_cli_renders_the_example(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["render", str(EXAMPLE), "--out", str(out), "--json", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary == json.loads((out / "summary.json").read_text())
    assert summary["images"] == 12 and summary["bit_depth"] == 12
    root = zarr.open_group(str(out / "render.zarr"), mode="r")
    assert len(root.attrs["patterns"]) == 12
    for i, cam in enumerate(summary["cameras"]):
        pngs = sorted((out / f"camera_{i}").glob("pattern_*.png"))
        assert len(pngs) == 12
        img = cv2.imread(str(pngs[0]), cv2.IMREAD_UNCHANGED)
        assert img.dtype == np.uint16 and 0 < img.max() <= 4095
        np.testing.assert_array_equal(img, root[f"camera_{i}/images"][0])
        depth = root[f"camera_{i}/depth"][...]
        assert np.nanmin(depth) == pytest.approx(cam["depth_mm"][0])
        assert 0.1 < cam["lit_fraction"] < cam["seen_fraction"] <= 1


def test_cli_reports_bad_scenes(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('rig = "missing.yaml"\n')
    assert main(["render", str(bad), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "ltc render: error:" in err and "bad.toml" in err and not (tmp_path / "o").exists()


def test_render_camera_from_a_kept_transport_equals_full_renders_without_tracing(monkeypatch):
    """Trace once, render many: pattern sets rendered from one kept transport equal full renders
    bit for bit, and rendering from it traces nothing."""
    import sim.render.images as images

    monkeypatch.setattr(images, "TILE_RAYS", 3000)  # several tiles
    rig, geom, pats, _ = _small_views()
    cam = CameraResponse(shot_noise=True, read_noise_e=3.0)
    lens = AberratedLens(pupil_diameter_mm=4.0, focus_distance_mm=600.0, samples=5)
    proj_a = project_patterns(pats, ProjectorResponse())
    proj_b = project_patterns(pats[::-1].copy(), ProjectorResponse())
    full_a = render_camera(geom, rig, 1, lens, proj_a, cam, np.random.default_rng(1))
    full_b = render_camera(geom, rig, 1, lens, proj_b, cam, np.random.default_rng(2))
    kept = render_camera(geom, rig, 1, lens, proj_a, cam, np.random.default_rng(1),
                         keep_transport=True)
    assert full_a.transport is None and len(kept.transport) > 1

    def no_tracing(*args, **kwargs):
        raise AssertionError("render_camera traced although it was given the transport")

    monkeypatch.setattr(images, "trace_camera", no_tracing)
    again_a = render_camera(geom, rig, 1, lens, proj_a, cam, np.random.default_rng(1),
                            transport=kept.transport)
    again_b = render_camera(geom, rig, 1, lens, proj_b, cam, np.random.default_rng(2),
                            transport=kept.transport)
    assert again_b.transport is kept.transport and again_b.timings["trace_s"] == 0.0
    for full, res in ((full_a, kept), (full_a, again_a), (full_b, again_b)):
        assert res.n_rays == full.n_rays
        for key in ("images", "radiance", "depth", "projector_map", "lit", "object_id"):
            np.testing.assert_array_equal(getattr(res, key), getattr(full, key), err_msg=key)
    with pytest.raises(ValueError, match=r"cover each pixel of camera 'right' once \(\d+ missing"):
        render_camera(geom, rig, 1, lens, proj_a, cam, np.random.default_rng(1),
                      transport=kept.transport[1:])
    other = dataclasses.replace(kept.transport[0], camera_size=(7, 5))
    with pytest.raises(ValueError, match=r"render_camera transport: it is of a \(7, 5\) camera"):
        render_camera(geom, rig, 1, lens, proj_a, cam, np.random.default_rng(1),
                      transport=(other, *kept.transport[1:]))


def test_pixels_no_lens_ray_reaches_are_not_traced_and_the_images_are_unchanged(monkeypatch):
    """A defocused sphere alone in view: only the pixels within the lens's blur reach of its
    silhouette are traced with the lens; the images, truth maps and a render from the kept
    transport equal a full trace's bit for bit, and the blur halo beyond the silhouette is
    inside the traced region."""
    import sim.render.images as images

    rig = small_rig(0.03)
    geom = Scene(objects=[SphereObject()]).trace_geometry()
    pats = PhaseShiftSet(periods_px=[8.0], steps=3).images(rig.projector.size)
    proj = project_patterns(pats, ProjectorResponse())
    cam = CameraResponse(quantize=False)
    lens = AberratedLens(pupil_diameter_mm=40.0, focus_distance_mm=300.0, samples=64,
                         vignetting_shift_mm=20.0, spherical_mm=8.0)
    masked = render_camera(geom, rig, 0, lens, proj, cam, None, keep_transport=True)
    with monkeypatch.context() as m:
        m.setattr(images, "_pixels_to_trace", lambda *a: (None, None))
        full = render_camera(geom, rig, 0, lens, proj, cam, None)
    for key in ("images", "radiance", "depth", "projector_map", "lit", "object_id"):
        np.testing.assert_array_equal(getattr(masked, key), getattr(full, key), err_msg=key)
    again = render_camera(geom, rig, 0, lens, proj, cam, None, transport=masked.transport)
    np.testing.assert_array_equal(again.radiance, full.radiance)
    w, h = rig.cameras[0].size
    dark = masked.transport[0]
    assert dark.weight.shape[1] == 1 and 0 < len(dark.pixels) < w * h  # the chief pass's
    halo = (full.radiance.max(axis=0) > 0) & (full.object_id < 0)
    assert halo.sum() > 50  # light beyond the silhouette: the blur the region must hold
    assert not np.isin(np.flatnonzero(halo), dark.pixels).any()
