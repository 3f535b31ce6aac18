"""Moments of a measured lens's aperture samples: the per-node mean and covariance, the
Gaussian lens of the same second moments at the optical centre, moment matching of sample
sets, and a lens smoothed across nodes (moments and radial profile) for noisy measurements.
"""

from __future__ import annotations

import numpy as np

from sim.optics.lens import GaussianLens
from sim.optics.measured_lens import MeasuredLens, _between_nodes, _bracket


def centre_moments(lens: MeasuredLens) -> tuple[np.ndarray, np.ndarray]:
    """Mean (2,) mm and covariance (2, 2) mm^2 of a measured lens's aperture distribution at
    the optical centre's pixel (the principal point of its camera matrix, else the sensor
    centre): each node's first and second moments of its samples, read there like the
    samples (nearest node or bilinear: the moments of the nodes' mixture; blending the
    samples themselves would narrow them wherever sample k differs from node to node)."""
    if lens.camera_matrix is not None:
        uv = lens.camera_matrix[:2, 2]
    else:
        uv = (np.asarray(lens.camera_size, dtype=np.float64) - 1) / 2
    uv = np.asarray(uv, dtype=np.float64)
    # only the (up to) 2 x 2 nodes about uv: the nearest one is among them too
    i0 = int(_bracket(lens.node_u, uv[:1])[0][0])
    j0 = int(_bracket(lens.node_v, uv[1:])[0][0])
    cols, rows = slice(i0, i0 + 2), slice(j0, j0 + 2)
    w = lens.weights[rows, cols]
    w = w / w.sum(axis=2, keepdims=True)
    x, y = lens.aperture_x_mm[rows, cols], lens.aperture_y_mm[rows, cols]
    m1 = np.stack([(w * x).sum(axis=2), (w * y).sum(axis=2)], axis=-1)
    m2 = np.stack([(w * x * x).sum(axis=2), (w * x * y).sum(axis=2),
                   (w * y * y).sum(axis=2)], axis=-1)
    mean, sq = (a[0] for a in _between_nodes(lens.node_u[cols], lens.node_v[rows],
                                             lens.interpolation, (m1, m2), uv[None]))
    second = np.array([[sq[0], sq[1]], [sq[1], sq[2]]])
    return mean, second - np.outer(mean, mean)


def gaussian_equivalent(lens: MeasuredLens, samples: int | None = None) -> GaussianLens:
    """The Gaussian defocus model of a measured lens (docs/optics.md section 4): its focus distance,
    with Gaussian aperture weights whose per-axis variance is the mean of the two axes' second
    moments of the measured LTC at the optical centre, the same for every pixel. ``samples``:
    aperture samples (default the measured lens's K)."""
    _, cov = centre_moments(lens)
    return GaussianLens(sigma_mm=float(np.sqrt(0.5 * np.trace(cov))),
                        focus_distance_mm=lens.focus_distance_mm,
                        samples=samples or lens.samples)


def smoothed_lens(lens: MeasuredLens, sigma_nodes: float) -> MeasuredLens:
    """The lens with the station's node-to-node measurement noise averaged out over
    neighbouring nodes (Gaussian weights of ``sigma_nodes`` node spacings), keeping the slow
    field dependence (vignetting, the principal rays' curved field).

    - The samples' centroids (each node's principal ray on the aperture plane, mm) by a local
      quadratic regression over the nodes' positions: quadratic fields pass unbiased, also at
      the sensor's border, where a plain average would pull a curved field inwards. The
      centroids' noise drives the large-defocus sizes (docs/decisions 0002). The aim offsets
      are kept: each node's principal ray aims at the same point of the focus plane.
    - The shape about the centroid (sample offsets, weights, transmittance) by a plain
      Gaussian average, edges held. Sample k is only roughly the same part of the aperture at
      neighbouring nodes, so averaging the samples alone would shrink the aperture (two nodes'
      samples blended 50/50 keep about 0.96 of their spread) and pile its light towards the
      middle. So the averaged samples are then reshaped, in each node's frame whitened by its
      second moment: their radii are mapped onto the smoothed radial profile (the nodes'
      radius quantiles averaged, which keeps a disk a disk), and an affine map restores the
      smoothed second moment (mm^2) exactly.

    Weights are renormalised per node. ``sigma_nodes = 0``: the lens itself."""
    if sigma_nodes < 0:
        raise ValueError(f"smoothed_lens: sigma_nodes must be >= 0, got {sigma_nodes}")
    if sigma_nodes == 0:
        return lens
    from dataclasses import replace

    from scipy.ndimage import gaussian_filter

    def f(a: np.ndarray) -> np.ndarray:
        return gaussian_filter(a, (sigma_nodes, sigma_nodes) + (0,) * (a.ndim - 2),
                               mode="nearest")

    gv, gu, k = lens.aperture_x_mm.shape
    ranks = (np.arange(_PROFILE_LEVELS) + 0.5) / _PROFILE_LEVELS

    def flat(a: np.ndarray) -> np.ndarray:
        return a.reshape((gv * gu,) + a.shape[2:])

    xy = flat(np.stack([lens.aperture_x_mm, lens.aperture_y_mm], axis=-1))  # (n, K, 2)
    w = flat(lens.weights / lens.weights.sum(axis=2, keepdims=True))
    c, cov = sample_moments(xy, w)
    profile = f(_quantiles(_whitened_radius(xy - c[:, None], cov), w, ranks)
                .reshape(gv, gu, -1))  # (Gv, Gu, M)
    target = f(cov.reshape(gv, gu, 2, 2))
    w = f(w.reshape(gv, gu, k))
    w = flat(w / w.sum(axis=2, keepdims=True))
    d = flat(f((xy - c[:, None]).reshape(gv, gu, k, 2)))
    mean, now = sample_moments(d, w)
    d = d - mean[:, None]
    rho = _whitened_radius(d, now)
    d = d * (_at_ranks(rho, w, ranks, flat(profile)) / np.maximum(rho, 1e-300))[..., None]
    centre = flat(_local_quadratic(c.reshape(gv, gu, 2), lens.node_u, lens.node_v, sigma_nodes))
    xy = match_moments(d, w, centre, flat(target)).reshape(gv, gu, k, 2)
    return replace(lens, aperture_x_mm=xy[..., 0], aperture_y_mm=xy[..., 1],
                   weights=w.reshape(gv, gu, k), transmittance=f(lens.transmittance))


def _local_quadratic(values: np.ndarray, node_u: np.ndarray, node_v: np.ndarray,
                     sigma_nodes: float) -> np.ndarray:
    """Per-node values (Gv, Gu, C) smoothed by a local quadratic regression: at each node,
    the weighted least-squares fit of ``a + b du + c dv + d du^2 + e du dv + f dv^2`` over all
    nodes, weights a Gaussian of the offsets (du, dv) in node spacings with sigma
    ``sigma_nodes``; its value at the node. Quadratic fields pass exactly; along an axis with
    fewer than 3 (2) nodes the fit drops the square (linear) terms."""
    def axis(nodes: np.ndarray, power: int) -> np.ndarray:
        """(G, G) weights g(d) d^power, d the offset from row node to column node."""
        spacing = float(np.median(np.diff(nodes))) if len(nodes) > 1 else 1.0
        d = (nodes[None, :] - nodes[:, None]) / spacing
        return np.exp(-0.5 * (d / sigma_nodes) ** 2) * d**power

    gv, gu = values.shape[:2]
    terms = [(a, b) for a in range(min(2, gu - 1) + 1) for b in range(min(2, gv - 1) + 1)
             if a + b <= 2]
    pu = {p: axis(node_u, p) for p in range(5)}
    pv = {p: axis(node_v, p) for p in range(5)}
    normal = np.stack([np.stack([np.outer(pv[b + e].sum(axis=1), pu[a + d].sum(axis=1))
                                 for d, e in terms], axis=-1)
                       for a, b in terms], axis=-2)  # (Gv, Gu, T, T)
    rhs = np.stack([np.einsum("ij,jkc,lk->ilc", pv[b], values, pu[a]) for a, b in terms],
                   axis=-2)  # (Gv, Gu, T, C)
    return np.linalg.solve(normal, rhs)[..., 0, :]


_PROFILE_LEVELS = 64  # radius quantiles per node that ``smoothed_lens`` averages


def sample_moments(x: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean (n, 2) mm and covariance (n, 2, 2) mm^2 of samples x (n, k, 2) with
    weights w (n, k) summing to 1."""
    mu = np.einsum("nk,nki->ni", w, x)
    d = x - mu[:, None]
    return mu, np.einsum("nk,nki,nkj->nij", w, d, d)


def sym_sqrtm(c: np.ndarray, inverse: bool = False) -> np.ndarray:
    """Square root (or its inverse) of symmetric 2 x 2 matrices c (n, 2, 2), eigenvalues
    clamped at 1e-18."""
    val, vec = np.linalg.eigh(c)
    val = np.maximum(val, 1e-18)
    f = val**-0.5 if inverse else np.sqrt(val)
    return np.einsum("nij,nj,nkj->nik", vec, f, vec)


def match_moments(
    x: np.ndarray, w: np.ndarray, mean: np.ndarray, cov: np.ndarray
) -> np.ndarray:
    """Affine map of samples x (n, k, 2) with weights w (n, k) about their mean so that their
    weighted mean and covariance become ``mean`` (n, 2) and ``cov`` (n, 2, 2)."""
    mu, c = sample_moments(x, w)
    t = sym_sqrtm(cov) @ sym_sqrtm(c, inverse=True)
    return mean[:, None] + np.einsum("nij,nkj->nki", t, x - mu[:, None])


def _whitened_radius(d: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Radius (n, K) of offsets d (n, K, 2) in the frame whitened by cov (n, 2, 2)."""
    return np.linalg.norm(np.einsum("nij,nkj->nki", sym_sqrtm(cov, inverse=True), d), axis=-1)


def _weighted_cdf(v: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per node (last axis): the sort order of v, v sorted and its mid-point weighted CDF."""
    order = np.argsort(v, axis=-1, kind="stable")
    ws = np.take_along_axis(w, order, axis=-1)
    return order, np.take_along_axis(v, order, axis=-1), np.cumsum(ws, axis=-1) - 0.5 * ws


def _interp_rows(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """np.interp along the last axis, row by row (xp increasing in each row; clamped)."""
    rows = int(np.prod(xp.shape[:-1]))
    xp2, fp2 = xp.reshape(rows, -1), fp.reshape(rows, -1)
    x2 = np.clip(x.reshape(rows, -1), xp2[:, :1], xp2[:, -1:])
    shift = 2.0 * (np.abs(xp2).max() + 1.0) * np.arange(rows)[:, None]  # rows never overlap
    return np.interp(x2 + shift, (xp2 + shift).ravel(), fp2.ravel()).reshape(x.shape)


def _quantiles(v: np.ndarray, w: np.ndarray, ranks: np.ndarray) -> np.ndarray:
    """Weighted quantiles (..., M) of v (..., K) at ``ranks`` (M,) in (0, 1)."""
    _, vs, cdf = _weighted_cdf(v, w)
    return _interp_rows(np.broadcast_to(ranks, v.shape[:-1] + ranks.shape), cdf, vs)


def _at_ranks(v: np.ndarray, w: np.ndarray, ranks: np.ndarray, profile: np.ndarray
              ) -> np.ndarray:
    """Each value of v (..., K) replaced by ``profile`` (..., M, given at ``ranks``) at its own
    weighted mid-rank: a monotone remap of v onto the profile."""
    order, _, cdf = _weighted_cdf(v, w)
    out = np.empty_like(v)
    np.put_along_axis(out, order,
                      _interp_rows(cdf, np.broadcast_to(ranks, profile.shape), profile), axis=-1)
    return out
