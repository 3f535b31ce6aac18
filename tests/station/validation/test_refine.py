"""The pose refinement by analysis by synthesis against analytic scanners: a camera at the
origin looking along +z, every pixel's point the ray's first hit on the balls, moved along
the ray by a bias that grows with depth and towards the limb (as defocus does). The real and
the virtual scanner share that bias but not their limb coverage; the refinement must land on
the true pose, and a ball bar whose real length is not the nominal one must still stop."""

from __future__ import annotations

import numpy as np

from sim.fpp.cloud import PointCloud
from station.validation.folder import BallBarArtefact, Pose, SphereArtefact
from station.validation.locate import (
    ball_centres,
    fit_near,
    pose_correction,
    pose_offset_um,
    refine_pose,
)

F_PX = 1000.0  # focal length, px: a 50.8 mm ball at 650 mm spans about 80 px


def scanned(centres: np.ndarray, radius_mm: float, limb_cos: float) -> PointCloud:
    """The biased cloud of balls (k, 3) mm: per pixel the nearest hit, moved away from the
    camera by ``20 um + 0.1 % of (z - 500 mm)``, times ``2 - cos`` (cos: between the normal and
    the ray); pixels with cos below ``limb_cos`` give no point."""
    u, v = np.meshgrid(np.arange(-200, 201), np.arange(-60, 61))
    d = np.stack([u / F_PX, v / F_PX, np.ones_like(u, dtype=float)], axis=-1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    best = np.full(len(d), np.inf)
    normal = np.zeros_like(d)
    for c in centres:
        b = d @ c
        disc = b * b - c @ c + radius_mm ** 2
        t = np.where(disc > 0, b - np.sqrt(np.maximum(disc, 0)), np.inf)
        near = t < best
        best[near] = t[near]
        normal[near] = (t[near, None] * d[near] - c) / radius_mm
    hit = np.isfinite(best)
    cos = -np.sum(normal * d, axis=1)
    keep = hit & (cos > limb_cos)
    p = best[keep, None] * d[keep]
    bias = (0.02 + 1e-3 * (p[:, 2] - 500.0)) * (2.0 - cos[keep])
    p = p + bias[:, None] * d[keep]
    fields = {"camera": np.zeros(keep.sum()), "u": u.ravel()[keep] + 200.0,
              "v": v.ravel()[keep] + 60.0}
    return PointCloud(points=p, normals=normal[keep], fields=fields)


class Twin:
    """The virtual scanner: the nominal artefact at a pose, scanned with the real bias."""

    def __init__(self, artefact, radius_mm: float) -> None:
        self.artefact, self.radius_mm, self.poses = artefact, radius_mm, []

    def __call__(self, pose: Pose):
        self.poses.append(pose)
        cloud = scanned(ball_centres(self.artefact, pose), self.radius_mm, limb_cos=0.15)

        class Scan:
            pass

        s = Scan()
        s.cloud = cloud
        return s


def test_the_refined_sphere_is_at_the_true_pose():
    art = SphereArtefact(diameter_mm=50.8)
    true = Pose(t=(12.0, -8.0, 650.0))
    real = scanned(ball_centres(art, true), 25.4, limb_cos=0.3)
    fit = fit_near(real, art, true, "S")
    assert pose_offset_um(fit.pose, true, art) > 100.0  # the real fit carries the bias
    twin = Twin(art, 25.4)
    ref = refine_pose(art, fit, fit.pose, twin, "S", real_cloud=real)
    assert ref.converged and ref.steps_um[-1] < 1.0 and len(ref.steps_um) <= 4, ref.steps_um
    assert pose_offset_um(ref.pose, true, art) < 1.0
    # the real and the virtual cloud differ only in their limb pixels: compared on the
    # pixels both have, the twin at the true pose needs no correction; each cloud's own fit
    # would move it by the bias of the limb pixels only one of them has
    at_true = twin(true).cloud
    own = fit_near(at_true, art, true, "S")
    assert np.abs(pose_correction(fit, own, art, real, at_true)).max() < 1e-6
    assert np.abs(pose_correction(fit, own, art)).max() > 1e-4


def test_a_ball_bar_longer_than_nominal_stops_at_its_midpoint():
    art = BallBarArtefact(ball_diameter_mm=38.1, centre_distance_mm=209.8219)
    true = Pose(t=(3.0, 5.0, 700.0))
    c = ball_centres(art, true)
    axis = (c[1] - c[0]) / np.linalg.norm(c[1] - c[0])
    longer = c + np.array([-1.0, 1.0])[:, None] * 0.010 * axis  # 20 um longer than nominal
    real = scanned(longer, 19.05, limb_cos=0.3)
    fit = fit_near(real, art, true, "B")
    twin = Twin(art, 19.05)
    ref = refine_pose(art, fit, fit.pose, twin, "B", real_cloud=real)
    # the balls' corrections keep 10 um each along the bar (the length the pose cannot
    # change); the rigid part converges all the same
    assert ref.converged and len(ref.steps_um) <= 4, ref.steps_um
    assert np.linalg.norm(np.asarray(ref.pose.t) - np.asarray(true.t)) * 1e3 < 0.5
