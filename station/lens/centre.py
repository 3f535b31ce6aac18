"""The optical centre (docs/optics.md section 6): where the principal rays meet, and the centre
consistent with the camera matrix K.

**Principal-ray intersection** (``intersect_rays``): the least-squares intersection of the
usable rays, iteratively reweighted (Huber weights on the ray-to-centre distance over a
robust scale), with the covariance ``s^2 (sum_n w_n (I - d_n d_n^T))^-1`` where ``s^2`` is the
weighted residual variance.

**Which optical centre** (``pinhole_centre``). A pixel's LTC centroid follows the centroid of
its *clipped* pupil. With vignetting that shifts with the field (cat's eyes), the centroid
rays cross the pupil plane at ``p_n ~ field``, so all of them converge on the axis behind the
pupil (34 mm on the small fake bench), near as well as far from the axis: no weighting fixes
it, and rays alone cannot fix it either (a field-shifted clipping circle is a second stop in
another plane, and two stops give the same rays whichever is called the pupil). The simulator
casts pixel n's rays through ``O + z_f (x_n, y_n, 1)`` with ``x_n`` from the camera matrix K,
so the centre it needs is the one from which the in-focus points are seen in K's directions.
With K known, that is what is estimated (``pinhole_centre``): the principal rays at the focus
plane give each pixel's in-focus point (every ray of the pixel passes there, clipped or not),
whose spread over the sensor is ``z_f`` times that of K's directions; the centre lies ``z_f``
before the focus plane, on the axis through the principal-ray intersection. Without K the
principal-ray intersection (the paper's definition) is used, and the report says so.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from station.lens.rays import FLAG_FEW_DEPTHS, PrincipalRays, RayFitError

HUBER_K = 2.0  # Huber threshold in robust-scale units for the ray intersection
BLOCK_RAYS = 1 << 18  # rays per block of the intersection's sums


@dataclass(frozen=True)
class OpticalCentre:
    """position : (3,) mm station frame; covariance : (3, 3) mm^2; weights : (N,) float32
    final robust weights (0 for unused rays); method : how it was found."""

    position: np.ndarray
    covariance: np.ndarray
    weights: np.ndarray
    method: str

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))


def _weighted(prior: np.ndarray, robust: np.ndarray, b: slice) -> np.ndarray:
    """The weights of the rays in block ``b``: a-priori times robust."""
    return prior[b] * robust[b]


def _huber(r: np.ndarray) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= HUBER_K, 1.0, HUBER_K / np.maximum(a, 1e-300))


def intersect_rays(rays: PrincipalRays, use: np.ndarray | None = None,
                   iterations: int = 20) -> OpticalCentre:
    """Robust least-squares intersection of the usable rays (``use`` restricts further)."""
    ok = rays.usable if use is None else rays.usable & np.asarray(use, dtype=bool)
    if ok.sum() < 2:
        raise RayFitError(f"optical centre: {int(ok.sum())} usable principal ray(s); need >= 2 "
                          f"({int((rays.flags & FLAG_FEW_DEPTHS).astype(bool).sum())} pixels "
                          "have too few depths with signal)")
    # sum_n w_n (I - d_n d_n^T) and its right-hand side in blocks of rays, without (n, 3, 3)
    # temporaries: memory per ray is a few scalars whatever the sensor
    idx = np.flatnonzero(ok)
    n = len(idx)
    blocks = [slice(b, min(n, b + BLOCK_RAYS)) for b in range(0, n, BLOCK_RAYS)]

    def lines(b: slice) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        j = idx[b]
        d = np.concatenate([rays.slope[j], np.ones((len(j), 1))], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        a = np.concatenate([rays.xy_ref[j], rays.z_ref[j, None]], axis=1)
        return d, a, np.einsum("ni,ni->n", d, a)

    # per ray: its robust weight, a-priori weight, distance and a scratch array (8 B each);
    # everything else is computed per block
    robust = np.ones(n)
    prior = np.empty(n)
    dist = np.empty(n)
    scratch = np.empty(n)
    z_c = float(np.mean(rays.z_ref[ok]))
    o = np.full(3, np.inf)

    def normal(weight: Callable[[slice], np.ndarray]) -> np.ndarray:  # the block's weights
        mat = np.zeros((3, 3))
        for b in blocks:
            d, _, _ = lines(b)
            wb = weight(b)
            mat += np.eye(3) * wb.sum() - np.einsum("n,ni,nj->ij", wb, d, d)
        return mat

    for _ in range(iterations):
        # a-priori lateral variance of each ray where it passes the current centre
        for b in blocks:
            j = idx[b]
            prior[b] = 1.0 / (rays.var_ref[j] + (z_c - rays.z_ref[j]) ** 2 * rays.var_slope[j])
        mat, rhs = normal(lambda b: prior[b] * robust[b]), np.zeros(3)
        for b in blocks:
            d, a, da = lines(b)
            w = prior[b] * robust[b]
            rhs += np.einsum("n,ni->i", w, a) - np.einsum("n,ni->i", w * da, d)
        o_prev, o = o, np.linalg.solve(mat, rhs)
        z_c = float(o[2])
        for b in blocks:
            d, a, da = lines(b)
            dist[b] = np.linalg.norm((o - a) - d * (d @ o - da)[:, None], axis=1)
            scratch[b] = dist[b] * np.sqrt(prior[b])
        # a 2-D Gaussian miss has a Rayleigh length, median sigma * sqrt(ln 4)
        scale = np.median(scratch, overwrite_input=True) / np.sqrt(np.log(4.0))
        same = True
        for b in blocks:  # the new weights, in place, from the scaled misses again
            new = _huber(dist[b] * np.sqrt(prior[b]) / max(scale, 1e-300))
            same = same and np.allclose(new, robust[b], atol=1e-10)
            robust[b] = new
        if same and np.allclose(o, o_prev, atol=1e-9, rtol=0):
            break
    w = prior  # prior x robust, in place
    w *= robust
    mat = normal(lambda b: w[b])
    dof = max(2 * len(w) - 3, 1)
    np.square(dist, out=scratch)
    scratch *= w
    s2 = float(scratch.sum() / dof)
    del scratch
    cov = s2 * np.linalg.inv(mat)
    weights = np.zeros(len(ok), np.float32)
    weights[ok] = w
    return OpticalCentre(o, cov, weights, "principal-ray intersection")


def pinhole_centre(rays: PrincipalRays, usable: np.ndarray, xn: np.ndarray,
                   focus_plane_z_mm: float, focus_plane_var_mm2: float, axis: OpticalCentre,
                   iterations: int = 20,
                   bias_mm: np.ndarray | None = None) -> tuple[OpticalCentre, np.ndarray]:
    """Optical centre consistent with K (see the module docstring).

    xn : (n, 2) the usable pixels' normalised directions from K (``pixel_to_normalized``
    of their (u, v), in the order of ``np.flatnonzero(usable)``).
    The in-focus points ``A_n`` (principal rays at the focus plane ``Z_F``) must be the
    pixels' directions ``x_n`` scaled by z_f about the axis, up to a roll phi:
    ``A_n = o + z_f Rot(phi) x_n``, linear in ``(o_x, o_y, z_f cos phi, z_f sin phi)``
    (robust: Huber-reweighted; the 4 x 4 normal equations are summed per pixel, no (2n, 4)
    design is built). The centre is at ``z = Z_F - z_f`` on the axis through the
    principal-ray intersection ``axis`` (its x, y; a camera tilt would enter ``o`` with a
    lever of z_f, and only 34 mm x tilt into the intersection). Covariance: x, y from the
    intersection, z from the fit's residuals plus the focus-plane variance propagated.
    bias_mm : (n, 2) station frame, optional: where each principal ray is known to miss its
    pixel's pinhole point at the focus plane (a lens whose zones focus at different depths:
    ``derive.zoned_centre``); subtracted from the in-focus points.
    Returns the centre and the rotation (3, 3) from station to camera axes (the roll).
    """
    idx = np.flatnonzero(usable)
    if len(idx) < 3:
        raise RayFitError(f"pinhole optical centre: {len(idx)} usable principal rays; need >= 3")
    n = len(idx)
    blocks = [slice(b, min(n, b + BLOCK_RAYS)) for b in range(0, n, BLOCK_RAYS)]
    # per ray: a-priori and robust weights, distance and a scratch array (8 B each)
    prior = np.empty(n)
    for b in blocks:
        j = idx[b]
        dz = focus_plane_z_mm - rays.z_ref[j]
        prior[b] = 1.0 / (rays.var_ref[j] + dz**2 * rays.var_slope[j])

    def data(b: slice) -> np.ndarray:  # the in-focus points of a block of rays
        j = idx[b]
        a = rays.xy_ref[j] + rays.slope[j] * (focus_plane_z_mm - rays.z_ref[j])[:, None]
        return a if bias_mm is None else a - bias_mm[b]

    def normal(weight: Callable[[slice], np.ndarray],
               slopes: bool = False) -> tuple[np.ndarray, np.ndarray]:
        # rows (1, 0, x0, -x1) for x and (0, 1, x1, x0) for y, both with weight w; np.dot,
        # not @: a 1-D matmul goes through threaded BLAS, whose spinning threads cost ~15x
        # the CPU time on a shared machine
        dot = np.dot
        ata, atb = np.zeros((4, 4)), np.zeros(4)
        for b in blocks:
            x0, x1, wb = xn[b, 0], xn[b, 1], weight(b)
            y = rays.slope[idx[b]] if slopes else data(b)
            sw, s0, s1, sq = wb.sum(), dot(wb, x0), dot(wb, x1), dot(wb, x0 * x0 + x1 * x1)
            ata += np.array([[sw, 0.0, s0, -s1], [0.0, sw, s1, s0], [s0, s1, sq, 0.0],
                             [-s1, s0, 0.0, sq]])
            wy0, wy1 = wb * y[:, 0], wb * y[:, 1]
            atb += np.array([wy0.sum(), wy1.sum(), dot(wy0, x0) + dot(wy1, x1),
                             dot(wy1, x0) - dot(wy0, x1)])
        return ata, atb

    robust = np.ones(n)
    dist_n = np.empty(n)
    scratch = np.empty(n)
    for _ in range(iterations):
        ata, atb = normal(functools.partial(_weighted, prior, robust))
        theta = np.linalg.solve(ata, atb)
        for b in blocks:  # each ray's miss, and scaled by its a-priori std
            x0, x1, y = xn[b, 0], xn[b, 1], data(b)
            rx = y[:, 0] - (theta[0] + theta[2] * x0 - theta[3] * x1)
            ry = y[:, 1] - (theta[1] + theta[2] * x1 + theta[3] * x0)
            dist_n[b] = np.sqrt(rx * rx + ry * ry)
            scratch[b] = dist_n[b] * np.sqrt(prior[b])
        scale = max(float(np.median(scratch, overwrite_input=True)) / np.sqrt(np.log(4.0)),
                    1e-300)
        done = True
        for b in blocks:  # the new weights, in place, from the scaled misses again
            scaled = dist_n[b] * np.sqrt(prior[b])
            new = np.where(scaled <= HUBER_K * scale, 1.0,
                           HUBER_K * scale / np.maximum(scaled, 1e-300))
            done = done and np.allclose(new, robust[b], atol=1e-10)
            robust[b] = new
        if done:
            break
    w = prior  # prior x robust, in place
    w *= robust
    del robust
    ata, _ = normal(lambda b: w[b])
    ata_inv = np.linalg.inv(ata)
    np.square(dist_n, out=scratch)
    scratch *= w
    s2 = float(scratch.sum()) / max(2 * n - 4, 1)
    del scratch, dist_n
    ca, cb = theta[2], theta[3]
    z_f = float(np.hypot(ca, cb))
    jac = np.array([ca, cb]) / z_f
    var_zf = float(jac @ (s2 * ata_inv[2:, 2:]) @ jac)
    dtheta = ata_inv @ normal(lambda b: w[b], slopes=True)[1]
    dz_o = 1.0 - float(jac @ dtheta[2:])
    cov = np.array(axis.covariance, dtype=np.float64, copy=True)
    cov[2, :] = cov[:, 2] = 0.0
    cov[2, 2] = var_zf + dz_o**2 * focus_plane_var_mm2
    o = np.array([axis.position[0], axis.position[1], focus_plane_z_mm - z_f])
    phi = float(np.arctan2(cb, ca))
    rot = np.array([[np.cos(phi), np.sin(phi), 0.0], [-np.sin(phi), np.cos(phi), 0.0],
                    [0.0, 0.0, 1.0]])
    weights = np.zeros(len(usable), np.float32)
    weights[idx] = w
    return OpticalCentre(o, cov, weights, "pinhole: in-focus points vs K"), rot
