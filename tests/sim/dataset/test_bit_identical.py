"""The compiled per-pixel passes of ``sim.dataset.generate`` give the very bits of plain numpy
passes (an independent implementation of the same maths, written here), and samples keep
their pinned checksums: speed work may not change one value of a data set."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from test_dataset_run import CONFIG
from test_ground_truth import EXACT

from sim.dataset import generate as G
from sim.dataset.config import parse_config
from sim.dataset.randomise import config_rig, draw_scene
from sim.render.images import project_patterns, render_camera

TWO_PI = 2 * np.pi
F32 = np.float32

# sha256 of the scene and every array (``Sample.checksum``), from the numpy implementation
# these passes replaced (x86-64, numpy 2.4 with its OpenBLAS: BLAS sums M and D)
PINNED = {
    ("run", 0): "c9d634a8b09b70e168fcb8367c6986a9163a3035a9e235b0249ef4057613a4d3",
    ("run", 1): "3eccc37a8a1f685a7bc3979e8233f77c15fa4f2299a0331da186111e5426b8ae",
    ("run", 2): "4bae4014667153c43b94b060ee3bc0dc8a87edd928c1290d6d5de022a17e32da",
    ("run", 3): "fd0b3955a79f883d29d3bc8813f74719bcade2455792b44570f77bc304526286",
    ("exact", 0): "fe2a729da9bb2edb1c2c65941809f2de6b6a09180035b98d6077010ae7a5eb04",
    ("exact", 1): "ee4e4e3b01a8863112006ac48530ffe59ebdee8ecc64cacff702a49a36271fd5",
}


def _config(name: str):
    return parse_config(tomllib.loads(CONFIG) if name == "run" else EXACT)


@pytest.mark.parametrize(("name", "index"), sorted(PINNED))
def test_samples_keep_their_pinned_checksums(name, index):
    cfg = _config(name)
    sample = G.render_sample(draw_scene(cfg, config_rig(cfg), index))
    assert sample.checksum() == PINNED[name, index]


def test_a_later_sample_leaves_an_earlier_ones_arrays_alone():
    cfg = _config("run")
    rig = config_rig(cfg)
    first = G.render_sample(draw_scene(cfg, rig, 0))
    G.render_sample(draw_scene(cfg, rig, 1))  # reuses this thread's scratch buffers
    assert first.checksum() == PINNED["run", 0]


# ------------------------------------------------------------------ the numpy passes


def _noise_numpy(rad, camera, rng):
    rad = rad.astype(F32).reshape(-1)
    z = rng.standard_normal(rad.size, dtype=F32)
    e = np.maximum(rad * F32(camera.exposure_e), F32(0))
    shot = bool(camera.shot_noise)
    low = (e > 0) & (e < F32(G.POISSON_EXACT_BELOW_E)) if shot else np.zeros(e.shape, bool)
    r2 = F32(camera.read_noise_e**2)
    var = r2 + (e if shot else F32(0))
    e = np.minimum(e + np.sqrt(var) * z, F32(camera.full_well_e))
    dn = np.clip(e * F32(camera.dn_per_e) + F32(camera.black_level_dn), F32(0),
                 F32(camera.max_dn))
    idx = np.flatnonzero(low)
    el = rng.poisson(rad[idx] * F32(camera.exposure_e)).astype(F32) + np.sqrt(r2) * z[idx]
    el = np.minimum(el, F32(camera.full_well_e)) * F32(camera.dn_per_e) \
        + F32(camera.black_level_dn)
    dn[idx] = np.clip(el, F32(0), F32(camera.max_dn))
    return np.rint(dn).astype(np.uint8 if camera.bit_depth == 8 else np.uint16)


def _labels_numpy(rad, camera, groups):
    dn = (np.minimum(rad * F32(camera.exposure_e), F32(camera.full_well_e))
          * F32(camera.dn_per_e) + F32(camera.black_level_dn))
    out = {}
    for _, idx, n in groups:
        d = TWO_PI * np.arange(n) / n
        stack = dn[idx]
        m = np.tensordot(np.sin(d).astype(F32), stack, axes=1)
        c = np.tensordot(np.cos(d).astype(F32), stack, axes=1)
        ph = np.mod(np.arctan2(m, c), F32(TWO_PI))
        ph[ph >= F32(TWO_PI)] = 0
        for k, v in (("numerator", m), ("denominator", c), ("wrapped_phase", ph),
                     ("background", stack.mean(axis=0, dtype=F32)),
                     ("modulation", F32(2.0 / n) * np.hypot(m, c))):
            out.setdefault(k, []).append(v)
    return {k: np.stack(v) for k, v in out.items()}


def _normals_numpy(points, obj):
    def diff(axis):
        g, o = np.moveaxis(points, axis, 0), np.moveaxis(obj, axis, 0)
        fwd, bwd = np.full_like(g, np.nan), np.full_like(g, np.nan)
        same = (o[1:] == o[:-1]) & (o[1:] >= 0)
        d = np.where(same[..., None], g[1:] - g[:-1], np.nan)
        fwd[:-1], bwd[1:] = d, d
        c = 0.5 * (fwd + bwd)
        c = np.where(np.isnan(c), fwd, c)
        return np.moveaxis(np.where(np.isnan(c), bwd, c), 0, axis)

    n = np.cross(diff(1), diff(0))
    with np.errstate(invalid="ignore", divide="ignore"):
        n /= np.linalg.norm(n, axis=2, keepdims=True)
        flip = np.sum(n * points, axis=2) > 0
    n[flip] *= -1
    return n


def _same_bits(a, b) -> bool:
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("backdrop", [0.0, 1.0])  # most pixels dark, and most pixels hit
def test_compiled_passes_equal_the_numpy_passes_bit_for_bit(backdrop):
    cfg = parse_config({
        "seed": 3, "rig": {"builtin": {"camera_size_px": [160, 120], "camera_scale": 0.15}},
        "objects": {"size_mm": [60.0, 90.0]}, "placement": {"backdrop_probability": backdrop},
        "camera": {"shot_noise": True, "read_noise_e": [2.0, 8.0]},
        "patterns": [{"kind": "phase_shift", "steps": [4, 5],
                      "periods_px": [[2048.0, 128.0, 16.0]]}]})
    rig = config_rig(cfg)
    for index in range(2):
        scene = draw_scene(cfg, rig, index)
        geom = G.scene_geometry(scene.objects)
        projected = project_patterns(G.pattern_stack(scene), scene.projector)
        groups = G.phase_groups(scene)
        quiet = scene.camera.model_copy(update={"shot_noise": False, "read_noise_e": 0.0})
        for i, cam in enumerate(rig.cameras):
            res = render_camera(geom, rig, i, G.build_lens(scene.lenses[i], cam), projected,
                                quiet, None)
            hit = (res.object_id >= 0).mean()
            assert (hit > 0.5) == (backdrop == 1.0)
            seed = [*scene.noise_seed, i]
            assert _same_bits(G._noisy_images(res.radiance, scene.camera,
                                               np.random.default_rng(seed)),
                              _noise_numpy(res.radiance, scene.camera,
                                           np.random.default_rng(seed)).reshape(
                                  res.radiance.shape))
            arrays = G._camera_arrays(res, cam, scene, groups)
            for key, ref in _labels_numpy(res.radiance, scene.camera, groups).items():
                assert _same_bits(arrays[key], ref), key
            z = res.depth.astype(F32)[..., None]
            pts = np.concatenate([G._pixel_xy(cam).astype(F32) * z, z], axis=-1)
            assert _same_bits(arrays["normals"], _normals_numpy(pts, res.object_id))
            absph = TWO_PI * res.projector_map[..., 0] / min(p for p, _, _ in groups)
            order = np.where(np.isfinite(absph), np.floor(absph / TWO_PI), -1)
            inside = np.isfinite(res.projector_map[..., 0])
            mask = np.where(res.object_id < 0, 0, np.where(res.lit, 1, np.where(inside, 2, 3)))
            for key, ref in (("absolute_phase", absph.astype(F32)),
                             ("fringe_order", order.astype(np.int32)),
                             ("projector_uv", res.projector_map.astype(F32)),
                             ("depth_mm", res.depth.astype(F32)),
                             ("mask", mask.astype(np.uint8))):
                assert _same_bits(arrays[key], ref), key
