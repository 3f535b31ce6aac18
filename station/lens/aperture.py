"""The LTC at the optical centre (docs/optics.md section 6): scale, resample, fuse, quantise.

Similar triangles about the pixel's in-focus point map an LCD point ``q`` at depth ``z_i`` to
the aperture plane (the plane of the optical centre, ``z_O``):

    p = a + s_i (q - c_i),   s_i = (Z_F - z_O) / (Z_F - z_i)

with ``c_i`` the principal ray at ``z_i``, ``a`` the principal ray at ``z_O`` (both station
frame) and ``Z_F`` the focus plane; ``s_i < 0`` beyond the focus plane inverts the LTC. All
z enter as differences, so a constant added to every stage reading cancels.

With a focus per pupil zone (spherical aberration, ``station.lens.zones``: ``1 / z(rho) =
c0 + c1 rho^2`` from the optical centre) the scale depends on the pupil radius rho: a ray
through the aperture point p (camera frame, from the optical centre) meets the LCD at
``p g_i(|p|)`` from where the pupil's weighted ``p g_i`` lands (the LTC's centroid),
``g_i(rho) = 1 - (z_i - z_O) / z(rho)`` (the rim's ``g`` beyond the rim), so the rim of a
near LCD is wider than one focus predicts and a far one's narrower; one focus for every zone
maps a vignetted pupil with a skew of 0.04-0.08 on the near side (``zone_map``,
``resample(..., g2_per_mm2=...)``).

Each LCD pixel becomes a box of side ``pitch |s_i|`` on the aperture plane. A common grid of
``G x G`` cells (mm, camera-frame axes, origin at the optical centre) is filled by sampling
each cell on a ``k x k`` sub-grid (nearest LCD pixel: exact box densities, area-averaged).

Fusion weights: each depth's aperture distribution is in error by noise and by blur, both
predicted from known quantities (``depth_errors``). Noise: a cell's mass has std
``sigma_h sqrt(A/B) min(1, sqrt(A/B))`` (cell area A, LCD box area B, ``sigma_h`` the store's
per-weight noise), an L1 error ``sqrt(2/pi) N_cells sigma_cell``. Blur: the LCD box and the
camera pixel's footprint spread the distribution by ``sigma_b`` (box std), an L1 error
``0.8 sigma_b perimeter / area`` for a disk-like pupil. Blur errors of one pixel's depths
all smear the same pupil edge outwards, so they add linearly; noise errors are independent
and add in quadrature. The weights minimise ``(sum w b)^2 + sum w^2 n^2`` over the
non-negative weights summing to 1 (``fusion_weights``): with no noise the sharpest depth
alone; with noise a blend. (By noise alone, depths near focus, whose LTC is a few large
boxes with little noise, would win while being the blurriest.)

On request (``deblur``, ``LensFitConfig.support_floor`` and ``deconvolve_iterations``, off by
default), before the samples are drawn the fused distribution is cut to its main body (the
connected cells above 10 % of its largest: the LTC's noise over the blur margin, clipped to
non-negative, is a pedestal of far tails) and the known blur is removed by Richardson-Lucy
deconvolution with the fusion weights' mixture of the depths' kernels (LCD pixel box
``pitch |s_i|`` convolved with the camera pixel's footprint ``footprint |s_i|``). Moment
matching alone shrinks the blurred shape and keeps its tails: on the experiment's benches the
samples' ``E[rho^4]^(1/4)`` at the centre was 6.9 / 6.4 mm against the true 6.1 / 5.5 mm,
after the cut and 20 steps 6.0 / 5.4 mm (docs/decisions 0002).

K samples (``ring_samples``): equal-mass polar strata about the mean in whitened
coordinates (rings by radius, sectors by angle from a golden-angle offset per ring), each
sample its stratum's centroid, refined by a few weighted Lloyd (k-means) steps over the
cells; sample j is the same part of the aperture at every node, so bilinear interpolation
between nodes blends like with like. (It replaced weighted k-means from raster-quantile
seeds plus an optimal-assignment reordering per node (scipy, a Python loop over nodes).)
An affine map about the mean then gives the samples the target covariance exactly (the grid
covariance less a cell's own ``cell^2/12``, Sheppard's correction for binned masses, and less
the known box blurs: the LCD pixel's twice, once for binning the light and once for the
resampling's hold, and the camera pixel's once; so the samples describe the aperture, not the
measurement's pixels).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from sim.optics.lens_moments import sym_sqrtm

SQRT_2_OVER_PI = float(np.sqrt(2.0 / np.pi))
EDGE_L1_PER_SIGMA = 0.8  # L1 error of a blurred step edge per unit blur std and edge length
LLOYD_ITERATIONS = 5  # Lloyd steps after the ring strata (see ring_samples)
NOISE_FLOOR_L1 = 1e-4  # keeps noise-free weights finite


@dataclass(frozen=True)
class ApertureGrid:
    """A square grid of ``cells x cells`` on the aperture plane, centred on the optical centre.

    Cell ``[j, i]`` (row j along y, column i along x) has centre
    ``(-half + (i + 0.5) cell, -half + (j + 0.5) cell)`` mm.
    """

    half_width_mm: float
    cells: int

    def __post_init__(self) -> None:
        if not (self.half_width_mm > 0 and np.isfinite(self.half_width_mm)):
            raise ValueError(f"ApertureGrid: half_width_mm must be > 0, got {self.half_width_mm}")
        if self.cells < 2:
            raise ValueError(f"ApertureGrid: cells must be >= 2, got {self.cells}")

    @property
    def cell_mm(self) -> float:
        return 2.0 * self.half_width_mm / self.cells

    @property
    def centres_mm(self) -> np.ndarray:
        """Cell centre coordinates along one axis, (G,) mm."""
        return -self.half_width_mm + (np.arange(self.cells) + 0.5) * self.cell_mm

    def points(self, sub: int = 1) -> np.ndarray:
        """Cell centres (sub=1) or sub x sub sub-cell centres, (G*sub, G*sub, 2) (x, y) mm."""
        n = self.cells * sub
        c = -self.half_width_mm + (np.arange(n) + 0.5) * (self.cell_mm / sub)
        xx, yy = np.meshgrid(c, c)
        return np.stack([xx, yy], axis=-1)


def scale_ratio(depths_mm: np.ndarray, focus_plane_z_mm: float, centre_z_mm: float) -> np.ndarray:
    """Signed scale (D,) from depth ``z_i`` to the aperture plane: (Z_F - z_O) / (Z_F - z_i)."""
    dz = focus_plane_z_mm - np.asarray(depths_mm, dtype=np.float64)
    if np.any(np.abs(dz) < 1e-9):
        raise ValueError(f"scale_ratio: a depth lies on the focus plane z = {focus_plane_z_mm} mm;"
                         " its LTC carries no aperture information (drop it)")
    return (focus_plane_z_mm - centre_z_mm) / dz


class ZoneMap(NamedTuple):
    """A lens's radial maps per depth through its focus per pupil zone (``zone_map``)."""

    centre_ratio: np.ndarray  # (D,) 1 / g0: the scale at the pupil's centre
    g2_per_mm2: np.ndarray  # (D,) g = g0 + g2 rho^2
    fold: np.ndarray  # (D,) bool: g changes sign inside the pupil; the depth is not used
    blur_ratio: np.ndarray  # (D,) sign(g0) / sqrt(g0 g_rim): blur variances scale by its square
    rim_mm: float  # the pupil's radius; beyond it the rim's scale


def zone_map(depths_mm: np.ndarray, centre_z_mm: float, c0_per_mm: float,
             c1_per_mm3: float, rim_mm: float) -> ZoneMap:
    """The radial maps of a lens with a focus per pupil zone, ``1 / z(rho) = c0 + c1 rho^2``
    up to the pupil's rim ``rim_mm`` and the rim's focus beyond (``station.lens.zones``; z
    from the optical centre, mm): a ray through pupil radius rho aimed at its zone's focus
    lands on the LCD at distance ``d_i = z_i - z_O`` at ``p g_i(rho)`` from where the
    pupil's origin lands, ``g_i = 1 - d_i / z(rho) = g0_i + g2_i rho^2``. A depth folds where
    g changes sign inside the pupil (a zone focuses between the optical centre and the LCD,
    others beyond it): its LTC mixes the zones. ``blur_ratio`` squared is the mean of
    ``1 / g^2`` over a uniform pupil, so an LCD-plane blur's variance mapped through the
    zones is that blur's variance times ``blur_ratio^2`` (where one focus would use its
    ``scale_ratio``)."""
    d = np.asarray(depths_mm, dtype=np.float64) - centre_z_mm
    g0 = 1.0 - d * c0_per_mm
    g2 = -d * c1_per_mm3
    g_rim = g0 + g2 * rim_mm**2
    fold = (g0 * g_rim <= 0) | (np.abs(g0) < 1e-9)
    safe = np.where(fold, 1.0, g0)
    blur = np.sign(safe) / np.sqrt(np.where(fold, 1.0, g0 * g_rim))
    return ZoneMap(1.0 / safe, g2, fold, blur, float(rim_mm))


def resample(
    h: np.ndarray,
    origin: np.ndarray,
    ray_at_depth_mm: np.ndarray,
    ray_at_centre_mm: np.ndarray,
    ratio: float | np.ndarray,
    pitch_mm: float,
    grid: ApertureGrid,
    rotation2: np.ndarray | None = None,
    sub: int = 2,
    g2_per_mm2: float = 0.0,
    rim_mm: float = np.inf,
) -> np.ndarray:
    """Aperture-plane masses (n, G, G) of n LTC windows at one depth.

    h : (n, P, P) weights (0 outside the region to keep); origin : (n, 2) LCD (col, row) of
    element [0, 0]; ray_at_depth_mm : (n, 2) the point of the LTC that maps onto
    ``ray_at_centre_mm`` (the principal ray at the depth, or the LTC's own centroid)
    (LCD-plane mm); ray_at_centre_mm : (n, 2) principal ray at z_O minus the optical centre
    (mm);
    ratio : scalar or (n,) signed scale; rotation2 : (2, 2) station-to-camera rotation of
    aperture-plane vectors (identity if None).
    g2_per_mm2, rim_mm : a focus per pupil zone (``zone_map``): the scale from the aperture
    to the LCD is ``g(rho) = 1 / ratio + g2 min(rho, rim)^2`` at pupil radius rho (mm, from
    the optical centre) instead of ``1 / ratio`` (ratio then a scalar; ``zone_map`` rules out
    a fold).
    """
    from station.lens.kernels import resample_kernel

    h = np.ascontiguousarray(h, dtype=np.float64)
    n = h.shape[0]
    rot = np.eye(2) if rotation2 is None else np.asarray(rotation2, dtype=np.float64)
    if g2_per_mm2 != 0.0:
        return _resample_zoned(h, origin, ray_at_depth_mm, ray_at_centre_mm, float(ratio),
                               float(pitch_mm), grid, rot, sub, float(g2_per_mm2), rim_mm)
    pts = grid.points(sub).reshape(-1, 2)  # camera-frame aperture coordinates
    if rotation2 is not None:
        pts = pts @ rot  # p_station = R2^T p_cam, row-vector form
    out = np.zeros((n, grid.cells, grid.cells))
    step = grid.cell_mm / sub
    s = np.broadcast_to(np.asarray(ratio, dtype=np.float64), (n,))
    resample_kernel(h, np.ascontiguousarray(origin, dtype=np.int64),
                    np.ascontiguousarray(ray_at_depth_mm, dtype=np.float64),
                    np.ascontiguousarray(ray_at_centre_mm, dtype=np.float64),
                    np.ascontiguousarray(1.0 / s), np.ascontiguousarray((pitch_mm * s) ** 2),
                    np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1]),
                    float(pitch_mm), grid.cells, sub, grid.cell_mm**2, rot,
                    -grid.half_width_mm + 0.5 * step, step, out)
    return out


ZONED_CENTRING_STEPS = 2  # corrections of the zoned map's centre (``_resample_zoned``)


def _resample_zoned(h: np.ndarray, origin: np.ndarray, ray_d: np.ndarray, ray_c: np.ndarray,
                    ratio: float, pitch_mm: float, grid: ApertureGrid, rot: np.ndarray,
                    sub: int, g2: float, rim_mm: float) -> np.ndarray:
    """``resample`` through a focus per pupil zone. The LTC's centroid is where the pupil's
    ``E[p g(|p|)]`` lands, which the radial map does not know beforehand (``ray_c g(|ray_c|)``
    is its first guess, off by ``g2 (E[p rho^2] - ray_c |ray_c|^2)``: for a vignetted pupil
    about 0.1-0.3 mm on the aperture plane, and a map about the wrong centre skews the
    distribution); each of ``ZONED_CENTRING_STEPS`` moves the map so that the resampled
    distribution's mean is the principal ray ``ray_c``."""
    from station.lens.kernels import resample_zoned_kernel

    step = grid.cell_mm / sub
    org = np.ascontiguousarray(origin, dtype=np.int64)
    rc = np.ascontiguousarray(ray_c, dtype=np.float64)
    rd = np.array(ray_d, dtype=np.float64)
    r2_rim = float(min(rim_mm, 1e150)) ** 2
    g0 = 1.0 / ratio
    # the pupil's mean moves by about a shift on the LCD over the pupil's mean scale
    g_eff = np.sign(g0) * np.sqrt(abs(g0 * (g0 + g2 * r2_rim)))

    def mapped() -> np.ndarray:
        out = np.zeros((len(h), grid.cells, grid.cells))
        resample_zoned_kernel(h, org, np.ascontiguousarray(rd), rc, g0, g2, r2_rim, pitch_mm,
                              grid.cells, sub, grid.cell_mm**2, rot,
                              -grid.half_width_mm + 0.5 * step, step, out)
        return out

    for _ in range(ZONED_CENTRING_STEPS):
        out = mapped()
        tot = out.sum(axis=(1, 2))
        has = tot > 0
        if not has.any():
            return out
        mean_cam, _ = grid_moments(out[has] / tot[has, None, None], grid)
        mean_st = mean_cam @ rot  # camera-frame means to the station frame (R2^T p)
        rd[has] -= g_eff * (rc[has] - mean_st)
    return mapped()


def depth_errors(
    sigma_h: np.ndarray,
    ratio: np.ndarray,
    pitch_mm: float,
    footprint_mm: np.ndarray,
    cov_mm2: np.ndarray,
    cell_mm: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted L1 errors (..., D) of each depth's aperture distribution: (blur, noise).

    sigma_h : (..., D) per-weight noise (NaN: unknown, counts as infinite); ratio : (D,);
    footprint_mm : (D,) camera-pixel footprint on the LCD; cov_mm2 : (..., 2, 2) the pixel's
    aperture covariance (sets the area and edge length of a disk-like pupil).
    """
    det = np.maximum(np.linalg.det(cov_mm2), 1e-30)[..., None]
    area = 4.0 * np.pi * np.sqrt(det)  # a uniform disk of radius R: pi R^2
    radius = 2.0 * det**0.25
    a = cell_mm**2
    b = (pitch_mm * ratio) ** 2
    rel = np.sqrt(a / b)
    sigma_cell = np.nan_to_num(sigma_h, nan=np.inf) * rel * np.minimum(1.0, rel)
    l1_noise = SQRT_2_OVER_PI * (area / a) * sigma_cell
    sigma_b = np.sqrt(((pitch_mm * ratio) ** 2 + (footprint_mm * ratio) ** 2) / 12.0)
    l1_blur = EDGE_L1_PER_SIGMA * sigma_b * 2.0 / radius
    return np.broadcast_to(l1_blur, l1_noise.shape).copy(), l1_noise


def fusion_weights(blur: np.ndarray, noise: np.ndarray, available: np.ndarray) -> np.ndarray:
    """Weights (n, D), each row summing to 1 (0 where nothing is available), minimising the
    predicted error of the fused distribution ``(sum w b)^2 + sum w^2 n^2``.

    Blur errors of one pixel's depths share their sign (every depth smears the same pupil
    edge outwards), so they add linearly; noise errors are independent and add in quadrature.
    Solved in closed form (Sherman-Morrison) on the active set, dropping depths whose weight
    comes out negative until none does.
    """
    active = np.asarray(available, dtype=bool) & np.isfinite(noise) & np.isfinite(blur)
    b = np.where(active, blur, 0.0)
    v = np.where(active, noise**2, 1.0) + NOISE_FLOOR_L1**2
    w = np.zeros(b.shape)
    for _ in range(b.shape[1]):
        vi = np.where(active, 1.0 / v, 0.0)
        sb = (vi * b).sum(axis=1, keepdims=True)
        bb = (vi * b * b).sum(axis=1, keepdims=True)
        w = vi - vi * b * sb / (1.0 + bb)
        neg = active & (w < 0)
        if not neg.any():
            break
        active &= ~neg
    w = np.where(active, np.maximum(w, 0.0), 0.0)
    tot = w.sum(axis=1, keepdims=True)
    return w / np.where(tot > 0, tot, 1.0)


def grid_moments(mass: np.ndarray, grid: ApertureGrid) -> tuple[np.ndarray, np.ndarray]:
    """Mean (n, 2) and covariance (n, 2, 2) of normalised grid masses (n, G, G)."""
    from station.lens.kernels import moments_kernel

    n = len(mass)
    m = np.ascontiguousarray(np.asarray(mass, dtype=np.float64).reshape(n, grid.cells,
                                                                         grid.cells))
    mean, cov = np.empty((n, 2)), np.empty((n, 2, 2))
    moments_kernel(m, grid.centres_mm, mean, cov)
    return mean, cov


def ring_counts(k: int) -> np.ndarray:
    """Samples per ring of ``ring_samples``: R = round(sqrt(k / pi)) rings (at least 1), ring
    i holding about k (2 i + 1) / R^2 (equal areas per sample for a uniform disk)."""
    r = max(1, int(round(np.sqrt(k / np.pi))))
    c = np.maximum(1, np.round(k * (2 * np.arange(r) + 1) / r**2)).astype(np.int64)
    while c.sum() != k:  # round-off goes to the outer rings
        i = int(np.argmax(c)) if c.sum() > k else len(c) - 1
        c[i] += 1 if c.sum() < k else -1
    return c[c > 0]


def ring_samples(mass: np.ndarray, grid: ApertureGrid, k: int,
                 iterations: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """K samples of grid masses (n, G, G) by equal-mass polar strata: positions (n, k, 2) mm
    and weights (n, k) summing to 1 (each about 1/k). About the distribution's mean, in
    coordinates whitened by its covariance, the cells are cut into rings of equal mass per
    sample (``ring_counts``) by radius and each ring into sectors of equal mass by angle,
    starting at a golden-angle offset per ring (so no two rings line up); a cell's mass is
    split where a boundary falls inside it, and a sample is its stratum's centroid. The
    first moment is kept exactly, the samples spread like a Vogel spiral over a disk (no
    lattice: many distinct positions along every direction), and sample j is the same
    stratum at every node, so bilinear blending of neighbouring nodes blends like with
    like. Then ``iterations`` (default ``LLOYD_ITERATIONS``) weighted Lloyd (k-means) steps
    over the cells move each sample to the centroid of the cells nearest to it (first
    moment still exact; weights then unequal; sample j keeps its number). Negative masses
    count as 0."""
    from station.lens.kernels import lloyd_kernel, rings_kernel

    if k < 1:
        raise ValueError(f"ring_samples: need k >= 1 samples, got {k}")
    n = len(mass)
    m = np.maximum(np.asarray(mass, dtype=np.float64).reshape(n, grid.cells, grid.cells), 0.0)
    tot = m.sum(axis=(1, 2))
    if np.any(tot <= 0):
        raise ValueError(f"ring_samples: {int((tot <= 0).sum())} distribution(s) have no "
                         "positive mass")
    m = np.ascontiguousarray(m / tot[:, None, None])
    mean, cov = grid_moments(m, grid)
    white = sym_sqrtm(cov + np.eye(2) * grid.cell_mm**2 / 12.0, inverse=True)
    counts = ring_counts(k)
    offsets = np.arange(len(counts)) * np.pi * (3.0 - np.sqrt(5.0))
    x, w = np.empty((n, k, 2)), np.empty((n, k))
    rings_kernel(m, grid.centres_mm, mean, np.ascontiguousarray(white), counts, offsets, x, w)
    iterations = LLOYD_ITERATIONS if iterations is None else iterations
    if iterations:
        lloyd_kernel(m, grid.centres_mm, x, w, iterations)
    return x, w / w.sum(axis=1, keepdims=True)


def blur_kernels(ratio: np.ndarray, pitch_mm: float, footprint_mm: np.ndarray,
                 pixel_samples: int, cell_mm: float, half_cells: int) -> np.ndarray:
    """Each depth's blur on the aperture grid along one axis, (D, 2 L + 1) with L =
    ``half_cells``, each row summing to 1: the LCD pixel's box (``pitch_mm |s_i|`` wide)
    convolved with the camera pixel's footprint (``footprint_mm`` (D,) is the box-equivalent
    width of ``geometry.footprint_mm``: a box for ``pixel_samples = 0``, else
    ``pixel_samples`` points spread over the full footprint), integrated over each cell.
    The blur is the same along both axes (square pixels), so the 2-D kernel is the outer
    product of a row with itself."""
    s = np.abs(np.asarray(ratio, dtype=np.float64))
    fp = np.asarray(footprint_mm, dtype=np.float64)
    n, full = 16, fp  # a box footprint as 16 points over it
    if pixel_samples > 0:  # n x n points over the full footprint (box-equivalent width given)
        n = pixel_samples
        full = fp / np.sqrt(1.0 - 1.0 / n**2) if n > 1 else fp
    offs = ((np.arange(n) + 0.5) / n - 0.5)[None] * (full * s)[:, None] / cell_mm  # (D, n)
    width = np.maximum(pitch_mm * s / cell_mm, 1e-6)[:, None, None]  # the box, cells
    k = np.arange(-half_cells, half_cells + 1, dtype=np.float64)[None, None]
    lo = np.maximum(k - 0.5, offs[..., None] - width / 2)
    hi = np.minimum(k + 0.5, offs[..., None] + width / 2)
    row = (np.clip(hi - lo, 0.0, None) / width).mean(axis=1)
    return row / row.sum(axis=1, keepdims=True)


def support_floor(mass: np.ndarray, floor: float) -> np.ndarray:
    """Grid masses (n, G, G) outside their main body set to 0: only the 8-connected cells above
    ``floor`` times the node's largest cell that hold that cell are kept (negative masses
    become 0). The fused distribution carries the LTC's noise over its whole signal region
    (the blur margin included); clipped to non-negative it is a pedestal of positive noise
    around the pupil that the samples would keep as far tails (at the experiment's centre
    node E[rho^4]^(1/4) 6.9 mm against the true 6.1 mm, docs/decisions 0002)."""
    from scipy import ndimage

    m = np.maximum(np.asarray(mass, dtype=np.float64), 0.0)
    if floor <= 0:
        return m
    out = np.zeros_like(m)
    eight = np.ones((3, 3), dtype=bool)
    for j in range(len(m)):
        peak = np.unravel_index(int(np.argmax(m[j])), m[j].shape)
        if m[j][peak] <= 0:
            continue
        lab, _ = ndimage.label(m[j] > floor * m[j][peak], eight)
        out[j] = np.where(lab == lab[peak], m[j], 0.0)
    return out


def deblur(mass: np.ndarray, weight: np.ndarray, grid: ApertureGrid, ratio: np.ndarray,
           pitch_mm: float, footprint_mm: np.ndarray, pixel_samples: int,
           iterations: int, floor: float) -> np.ndarray:
    """Fused grid masses (n, G, G) cut to their main body (``support_floor`` at ``floor``)
    and with the known blur removed by ``iterations`` Richardson-Lucy steps; (n, G, G)
    normalised, non-negative (rows without mass stay 0).

    The fused distribution is the fusion weights' (n, D) mixture of the depths' distributions,
    each the aperture's convolved with its own blur (``blur_kernels``: the scaled LCD pixel and
    camera-pixel footprint), so it is the aperture's convolved with the weight-mixed kernel.
    Moment matching alone (``match_moments`` to the deblurred covariance) shrinks the blurred
    shape and keeps the blur's tails; this restores the shape. RL starts from the cut masses:
    cells outside the body stay empty, mass stays non-negative and sums to 1 (the whole grid
    counts as observed: cells outside the body are observed empty). The kernels are clipped
    to +-G/2 cells and taken along the grid's axes (the LCD's in-plane rotation against the
    camera, ``rotation2``, is a small alignment error on a station)."""
    from station.lens.kernels import richardson_lucy_kernel

    d = support_floor(mass, floor)
    tot = d.sum(axis=(1, 2), keepdims=True)
    d = d / np.where(tot > 0, tot, 1.0)
    if iterations <= 0 or len(d) == 0:
        return d
    g = grid.cells
    half = g // 2
    rows = blur_kernels(ratio, pitch_mm, footprint_mm, pixel_samples, grid.cell_mm, half)
    cells = np.arange(g)[:, None] + np.arange(-half, half + 1)[None]
    norm_rows = (rows[:, None, :] * ((cells >= 0) & (cells < g))[None]).sum(axis=2)  # (D, G)
    wn = np.asarray(weight, dtype=np.float64)
    s = wn.sum(axis=1, keepdims=True)
    wn = np.ascontiguousarray(wn / np.where(s > 0, s, 1.0))
    x = np.empty_like(d)
    richardson_lucy_kernel(np.ascontiguousarray(d), wn, np.ascontiguousarray(rows),
                           np.ascontiguousarray(norm_rows), int(iterations), x)
    tot = x.sum(axis=(1, 2), keepdims=True)
    return x / np.where(tot > 0, tot, 1.0)
