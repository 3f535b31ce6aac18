"""Stereo matching on rendered spheres: the sub-pixel match does not depend on the
interpolation, and the consistency checks drop the silhouette's mixed pixels."""

from __future__ import annotations

import numpy as np
import pytest

from sim.fpp.decode import DecodeSettings, scan
from sim.metrology.spheres import fit_sphere
from sim.optics.lens import AberratedLens, PinholeLens
from sim.optics.rig import Rig, small_rig
from sim.render.fringe_patterns import PhaseShiftSet
from sim.render.images import CameraResponse, ProjectorResponse, RenderSettings, render_views
from sim.render.scene import PlaneObject, Scene, SphereObject

D_SPHERE = 50.8007
PLANE_Z = 80.0


@pytest.fixture(scope="module")
def scene(crop):
    base = small_rig(0.3)  # sphere about 90 px across
    rig = Rig(cameras=[crop(c, (128, 112)) for c in base.cameras], projector=base.projector)
    w = rig.projector.size[0]
    ps = PhaseShiftSet(periods_px=[float(w), w / 8, w / 64], steps=4)
    geom = Scene(objects=[SphereObject(), PlaneObject(size_mm=(500.0, 400.0),
                                                      pose={"t": [0.0, 0.0, PLANE_Z]})]).trace_geometry()
    settings = RenderSettings(projector=ProjectorResponse(input_bits=None, defocus_sigma_px=0.3),
                              camera=CameraResponse(quantize=False))
    return rig, ps, geom, settings


def _render(scene, lens):
    rig, ps, geom, settings = scene
    res = render_views(geom, rig, [lens, lens], ps.images(rig.projector.size), settings,
                       np.random.default_rng(0))
    return [c.images for c in res.cameras], res


def _sphere_points(points):
    r = np.linalg.norm(points, axis=1)
    return points[r < D_SPHERE / 2 + 3]


def test_stereo_diameter_does_not_depend_on_the_interpolation(scene):
    rig, ps, _, _ = scene
    images, _ = _render(scene, PinholeLens())
    d = {}
    for order in (1, 3):
        cloud = scan(images, ps, rig, DecodeSettings(min_modulation=0.0, interpolation_order=order))
        d[order] = fit_sphere(_sphere_points(cloud.points), reject_sigma=None).diameter
    assert abs(d[1] - d[3]) < 0.5e-3
    assert abs(d[3] - D_SPHERE) < 5e-3


def test_consistency_checks_drop_the_silhouette(scene):
    """A thin lens blurs sphere and backdrop together at the silhouette: those pixels' phases
    are mixtures that would triangulate between the two surfaces."""
    rig, ps, _, _ = scene
    images, res = _render(scene, AberratedLens(pupil_diameter_mm=8.0, focus_distance_mm=700.0,
                                               samples=16))

    def off_surface(cloud):
        r = np.linalg.norm(cloud.points, axis=1) - D_SPHERE / 2
        plane = np.abs(cloud.points[:, 2] - PLANE_Z)
        return (np.abs(r) > 0.05) & (plane > 0.05)  # mixtures: mm off; fringe ripple: < 25 um

    checked = scan(images, ps, rig, DecodeSettings(min_modulation=0.0))
    loose = scan(images, ps, rig, DecodeSettings(min_modulation=0.0, max_lr_error_px=100.0,
                                                 max_model_residual=1e9,
                                                 max_range_step=float("inf")))
    assert off_surface(loose).sum() > 50  # without the checks, the silhouette is kept wrong
    assert off_surface(checked).sum() == 0
    # the silhouette pixels (sphere and backdrop within 1 px) give no point
    for k in (0, 1):
        obj = res.cameras[k].object_id
        pad = np.pad(obj, 1, mode="edge")
        mixed = np.zeros(obj.shape, bool)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                mixed |= pad[1 + dy : 1 + dy + obj.shape[0], 1 + dx : 1 + dx + obj.shape[1]] != obj
        mine = checked.fields["camera"] == k
        u, v = checked.fields["u"][mine].astype(int), checked.fields["v"][mine].astype(int)
        assert mixed.sum() > 100 and not mixed[v, u].any()


def test_pixel_footprint_correction_undoes_area_averaging(scene):
    """Pixels that average their area (rendered 3 x 3 supersampled, then averaged: a box of
    second moment 2/27 px^2 per axis) bias the sphere; the footprint correction removes it.
    Fringes of 18 projector px (about 18 camera px, as in the Mitsuba benchmark's 20)."""
    rig, _, geom, settings = scene
    ps = PhaseShiftSet(periods_px=[576.0, 72.0, 18.0], steps=4)
    scene = (rig, ps, geom, settings)
    s = 3

    def fine(cam):
        k = cam.K_array.copy()
        k[:2, :2] *= s
        k[:2, 2] = (k[:2, 2] + 0.5) * s - 0.5
        return cam.model_copy(update={"K": k.tolist(), "size": (cam.width * s, cam.height * s)})

    big = Rig(cameras=[fine(c) for c in rig.cameras], projector=rig.projector)
    res = render_views(geom, big, [PinholeLens()] * 2, ps.images(rig.projector.size), settings,
                       np.random.default_rng(0))
    images = []
    for c in res.cameras:
        n, h, w = c.images.shape
        images.append(c.images.reshape(n, h // s, s, w // s, s).mean(axis=(2, 4)))
    point, _ = _render(scene, PinholeLens())
    d = {}
    for name, imgs, var in (("point", point, 0.0), ("area", images, 0.0),
                            ("corrected", images, 2.0 / 27.0)):
        cloud = scan(imgs, ps, rig, DecodeSettings(min_modulation=0.0, pixel_variance_px2=var))
        d[name] = fit_sphere(_sphere_points(cloud.points), reject_sigma=None).diameter
    assert abs(d["area"] - d["point"]) > 2e-3  # the bias is real
    assert abs(d["corrected"] - d["point"]) < 0.3 * abs(d["area"] - d["point"])
