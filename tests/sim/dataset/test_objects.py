"""Procedural objects, placement in the working volume and drawn lenses: known answers."""

from __future__ import annotations

import numpy as np
import pytest

from sim.dataset.config import FAMILIES, parse_config
from sim.dataset.generate import build_lens, object_parts
from sim.dataset.objects import procedural
from sim.dataset.randomise import MeasuredLensDraw, config_rig, draw_scene, place


@pytest.mark.parametrize("family", FAMILIES)
def test_every_family_is_normalised_to_its_bounding_sphere_and_repeatable(family):
    a = procedural(family, [3, 7, 11], 90.0)
    b = procedural(family, [3, 7, 11], 90.0)
    v = np.concatenate([m.vertices for m in a.meshes])
    r = np.linalg.norm(v, axis=1).max()
    if len(a.spheres):  # exact spheres reach the bounding sphere, their icospheres inside it
        r = max(r, float((np.linalg.norm(a.spheres[:, :3], axis=1) + a.spheres[:, 3]).max()))
    assert abs(r - 45.0) < 1e-9
    for m, n in zip(a.meshes, b.meshes, strict=True):
        np.testing.assert_array_equal(m.vertices, n.vertices)
        np.testing.assert_array_equal(m.faces, n.faces)
    assert np.all(np.isfinite(v)) and sum(len(m.faces) for m in a.meshes) > 1


def test_every_placed_object_is_inside_every_view():
    cfg = parse_config({"rig": {"builtin": {"camera_size_px": [64, 48], "camera_scale": 0.08}},
                        "objects": {"size_mm": [50.0, 80.0]}})
    rig = config_rig(cfg)
    for i in range(10):
        scene = draw_scene(cfg, rig, i)
        obj = scene.objects[0]
        parts = object_parts(obj)
        v = np.concatenate([m.vertices for m in parts.meshes]) @ np.asarray(obj.pose.R).T \
            + np.asarray(obj.pose.t)
        for dev in (*rig.cameras, rig.projector):
            uv = dev.project(v)
            w, h = dev.size
            assert np.all((uv > -0.5) & (uv < [w - 0.5, h - 0.5])), (i, dev.name)
    rng = np.random.default_rng(0)
    assert place(rig, cfg.placement, 2000.0, rng) is None  # 4 m: fits nowhere


def test_a_measured_lens_pupil_scale_scales_its_aperture(tmp_path):
    from sim.optics.lens import sunflower_disk
    from sim.optics.measured_lens import MeasuredLens, save_lens

    disk = sunflower_disk(8)
    path = save_lens(tmp_path / "l.npz", MeasuredLens(
        focus_distance_mm=700.0, optical_centre_mm=np.zeros(3), camera_size=(64, 48),
        node_u=[0.0], node_v=[0.0], aperture_x_mm=disk[None, None, :, 0],
        aperture_y_mm=disk[None, None, :, 1], weights=np.full((1, 1, 8), 1 / 8),
        transmittance=np.ones((1, 1))))
    cfg = parse_config({"rig": {"builtin": {"camera_size_px": [64, 48]}}})
    cam = config_rig(cfg).cameras[0]
    one = build_lens(MeasuredLensDraw(path=str(path)), cam)
    two = build_lens(MeasuredLensDraw(path=str(path), pupil_scale=2.0), cam)
    np.testing.assert_allclose(two.aperture_x_mm, 2 * one.aperture_x_mm)
    np.testing.assert_allclose(two.aperture_y_mm, 2 * one.aperture_y_mm)
    wrong = parse_config({"rig": {"builtin": {"camera_size_px": [32, 48]}}})
    with pytest.raises(ValueError, match=r"l.npz is for a \(64, 48\) camera"):
        build_lens(MeasuredLensDraw(path=str(path)), config_rig(wrong).cameras[0])
