"""The data set's labels against known answers: the project's own decoder and triangulation
on noise-free float images, exact planes and spheres, and the Feng/Zuo label identities."""

from __future__ import annotations

import numpy as np
import pytest

from sim.dataset.config import parse_config
from sim.dataset.generate import MASK_NONE, MASK_OUTSIDE, MASK_SHADOWED, MASK_VALID, render_sample
from sim.dataset.randomise import check_fits, config_rig, draw_scene
from sim.fpp.decode import DecodeSettings, decode_view
from sim.fpp.stereo import camera_projector_cloud
from sim.render.fringe_patterns import GrayCodeSet

TWO_PI = 2 * np.pi

EXACT = {  # noise-free, unquantised, a pinhole: the images carry the geometry exactly
    "seed": 11,
    "rig": {"builtin": {"camera_size_px": [80, 64], "camera_scale": 0.1}},
    "objects": {"size_mm": [50.0, 80.0]},
    "camera": {"quantize": False, "exposure_e": [5000.0, 9000.0]},
    "projector": {"input_bits": None},
    "patterns": [{"kind": "phase_shift", "steps": [4, 5], "periods_px": [[2048.0, 128.0, 32.0]]},
                 {"kind": "gray_code", "steps": [4], "period_px": [32.0], "weight": 0.5}],
}


def _decode_and_triangulate(sample, cam_index: int):
    scene, arr = sample.scene, sample.cameras[cam_index]
    rig = scene.rig
    view = decode_view(arr["images"], scene.patterns, tuple(rig.projector.size),
                       DecodeSettings(min_modulation=1.0, min_modulation_fraction=0.0),
                       where="test")
    coord = view.coord["u"]
    ok = np.isfinite(coord) & (arr["mask"] == MASK_VALID)
    period = (scene.patterns.period_px if isinstance(scene.patterns, GrayCodeSet)
              else min(scene.patterns.periods_px))
    phase_err = TWO_PI * coord[ok] / period - arr["absolute_phase"][ok].astype(np.float64)
    pts, uv = camera_projector_cloud(np.where(ok, coord, np.nan), rig.cameras[cam_index],
                                     rig.projector, "u")
    z = rig.cameras[cam_index].to_device(pts)[:, 2]
    truth = arr["depth_mm"][uv[:, 1].astype(int), uv[:, 0].astype(int)].astype(np.float64)
    return ok, phase_err, z - truth


@pytest.mark.slow
def test_decoding_the_images_gives_the_truth_phase_and_depth_on_20_samples():
    cfg = parse_config(EXACT)
    rig = config_rig(cfg)
    check_fits(rig, cfg)
    worst_phase = worst_depth = 0.0
    pixels = 0
    for index in range(20):
        sample = render_sample(draw_scene(cfg, rig, index))
        for cam in range(2):
            ok, dphi, dz = _decode_and_triangulate(sample, cam)
            assert ok.sum() > 50, f"sample {index} camera {cam}: only {ok.sum()} valid pixels"
            worst_phase = max(worst_phase, float(np.abs(dphi).max()))
            worst_depth = max(worst_depth, float(np.abs(dz).max()))
            pixels += int(ok.sum())
    assert worst_phase < 0.01, worst_phase
    assert worst_depth < 0.005, worst_depth  # 5 um
    assert pixels > 20 * 2 * 200


def test_feng_zuo_labels_are_those_of_the_noise_free_images():
    cfg = parse_config(EXACT)
    rig = config_rig(cfg)
    sample = render_sample(draw_scene(cfg, rig, 0))
    scene, arr = sample.scene, sample.cameras[0]
    assert not isinstance(scene.patterns, GrayCodeSet)
    n = scene.patterns.steps
    imgs = arr["images"].astype(np.float64)  # noise-free float DN: the labels' images
    for f, _ in enumerate(scene.patterns.periods_px):
        stack = imgs[f * n:(f + 1) * n]
        d = TWO_PI * np.arange(n) / n
        m = np.tensordot(np.sin(d), stack, axes=1)
        c = np.tensordot(np.cos(d), stack, axes=1)
        np.testing.assert_allclose(arr["numerator"][f], m, atol=1e-3)
        np.testing.assert_allclose(arr["denominator"][f], c, atol=1e-3)
        np.testing.assert_allclose(arr["background"][f], stack.mean(axis=0), atol=1e-3)
        np.testing.assert_allclose(arr["modulation"][f], 2 / n * np.hypot(m, c), atol=1e-3)
        # I_k = A + B cos(phi - 2 pi k / N) back from the labels
        rebuilt = arr["background"][f] + arr["modulation"][f] * np.cos(
            arr["wrapped_phase"][f][None] - d[:, None, None])
        np.testing.assert_allclose(rebuilt, stack, atol=2e-2)
    # the fine wrapped phase equals the truth's where lit (pinhole, exact projector)
    valid = arr["mask"] == MASK_VALID
    fine = int(np.argmin(scene.patterns.periods_px))
    err = np.angle(np.exp(1j * (arr["wrapped_phase"][fine] - arr["absolute_phase"])))[valid]
    assert np.abs(err).max() < 0.01
    order = np.floor(arr["absolute_phase"] / TWO_PI)
    np.testing.assert_array_equal(arr["fringe_order"][valid], order[valid])


def test_mask_and_normals_on_a_sphere_before_a_plane():
    cfg = parse_config({**EXACT, "objects": {"families": {"sphere": 1.0}, "size_mm": [80, 80]},
                        "placement": {"backdrop_probability": 1.0,
                                      "backdrop_tilt_deg": [0.0, 0.0]}})
    rig = config_rig(cfg)
    sample = render_sample(draw_scene(cfg, rig, 2))
    scene, arr = sample.scene, sample.cameras[0]
    cam = rig.cameras[0]
    sphere, plane = scene.objects
    mask, normals, depth = arr["mask"], arr["normals"].astype(np.float64), arr["depth_mm"]
    assert {MASK_VALID, MASK_SHADOWED} <= set(np.unique(mask).tolist())
    assert np.all(np.isfinite(depth[mask != MASK_NONE])) and np.all(np.isnan(depth[mask == 0]))
    assert np.all(np.isfinite(arr["projector_uv"][(mask == MASK_VALID) | (mask == MASK_SHADOWED)]))
    assert np.all(np.isnan(arr["projector_uv"][mask == MASK_OUTSIDE]))
    # the backdrop's normal (its object z axis, facing the camera) in the camera frame
    n_plane = cam.R_array @ np.asarray(plane.pose.R)[:, 2]
    n_plane *= -np.sign(n_plane @ cam.to_device(np.asarray([plane.pose.t]))[0])
    # the sphere's normals: (X - c) / r, camera frame
    v, u = np.nonzero(mask != MASK_NONE)
    pts = cam.backproject(np.stack([u, v], 1).astype(float), depth[v, u])
    c = np.asarray(sphere.pose.t)
    on_sphere = np.abs(np.linalg.norm(pts - c, axis=1) - sphere.size_mm / 2) < 1e-3
    want = np.where(on_sphere[:, None], ((pts - c) / (sphere.size_mm / 2)) @ cam.R_array.T,
                    n_plane)
    got = normals[v, u]
    ok = np.all(np.isfinite(got), axis=1)
    assert ok.mean() > 0.8
    cos = np.sum(got[ok] * want[ok], axis=1)
    interior = np.percentile(cos, 50)
    assert interior > 0.9999  # exact on the plane; second order on the sphere
    assert np.mean(cos > 0.99) > 0.9  # the rest: pixels beside a silhouette


def test_a_defocused_lens_shows_the_phase_error_at_depth_edges():
    from scipy.ndimage import binary_dilation

    from sim.optics.lens import GaussianLens, PinholeLens

    cfg = parse_config({**EXACT, "objects": {"families": {"steps": 1.0}, "size_mm": [80, 80]},
                        "placement": {"backdrop_probability": 1.0, "backdrop_gap_mm": [40, 40]},
                        "patterns": [EXACT["patterns"][0]]})
    rig = config_rig(cfg)
    scene = draw_scene(cfg, rig, 1)
    errs = {}
    for name, lens in (("pinhole", PinholeLens()),
                       ("gaussian", GaussianLens(sigma_mm=2.0, focus_distance_mm=500.0,
                                                 samples=64))):
        s = render_sample(scene.model_copy(update={"lenses": [lens, lens]}))
        ok, dphi, _ = _decode_and_triangulate(s, 0)
        e = np.full(ok.shape, np.nan)
        e[ok] = dphi
        errs[name] = e
    pin, gau = errs["pinhole"], errs["gaussian"]
    both = np.isfinite(pin) & np.isfinite(gau)
    rms = {k: float(np.sqrt(np.mean(v[both] ** 2))) for k, v in errs.items()}
    assert rms["pinhole"] < 0.005 and rms["gaussian"] > 5 * rms["pinhole"], rms
    # the large errors sit where the blur mixes surfaces: within 3 px of a depth step or of
    # the edge of the valid region (silhouettes, shadows)
    s = render_sample(scene)
    depth = s.cameras[0]["depth_mm"].astype(np.float64)
    valid = s.cameras[0]["mask"] == MASK_VALID
    edge = binary_dilation(~valid) & valid
    for ax in (0, 1):
        d = np.abs(np.diff(np.nan_to_num(depth, nan=1e4), axis=ax)) > 2.0
        edge[tuple(slice(None, -1) if a == ax else slice(None) for a in (0, 1))] |= d
    near = binary_dilation(edge, iterations=3)
    big = both & (np.abs(gau) > 0.05)
    assert big.sum() > 20 and np.all(near[big])
