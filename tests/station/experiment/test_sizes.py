"""The experiment's size rule on synthetic clouds with known answers (no rendering): each
scanner's own-point size, and a virtual size against the real one on the pixels both
clouds share (``shared_size_mm``)."""

from __future__ import annotations

import numpy as np
import pytest

from sim.fpp.cloud import PointCloud
from station.experiment.run import (
    SPHERE_DIAMETER_MM,
    ExperimentConfig,
    Position,
    scene_of,
    shared_size_mm,
    size_fit,
)

CFG = ExperimentConfig()
CAP_DEG = 50.0  # the demo's spheres are caps of about 50 degrees about the view axis


def cap_cloud(centre, radius, camera=0, pitch_mm=1.6, noise_mm=0.0, rng=None):
    """A cap seen along +z (camera looking towards +z): one point per pixel (u, v) of a
    ``pitch_mm`` grid, on the sphere; returns points (n, 3), pixel (u, v) (n, 2) and the polar
    angle (n,) deg from the view axis."""
    n = int(radius / pitch_mm) + 1
    u, v = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1))
    x, y = u.ravel() * pitch_mm, v.ravel() * pitch_mm
    rho2 = x * x + y * y
    keep = rho2 < (radius * np.sin(np.radians(CAP_DEG))) ** 2
    x, y, rho2 = x[keep], y[keep], rho2[keep]
    z = -np.sqrt(radius * radius - rho2)
    p = np.column_stack([x, y, z]) + centre
    if noise_mm:
        d = (p - centre) / radius
        p = p + d * rng.normal(0.0, noise_mm, len(p))[:, None]
    theta = np.degrees(np.arcsin(np.sqrt(rho2) / radius))
    uv = np.column_stack([u.ravel()[keep], v.ravel()[keep]]) + 500
    return p, uv, np.full(len(p), float(camera)), theta


def cloud(points, uv, cam):
    return PointCloud(points, None, None, {"camera": cam, "u": uv[:, 0].astype(float),
                                           "v": uv[:, 1].astype(float)})


def radial(p, centre, d_mm):
    """Points moved outward from ``centre`` by ``d_mm`` (scalar or (n,))."""
    r = p - centre
    return p + r / np.linalg.norm(r, axis=1, keepdims=True) * np.reshape(d_mm, (-1, 1))


def test_a_uniform_offset_is_twice_the_diameter_on_shared_pixels_whatever_the_rims():
    """The virtual cloud is the real one moved 5 um outward (diameter +10 um exactly), but
    each scanner also kept rim pixels the other dropped (biased 100 um out or in) and the
    virtual one a gross outlier: the own-point sizes differ by far more than 10 um, the shared
    sizes by exactly 10 um."""
    rng = np.random.default_rng(0)
    pos = Position("S1", "sphere", "slight", (0.0, 0.0, 0.0), 760.0)
    scene = scene_of(pos, CFG, None)
    c = np.array(scene.objects[0].spheres()[0][:3])
    r = SPHERE_DIAMETER_MM / 2
    p, uv, cam, theta = cap_cloud(c, r, noise_mm=0.003, rng=rng)
    rim = theta > 42.0
    rim_real = rim & (uv[:, 0] > 500)   # kept only by the real scanner, 100 um outward
    rim_virt = rim & (uv[:, 0] <= 500)  # kept only by the virtual one, 100 um inward
    p_real = radial(p, c, np.where(rim_real, 0.1, 0.0))
    p_virt = radial(p, c, np.where(rim_virt, -0.1, 0.0) + 0.005)
    p_virt[np.flatnonzero(~rim)[0]] += [0.0, 0.0, -1.0]  # an outlier: 1 mm off, in the shell
    real = cloud(p_real[~rim_virt], uv[~rim_virt], cam[~rim_virt])
    virt = cloud(p_virt[~rim_real], uv[~rim_real], cam[~rim_real])
    own_r, own_v = size_fit(real, pos, scene), size_fit(virt, pos, scene)
    assert not own_v.fits[0].inliers.all()  # the outlier is trimmed by the virtual's own fit
    assert abs((own_v.size_mm - own_r.size_mm) - 0.010) > 0.02  # the rims dominate own sizes
    out = shared_size_mm(virt, own_v, real, own_r, pos)
    assert out["size_shared_mm"] - out["size_shared_real_mm"] == pytest.approx(0.010, abs=1e-7)
    # on the shared pixels the real cloud is the noisy true sphere: its diameter error is
    # within 4 standard errors of a 3 um noise on this cap
    assert abs(out["size_shared_real_mm"]) < 4 * 0.003 * 10 / np.sqrt(out["size_shared_points"]) * 2
    assert out["size_shared_points"] == int((~rim).sum()) - 1


def test_ball_bar_length_on_shared_pixels_ignores_a_rigid_shift():
    """A ball bar whose virtual cloud is the real one shifted rigidly by 30 um: its length
    on the shared pixels equals real's to rounding, though each kept other rim pixels."""
    pos = Position("B1", "ballbar", "slight", (0.0, 0.0, 0.0), 760.0)
    scene = scene_of(pos, CFG, None)
    balls = scene.objects[0].spheres()
    pts, uvs, cams, rims, centres = [], [], [], [], []
    for k, (cx, cy, cz, r) in enumerate(balls):
        p, uv, cam, theta = cap_cloud(np.array([cx, cy, cz]), r)
        pts.append(p)
        uvs.append(uv + [200 * k, 0])  # the two balls on different pixels
        cams.append(cam)
        rims.append(theta > 40.0)
        centres.append(np.tile([cx, cy, cz], (len(p), 1)))
    p, uv, cam, rim, c = (np.concatenate(a) for a in (pts, uvs, cams, rims, centres))
    half = uv[:, 1] > 500
    only_real, only_virt = rim & ~half, rim & half
    real = cloud(p[~only_virt], uv[~only_virt], cam[~only_virt])
    d = np.where(only_virt, 0.2, 0.0)[:, None]  # the virtual's own rim, 200 um outward
    pv = p + (p - c) / np.linalg.norm(p - c, axis=1, keepdims=True) * d + [0.03, -0.01, 0.02]
    virt = cloud(pv[~only_real], uv[~only_real], cam[~only_real])
    own_r, own_v = size_fit(real, pos, scene), size_fit(virt, pos, scene)
    assert own_r.size_mm == pytest.approx(0.0, abs=1e-7)  # the true balls, every pixel
    out = shared_size_mm(virt, own_v, real, own_r, pos)
    assert out["size_shared_mm"] == pytest.approx(out["size_shared_real_mm"], abs=1e-7)
    assert abs(out["size_shared_real_mm"]) < 1e-7


def test_a_ball_a_scanner_saw_only_in_patches_is_refused_naming_it():
    """Ball bar: the pinhole scanner sees both balls whole; a blurring scanner that kept a
    fifth of the second ball (a ball beyond its working range) is refused with one message
    naming the position, the scanner and the ball; with 40 % of it, it passes."""
    from station.errors import StationError
    from station.experiment.run import MIN_BALL_COVERAGE, Scan, build_rig, check_coverage

    rig = build_rig(CFG)
    pos = Position("B3", "ballbar", "large", (0.0, 0.0, 0.0), 760.0)
    scene = scene_of(pos, CFG, None)
    clouds = []
    for k, (cx, cy, cz, r) in enumerate(scene.objects[0].spheres()):
        p, uv, cam, _ = cap_cloud(np.array([cx, cy, cz]), r, pitch_mm=0.5)
        clouds.append((p, uv + [400 * k, 0], cam))

    def scans(second: float) -> dict:
        full = cloud(*(np.concatenate(a) for a in zip(*clouds, strict=True)))
        n = int(second * len(clouds[1][0]))
        part = cloud(*(np.concatenate([a, b[:n]]) for a, b in zip(*clouds, strict=True)))
        return {"real": Scan(full, None, 0.0), "ltc": Scan(part, None, 0.0),
                "gaussian": Scan(full, None, 0.0), "pinhole": Scan(full, None, 0.0)}

    assert MIN_BALL_COVERAGE == 0.25
    check_coverage(scans(0.4), pos, scene, rig)
    with pytest.raises(StationError) as err:
        check_coverage(scans(0.2), pos, scene, rig)
    msg = str(err.value)
    assert "position B3, scanner ltc: ball 2" in msg and "(20 %" in msg and "\n" not in msg
    assert "move it nearer focus" in msg
