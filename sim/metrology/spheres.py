"""Sphere metrology on point clouds: sphere fit, sphere detection, ball-bar length.

Sphere fit: algebraic least squares for the start, then geometric least squares on the radial
residuals ``|p - c| - r`` (scipy), with iterative outlier rejection at ``k`` robust standard
deviations (1.4826 MAD). The sphere fitting error is reported as RMS and peak-to-valley of the
radial residuals of the inliers. Lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from sim.errors import SimInputError
from sim.tolerances import SPHERE_DEGENERATE_REL, SPHERE_REJECT_FLOOR_MM

MAD_TO_SIGMA = 1.4826
RANSAC_POINTS = 4000  # sphere detection samples and scores on a random subset this large


@dataclass(frozen=True)
class SphereFit:
    """A fitted sphere.

    centre : (3,) mm; radius : mm; rms, pv : RMS and peak-to-valley of the inliers' radial
    residuals, mm; inliers : (n,) bool over the points given to the fit.
    """

    centre: np.ndarray
    radius: float
    rms: float
    pv: float
    inliers: np.ndarray

    @property
    def diameter(self) -> float:
        return 2.0 * self.radius

    def as_dict(self) -> dict:
        return {
            "centre_mm": [float(x) for x in self.centre],
            "diameter_mm": float(self.diameter),
            "fit_rms_mm": float(self.rms),
            "fit_pv_mm": float(self.pv),
            "points": int(self.inliers.size),
            "inliers": int(self.inliers.sum()),
        }


def finite_points(points: np.ndarray, name: str, minimum: int = 6) -> np.ndarray:
    """The finite rows of an (n, 3) point array (mm), float64; errors name ``name``."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise SimInputError(f"{name} must be an (n, 3) array of points, got shape {p.shape}")
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) < minimum:
        raise SimInputError(f"{name} has {len(p)} finite points, at least {minimum} are needed")
    return p


def fit_sphere_algebraic(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Linear least-squares sphere ``|p|^2 = 2 c.p + (r^2 - |c|^2)``: ``(centre (3,), radius)``.

    points : (n, 3) mm, n >= 4, not coplanar.
    """
    p = finite_points(points, "points", 4)
    m = p.mean(axis=0)
    q = p - m
    a = np.concatenate([2.0 * q, np.ones((len(q), 1))], axis=1)
    sol, _, rank, _ = np.linalg.lstsq(a, np.sum(q * q, axis=1), rcond=None)
    if rank < 4:
        raise SimInputError("points are degenerate (coplanar or collinear): no unique sphere")
    c = sol[:3]
    return c + m, float(np.sqrt(sol[3] + c @ c))


def _refine(p: np.ndarray, c0: np.ndarray, r0: float) -> tuple[np.ndarray, float]:
    m = p.mean(axis=0)
    q = p - m

    def res(x: np.ndarray) -> np.ndarray:
        return np.linalg.norm(q - x[:3], axis=1) - x[3]

    def jac(x: np.ndarray) -> np.ndarray:
        d = q - x[:3]
        n = np.linalg.norm(d, axis=1, keepdims=True)
        return np.concatenate([-d / n, -np.ones((len(q), 1))], axis=1)

    sol = least_squares(res, np.r_[c0 - m, r0], jac=jac, method="lm", xtol=1e-15, ftol=1e-15)
    return sol.x[:3] + m, float(sol.x[3])


def fit_sphere(
    points: np.ndarray, reject_sigma: float | None = 3.0, max_rounds: int = 10
) -> SphereFit:
    """Geometric least-squares sphere with outlier rejection.

    points : (n, 3) mm. reject_sigma : points whose radial residual is further than this many
    robust standard deviations from the median are dropped and the fit repeated until the
    inlier set is stable (None keeps every point). Returns a ``SphereFit`` whose ``inliers``
    index the finite rows of ``points``.
    """
    p = finite_points(points, "points", 4)
    c, r = fit_sphere_algebraic(p)
    inl = np.ones(len(p), dtype=bool)
    for _ in range(max_rounds):
        c, r = _refine(p[inl], c, r)
        d = np.linalg.norm(p - c, axis=1) - r
        if reject_sigma is None:
            break
        med = np.median(d[inl])
        sigma = MAD_TO_SIGMA * np.median(np.abs(d[inl] - med))
        new = np.abs(d - med) <= max(reject_sigma * sigma, SPHERE_REJECT_FLOOR_MM)
        if new.sum() < 4:
            raise SimInputError("outlier rejection left fewer than 4 points: no sphere in the data")
        if np.array_equal(new, inl):
            break
        inl = new
    d = np.linalg.norm(p[inl] - c, axis=1) - r
    return SphereFit(c, r, float(np.sqrt(np.mean(d * d))), float(np.ptp(d)), inl)


def _sphere_through_4(p4: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Spheres through point quadruples (m, 4, 3): centres (m, 3), radii (m,) (NaN if flat)."""
    q = p4 - p4[:, :1]
    a = 2.0 * q[:, 1:]
    b = np.sum(q[:, 1:] ** 2, axis=2)
    det = np.linalg.det(a)
    ok = np.abs(det) > SPHERE_DEGENERATE_REL * np.maximum(np.abs(a).max(axis=(1, 2)), 1e-300) ** 3
    a[~ok] = np.eye(3)
    c = np.linalg.solve(a, b[..., None])[..., 0]
    r = np.where(ok, np.linalg.norm(c, axis=1), np.nan)
    return c + p4[:, 0], r


def find_spheres(
    points: np.ndarray,
    count: int,
    radius_mm: float,
    radius_tolerance: float = 0.1,
    inlier_mm: float = 0.2,
    iterations: int = 3000,
    rng: np.random.Generator | None = None,
) -> list[SphereFit]:
    """Detect ``count`` spheres of about ``radius_mm`` in a cloud (RANSAC, then ``fit_sphere``).

    RANSAC runs on a random subset of ``RANSAC_POINTS`` points. Samples are drawn from a seed
    point and its neighbours within ``2 radius_mm``; a candidate is
    kept when its radius is within ``radius_tolerance`` (relative) of ``radius_mm``; its score is
    the number of points within ``inlier_mm`` of its surface. The best candidate's points within
    ``max(5 inlier_mm, 0.1 radius_mm)`` of its surface go to ``fit_sphere`` (which trims the
    outliers); then every point inside that shell is removed before the next search.
    """
    p = finite_points(points, "points", 4 * count)
    if radius_mm <= 0:
        raise SimInputError(f"radius_mm must be > 0, got {radius_mm}")
    rng = np.random.default_rng(0) if rng is None else rng
    found: list[SphereFit] = []
    remaining = p
    for k in range(count):
        if len(remaining) < 4:
            raise SimInputError(f"only {len(found)} of {count} spheres found: points ran out")
        sub = remaining[rng.choice(len(remaining), size=min(len(remaining), RANSAC_POINTS), replace=False)]
        tree = cKDTree(sub)
        seeds = rng.integers(0, len(sub), size=iterations)
        quads = np.empty((iterations, 4, 3))
        valid = np.zeros(iterations, dtype=bool)
        for i, nb in enumerate(tree.query_ball_point(sub[seeds], 2.0 * radius_mm)):
            if len(nb) >= 4:
                quads[i] = sub[rng.choice(nb, size=4, replace=False)]
                valid[i] = True
        c, r = _sphere_through_4(quads[valid])
        good = np.abs(r - radius_mm) <= radius_tolerance * radius_mm
        c, r = c[good], r[good]
        if len(r) == 0:
            raise SimInputError(
                f"sphere {k + 1} of {count}: no candidate sphere of radius {radius_mm:g} mm "
                f"(+-{100 * radius_tolerance:g}%) in the points"
            )
        score = _scores(sub, c, r, inlier_mm)
        wide = max(5.0 * inlier_mm, 0.1 * radius_mm)  # noisy points too; fit_sphere trims
        fit = _best_fit(remaining, c, r, score, wide,
                        lambda f: abs(f.radius - radius_mm) <= radius_tolerance * radius_mm)
        if fit is None:
            raise SimInputError(
                f"sphere {k + 1} of {count}: no fit of radius {radius_mm:g} mm "
                f"(+-{100 * radius_tolerance:g}%) to the best candidates' points"
            )
        found.append(fit)
        near = np.linalg.norm(remaining - fit.centre, axis=1) <= fit.radius + wide
        remaining = remaining[~near]
    return found


MIN_SPHERE_SUPPORT = 20
"""Fewest subset points on a candidate's surface for a sphere to be found without a prior."""
TOP_CANDIDATES = 5
"""RANSAC candidates (best scores first) whose points are fitted before one is accepted."""


def _scores(sub: np.ndarray, c: np.ndarray, r: np.ndarray, inlier_mm: float) -> np.ndarray:
    """Points of ``sub`` (n, 3) within ``inlier_mm`` of each candidate sphere (m,)."""
    score = np.zeros(len(r), dtype=np.int64)
    for k in range(0, len(r), 256):  # bounded memory
        dist = np.linalg.norm(sub[None, :, :] - c[k : k + 256, None, :], axis=2)
        score[k : k + 256] = np.sum(np.abs(dist - r[k : k + 256, None]) <= inlier_mm, axis=1)
    return score


def _best_fit(p: np.ndarray, c: np.ndarray, r: np.ndarray, score: np.ndarray,
              wide: float | None, accept) -> SphereFit | None:
    """``fit_sphere`` of the points within ``wide`` (None: ``max(5 inlier, 0.1 r)`` as the
    caller's) of each of the ``TOP_CANDIDATES`` best candidates; the accepted fit with the
    most inliers, or None."""
    best: SphereFit | None = None
    for i in np.argsort(-score, kind="stable")[:TOP_CANDIDATES]:
        band = wide if wide is not None else 0.1 * r[i]
        shell = np.abs(np.linalg.norm(p - c[i], axis=1) - r[i]) <= band
        if shell.sum() < 4:
            continue
        try:
            fit = fit_sphere(p[shell])
        except ValueError:
            continue
        if accept(fit) and (best is None or fit.inliers.sum() > best.inliers.sum()):
            best = fit
    return best


MIN_CAP_SAGITTA = 10.0
"""A sphere found beyond half the cloud's extent (second pass of ``find_sphere_unknown``) must
bulge by at least this many ``inlier_mm`` over its points (a plane patch fitted by a large
sphere bulges by about the inlier band)."""
MAX_RADIUS_EXTENT = 2.0
"""Second pass of ``find_sphere_unknown``: largest radius, times the cloud's extent."""


def _cap_sagitta(p: np.ndarray, fit: SphereFit, band: float) -> float:
    """How far (mm) the points of ``p`` within ``band`` of the fitted surface bulge: the
    radius times (1 - cos) of their largest angle from their mean direction seen from the
    centre."""
    d = p - fit.centre
    n = np.linalg.norm(d, axis=1)
    on = np.abs(n - fit.radius) <= band
    if on.sum() < 4:
        return 0.0
    u = d[on] / n[on, None]
    m = u.mean(axis=0)
    m /= np.linalg.norm(m)
    return float(fit.radius * (1.0 - np.min(u @ m)))


def find_sphere_unknown(
    points: np.ndarray,
    inlier_mm: float = 0.2,
    iterations: int = 1500,
    rng: np.random.Generator | None = None,
) -> SphereFit:
    """The best-supported sphere of a cloud, with no radius prior (RANSAC, then ``fit_sphere``).

    RANSAC on a random subset of ``RANSAC_POINTS`` points: quadruples are drawn from a seed
    point's neighbourhood, of 5, 10, 20 or 40 % of the subset's extent (bounding-box diagonal);
    spheres larger than half the extent (planes, in effect) or smaller than ``5 inlier_mm`` are
    not candidates; the score is the number of points within ``inlier_mm`` of the surface. The
    best candidate's points within ``max(5 inlier_mm, 0.1 r)`` of its surface go to
    ``fit_sphere``, as in ``find_spheres``. When that finds none, a second pass allows radii
    up to ``MAX_RADIUS_EXTENT`` times the extent, and accepts a fit only if its points bulge
    by ``MIN_CAP_SAGITTA`` inlier bands: a cap seen from one side can span less than its
    sphere's diameter (a 424-point cap of the 50.8 mm sphere 40 degrees about its pole spans
    45 mm), which the first pass refuses. Raises ``ValueError`` when no credible sphere is
    found."""
    p = finite_points(points, "points", 4)
    rng = np.random.default_rng(0) if rng is None else rng
    sub = p[rng.choice(len(p), size=min(len(p), RANSAC_POINTS), replace=False)]
    extent = float(np.linalg.norm(np.ptp(sub, axis=0)))
    if extent <= 0:
        raise SimInputError("points: all at one place, no sphere")
    tree = cKDTree(sub)
    seeds = rng.integers(0, len(sub), size=iterations)
    scales = extent * np.array([0.05, 0.1, 0.2, 0.4])
    quads = np.empty((iterations, 4, 3))
    valid = np.zeros(iterations, dtype=bool)
    for i, seed in enumerate(seeds):
        nb = tree.query_ball_point(sub[seed], scales[i % len(scales)])
        if len(nb) >= 4:
            quads[i] = sub[rng.choice(nb, size=4, replace=False)]
            valid[i] = True
    c_all, r_all = _sphere_through_4(quads[valid])
    try:
        return _unknown_pass(p, sub, c_all, r_all, inlier_mm, 0.5 * extent, "half the cloud")
    except ValueError as first:
        try:
            fit = _unknown_pass(p, sub, c_all, r_all, inlier_mm, MAX_RADIUS_EXTENT * extent,
                                f"{MAX_RADIUS_EXTENT:g} x the cloud's extent")
        except ValueError:
            raise first from None
        band = max(5.0 * inlier_mm, 0.1 * fit.radius)
        if _cap_sagitta(p, fit, band) < MIN_CAP_SAGITTA * inlier_mm:
            raise first from None
        return fit


def _unknown_pass(p: np.ndarray, sub: np.ndarray, c: np.ndarray, r: np.ndarray,
                  inlier_mm: float, largest: float, what: str) -> SphereFit:
    """One pass of ``find_sphere_unknown`` over the candidates (c, r) with radii below
    ``largest`` mm (``what`` names that bound)."""
    good = np.isfinite(r) & (r < largest) & (r > 5.0 * inlier_mm)
    c, r = c[good], r[good]
    if len(r) == 0:
        raise SimInputError(f"no sphere in the points: every candidate was flat or larger "
                            f"than {what}")
    score = _scores(sub, c, r, inlier_mm)
    if score.max() < MIN_SPHERE_SUPPORT:
        raise SimInputError(f"no sphere in the points: the best candidate has {score.max()} points "
                         f"within {inlier_mm:g} mm of its surface")
    fit = _best_fit(p, c, r, score, None, lambda f: 5.0 * inlier_mm < f.radius < largest)
    if fit is None:
        raise SimInputError("no sphere in the points: the best candidates' fits are flat or "
                            f"larger than {what}")
    return fit


def sphere_shell(points: np.ndarray, fit: SphereFit, inlier_mm: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Points (m, 3) within ``max(5 inlier_mm, 0.1 r)`` of a fitted sphere, and their signed
    radial distances (m,) mm (positive outside)."""
    p = finite_points(points, "points", 1)
    d = np.linalg.norm(p - fit.centre, axis=1) - fit.radius
    near = np.abs(d) <= max(5.0 * inlier_mm, 0.1 * fit.radius)
    return p[near], d[near]


@dataclass(frozen=True)
class BallBar:
    """Two fitted spheres and the distance between their centres (mm)."""

    spheres: tuple[SphereFit, SphereFit]
    length: float

    def as_dict(self) -> dict:
        return {
            "length_mm": float(self.length),
            "spheres": [s.as_dict() for s in self.spheres],
        }


def measure_ball_bar(
    points: np.ndarray, radius_mm: float, inlier_mm: float = 0.2, rng: np.random.Generator | None = None
) -> BallBar:
    """Find the two balls of a ball bar (nominal radius ``radius_mm``) and their centre distance."""
    a, b = find_spheres(points, 2, radius_mm, inlier_mm=inlier_mm, rng=rng)
    if a.centre[0] > b.centre[0]:
        a, b = b, a
    return BallBar((a, b), float(np.linalg.norm(a.centre - b.centre)))
