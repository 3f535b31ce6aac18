"""The measured lens (OPTICS.md 6.5, ARCHITECTURE.md "Lens model"): per pixel, or per node of
a grid of pixels, K aperture samples ``(x_k, y_k)`` mm on the plane of the optical centre with
weights ``w_k`` (sum 1), one focus distance ``z_f`` and, optionally, a focus distance per
pupil zone ``z(rho)`` (spherical aberration: ``focus_zones_mm``).

``MeasuredLens.bundle(xy_n, uv)`` casts ray k of a pixel from ``(x_k, y_k, 0)`` through the
pixel's in-focus point ``((x_n + e_x) z_k, (y_n + e_y) z_k, z_k)`` in the camera frame whose
origin is the optical centre (``z_k = z_f``, or with ``focus_zones_mm`` the zone's focus at
the sample's pupil radius ``rho_k = |(x_k, y_k)|``, linear between rows, clamped at the
ends; ``e`` the node's ``aim_offset``, 0 without one), with weight ``w_k * transmittance``
(relative transmittance: 1 for the brightest pixels, lower where the lens vignettes). Samples between nodes: ``nearest`` node,
or ``bilinear`` (sample k of the four surrounding nodes blended; the derivation orders
samples the same way at every node, so sample k means the same part of the aperture).

File: one ``.npz`` (no pickle), written by ``save_lens`` and read by ``load_lens``:

=====================  ==============  ===================================================
name                   shape, dtype    meaning
=====================  ==============  ===================================================
format                 () str          ``"ltc-fpp-measured-lens"``
format_version         () int          ``1``
focus_distance_mm      () float        z_f, mm from the optical centre
optical_centre_mm      (3,) float      where the optical centre was (station frame), mm
camera_size            (2,) int        (width, height), pixels
node_u, node_v         (Gu,), (Gv,)    node pixel columns and rows, strictly increasing
aperture_x_mm          (Gv, Gu, K)     sample x, mm, camera frame
aperture_y_mm          (Gv, Gu, K)     sample y, mm
weights                (Gv, Gu, K)     >= 0, each node sums to 1
transmittance          (Gv, Gu)        relative transmittance, >= 0
interpolation          () str          ``"nearest"`` or ``"bilinear"``
camera_matrix          (3, 3) float    optional: K the model is consistent with
dist_coeffs            (5,) float      optional: OpenCV distortion with that K
focus_zones_mm         (Z, 2) float    optional: rows (pupil radius mm, focus distance mm
                                       from the optical centre), radii strictly increasing
                                       from >= 0, Z >= 2; absent: every ray aims at z_f
aim_offset             (Gv, Gu, 2)     optional: per node, added to the pixel's normalised
                                       coordinates where its samples aim (the principal
                                       ray's offset from the pinhole direction, radians);
                                       absent: 0
metadata_json          () str          optional: how it was measured (free JSON)
=====================  ==============  ===================================================
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.errors import SimInputError
from sim.optics.lens import GaussianLens, RayBundle
from sim.optics.projection import normalized_to_pixel
from sim.tolerances import WEIGHT_SUM_TOL

FORMAT = "ltc-fpp-measured-lens"
FORMAT_VERSION = 1
INTERPOLATIONS = ("nearest", "bilinear")
REQUIRED = ("format", "format_version", "focus_distance_mm", "optical_centre_mm", "camera_size",
            "node_u", "node_v", "aperture_x_mm", "aperture_y_mm", "weights", "transmittance",
            "interpolation")
OPTIONAL = ("camera_matrix", "dist_coeffs", "metadata_json", "focus_zones_mm", "aim_offset")


class LensFileError(SimInputError):
    """A measured-lens file or model is invalid; the message names the file and the field."""


def _finite(name: str, a: np.ndarray) -> None:
    if not np.all(np.isfinite(a)):
        raise LensFileError(f"field '{name}' has {int((~np.isfinite(a)).sum())} NaN or "
                            "infinite value(s)")


@dataclass(frozen=True, eq=False)
class MeasuredLens:
    """A lens model measured by the LTC station (see the module docstring for the fields)."""

    focus_distance_mm: float
    optical_centre_mm: np.ndarray
    camera_size: tuple[int, int]
    node_u: np.ndarray
    node_v: np.ndarray
    aperture_x_mm: np.ndarray
    aperture_y_mm: np.ndarray
    weights: np.ndarray
    transmittance: np.ndarray
    interpolation: str = "bilinear"
    camera_matrix: np.ndarray | None = None
    dist_coeffs: np.ndarray | None = None
    metadata: dict = field(default_factory=dict)
    focus_zones_mm: np.ndarray | None = None
    aim_offset: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("optical_centre_mm", "node_u", "node_v", "aperture_x_mm", "aperture_y_mm",
                     "weights", "transmittance", "camera_matrix", "dist_coeffs",
                     "focus_zones_mm", "aim_offset"):
            if getattr(self, name) is not None:  # own float64 copies
                object.__setattr__(self, name, np.array(getattr(self, name), dtype=np.float64))
        object.__setattr__(self, "focus_distance_mm", float(self.focus_distance_mm))
        object.__setattr__(self, "camera_size", tuple(int(v) for v in self.camera_size))
        self._validate()

    def _validate(self) -> None:
        if not (np.isfinite(self.focus_distance_mm) and self.focus_distance_mm > 0):
            raise LensFileError(f"field 'focus_distance_mm' must be > 0, got "
                                f"{self.focus_distance_mm}")
        if self.optical_centre_mm.shape != (3,):
            raise LensFileError(f"field 'optical_centre_mm' must have shape (3,), got "
                                f"{self.optical_centre_mm.shape}")
        _finite("optical_centre_mm", self.optical_centre_mm)
        if len(self.camera_size) != 2 or min(self.camera_size) < 1:
            raise LensFileError(f"field 'camera_size' must be (width, height) >= 1, got "
                                f"{self.camera_size}")
        w, h = self.camera_size
        for name, n in (("node_u", w), ("node_v", h)):
            a = getattr(self, name)
            if a.ndim != 1 or len(a) < 1:
                raise LensFileError(f"field '{name}' must be a non-empty 1-D array, got shape "
                                    f"{a.shape}")
            _finite(name, a)
            if np.any(np.diff(a) <= 0) or a[0] < 0 or a[-1] > n - 1:
                raise LensFileError(f"field '{name}' must increase strictly within "
                                    f"[0, {n - 1}], got {a[:4].tolist()}...")
        gv, gu = len(self.node_v), len(self.node_u)
        shape = self.weights.shape
        if len(shape) != 3 or shape[:2] != (gv, gu) or shape[2] < 1:
            raise LensFileError(f"field 'weights' must have shape (len(node_v)={gv}, "
                                f"len(node_u)={gu}, K), got {shape}")
        for name in ("aperture_x_mm", "aperture_y_mm"):
            if getattr(self, name).shape != shape:
                raise LensFileError(f"field '{name}' must have the shape of 'weights' {shape}, "
                                    f"got {getattr(self, name).shape}")
            _finite(name, getattr(self, name))
        _finite("weights", self.weights)
        if np.any(self.weights < 0):
            raise LensFileError("field 'weights' has negative values")
        sums = self.weights.sum(axis=2)
        if np.any(np.abs(sums - 1.0) > WEIGHT_SUM_TOL):
            j, i = np.unravel_index(np.abs(sums - 1.0).argmax(), sums.shape)
            raise LensFileError(f"field 'weights' must sum to 1 per node; node (row {j}, col "
                                f"{i}) sums to {float(sums[j, i])!r}")
        if self.transmittance.shape != (gv, gu):
            raise LensFileError(f"field 'transmittance' must have shape ({gv}, {gu}), got "
                                f"{self.transmittance.shape}")
        _finite("transmittance", self.transmittance)
        if np.any(self.transmittance < 0):
            raise LensFileError("field 'transmittance' has negative values")
        if self.interpolation not in INTERPOLATIONS:
            raise LensFileError(f"field 'interpolation' must be one of {INTERPOLATIONS}, got "
                                f"{self.interpolation!r}")
        if self.camera_matrix is not None:
            if self.camera_matrix.shape != (3, 3):
                raise LensFileError(f"field 'camera_matrix' must be 3x3, got "
                                    f"{self.camera_matrix.shape}")
            _finite("camera_matrix", self.camera_matrix)
        if self.dist_coeffs is not None:
            if self.dist_coeffs.shape != (5,):
                raise LensFileError(f"field 'dist_coeffs' must have 5 values, got "
                                    f"{self.dist_coeffs.shape}")
            _finite("dist_coeffs", self.dist_coeffs)
        if self.aim_offset is not None:
            _check_aim_offset(self.aim_offset, gv, gu)
        zones = self.focus_zones_mm
        if zones is not None:
            if zones.ndim != 2 or zones.shape[1] != 2 or zones.shape[0] < 2:
                raise LensFileError(f"field 'focus_zones_mm' must have shape (Z >= 2, 2), got "
                                    f"{zones.shape}")
            _finite("focus_zones_mm", zones)
            if zones[0, 0] < 0 or np.any(np.diff(zones[:, 0]) <= 0):
                raise LensFileError("field 'focus_zones_mm' must have pupil radii (column 0) "
                                    f"increasing strictly from >= 0, got {zones[:4, 0].tolist()}")
            if np.any(zones[:, 1] <= 0):
                raise LensFileError("field 'focus_zones_mm' must have focus distances "
                                    f"(column 1) > 0, got {zones[:4, 1].tolist()}")

    def aim_depths(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray | float:
        """Focus distance mm that samples at aperture points (x_mm, y_mm) aim at: their zone's
        (``focus_zones_mm``, by pupil radius) or ``focus_distance_mm`` (``aim_depths``)."""
        return aim_depths(self.focus_zones_mm, self.focus_distance_mm, x_mm, y_mm)

    def save(self, path: str | Path) -> Path:
        """Write this lens as a lens file (``save_lens``); returns the path written."""
        return save_lens(path, self)

    @classmethod
    def load(cls, path: str | Path) -> MeasuredLens:
        """Read and validate a lens file (``load_lens``)."""
        return load_lens(path)

    @property
    def samples(self) -> int:
        """K, aperture samples per pixel."""
        return int(self.weights.shape[2])

    def samples_at(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Aperture samples of pixels uv (n, 2): x (n, K), y (n, K) mm and weights (n, K)
        times the relative transmittance."""
        t = _Transmitted(self.transmittance, self.weights)
        return self._at((self.aperture_x_mm, self.aperture_y_mm, t), uv)  # type: ignore

    def aim_offset_at(self, uv: np.ndarray) -> np.ndarray:
        """The aim offset (n, 2) of pixels uv (n, 2), read like the samples; 0 without one."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if self.aim_offset is None:
            return np.zeros((len(uv), 2))
        return self._at((self.aim_offset,), uv)[0]

    def _at(self, arrays: tuple[np.ndarray, ...], uv: np.ndarray) -> tuple[np.ndarray, ...]:
        """Per-node arrays (Gv, Gu, ...) at pixels uv (n, 2) (``_between_nodes``)."""
        return _between_nodes(self.node_u, self.node_v, self.interpolation, arrays, uv)

    def bundle(self, xy_n: np.ndarray, uv: np.ndarray | None = None) -> RayBundle:
        """Rays (n, K) of pixels with normalised coordinates xy_n (n, 2) and pixel
        coordinates uv (n, 2); uv may be omitted when the file has a camera matrix."""
        xy_n = np.asarray(xy_n, dtype=np.float64).reshape(-1, 2)
        if uv is None:
            if self.camera_matrix is None:
                raise LensFileError("MeasuredLens.bundle needs uv (pixel coordinates): the "
                                    "lens has no camera_matrix to compute them from xy_n")
            uv = normalized_to_pixel(xy_n, self.camera_matrix, self.dist_coeffs)
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if len(uv) != len(xy_n):
            raise LensFileError(f"MeasuredLens.bundle: xy_n has {len(xy_n)} rows but uv has "
                                f"{len(uv)}")
        t = _Transmitted(self.transmittance, self.weights)
        if self.aim_offset is None:
            x, y, w = self._at((self.aperture_x_mm, self.aperture_y_mm, t), uv)
            xy_aim = xy_n
        else:  # the offsets read with the samples (one bracketing of the nodes)
            x, y, w, e = self._at((self.aperture_x_mm, self.aperture_y_mm, t,
                                   self.aim_offset), uv)
            xy_aim = xy_n + e
        zf = np.broadcast_to(self.aim_depths(x, y), x.shape)
        aim = np.empty(x.shape + (3,))
        aim[..., :2] = xy_aim[:, None, :] * zf[..., None]
        aim[..., 2] = zf
        origins = np.zeros(x.shape + (3,))
        origins[..., 0] = x
        origins[..., 1] = y
        d = aim - origins
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return RayBundle(origins, d, w)


CAMERA_MATRIX_TOL_PX = 1e-3
"""A measured lens fits a rig camera whose K differs from its ``camera_matrix`` by at most this
(px, every element); distortion coefficients by at most ``1e-6``."""


def lens_camera_mismatch(lens: object, camera) -> str | None:
    """Why a lens cannot be used on the rig ``camera`` (a ``DeviceCalibration``), or None.

    A measured lens's nodes are pixels of the camera it was measured on, and its rays leave
    that camera's pixels through that camera's K: on a camera of another size, or with
    another K or distortion, every pixel would take another pixel's light, so such a use is
    refused rather than adapted (no adaptation is exact: the optical centre and the pupil
    samples were fitted against that K). Other lens models are not tied to a camera."""
    if not isinstance(lens, MeasuredLens):
        return None
    if tuple(lens.camera_size) != tuple(camera.size):
        return (f"the measured lens is for a {lens.camera_size[0]} x {lens.camera_size[1]} "
                f"camera, rig camera '{camera.name}' is {camera.size[0]} x {camera.size[1]}")
    if lens.camera_matrix is not None:
        d = float(np.max(np.abs(lens.camera_matrix - camera.K_array)))
        if d > CAMERA_MATRIX_TOL_PX:
            return (f"the measured lens was measured with camera matrix "
                    f"{np.round(lens.camera_matrix, 3).tolist()}, rig camera '{camera.name}' has "
                    f"{np.round(camera.K_array, 3).tolist()} (differs by {d:.3g} px): it was "
                    "measured on another camera, or the rig was recalibrated; measure the lens "
                    "with this camera's matrix")
    if lens.dist_coeffs is not None:
        d = float(np.max(np.abs(np.ravel(lens.dist_coeffs)[:5] - np.ravel(camera.dist)[:5])))
        if d > 1e-6:
            return (f"the measured lens's distortion {np.ravel(lens.dist_coeffs).tolist()} is not "
                    f"rig camera '{camera.name}''s {np.ravel(camera.dist).tolist()}")
    return None


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
    """The Gaussian defocus model of a measured lens (OPTICS.md section 7): its focus distance,
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
      centroids' noise drives the large-defocus sizes (benchmarks/README.md). The aim offsets
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


def aim_depths(focus_zones_mm: np.ndarray | None, focus_distance_mm: float,
               x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray | float:
    """Focus distance mm that aperture points (x_mm, y_mm) aim at: by pupil radius from the
    zones table (rows: radius mm, focus mm; linear between rows, clamped at the ends), or
    ``focus_distance_mm`` without one."""
    if focus_zones_mm is None:
        return focus_distance_mm
    return np.interp(np.hypot(x_mm, y_mm), focus_zones_mm[:, 0], focus_zones_mm[:, 1])


class _Transmitted:
    """``transmittance[..., None] * weights`` read node by node (``a[j, i]``), without the
    whole (Gv, Gu, K) product: the nodes a pixel reads are multiplied when read."""

    def __init__(self, transmittance: np.ndarray, weights: np.ndarray) -> None:
        self.t, self.w = transmittance, weights

    def __getitem__(self, index):
        return self.t[index][..., None] * self.w[index]


def _check_aim_offset(a: np.ndarray, gv: int, gu: int) -> None:
    """An aim offset field must be finite, of shape (Gv, Gu, 2)."""
    if a.shape != (gv, gu, 2):
        raise LensFileError(f"field 'aim_offset' must have shape ({gv}, {gu}, 2), got "
                            f"{a.shape}")
    _finite("aim_offset", a)


def _between_nodes(node_u: np.ndarray, node_v: np.ndarray, interpolation: str,
                   arrays: tuple[np.ndarray, ...], uv: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per-node arrays (Gv, Gu, ...) at pixels uv (n, 2): the nearest node, or bilinear
    between the four surrounding nodes (clamped at the border)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if interpolation == "nearest":
        i = np.abs(uv[:, 0, None] - node_u[None]).argmin(axis=1)
        j = np.abs(uv[:, 1, None] - node_v[None]).argmin(axis=1)
        return tuple(a[j, i] for a in arrays)
    i0, fu = _bracket(node_u, uv[:, 0])
    j0, fv = _bracket(node_v, uv[:, 1])
    i1 = np.minimum(i0 + 1, len(node_u) - 1)
    j1 = np.minimum(j0 + 1, len(node_v) - 1)
    fu, fv = fu[:, None], fv[:, None]
    return tuple((1 - fv) * ((1 - fu) * a[j0, i0] + fu * a[j0, i1])
                 + fv * ((1 - fu) * a[j1, i0] + fu * a[j1, i1]) for a in arrays)


def _bracket(nodes: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of the node at or left of x (clamped) and the fraction towards the next."""
    if len(nodes) == 1:
        return np.zeros(len(x), dtype=np.int64), np.zeros(len(x))
    xc = np.clip(x, nodes[0], nodes[-1])
    i = np.clip(np.searchsorted(nodes, xc, side="right") - 1, 0, len(nodes) - 2)
    return i, (xc - nodes[i]) / (nodes[i + 1] - nodes[i])


def _header(lens: MeasuredLens, node_u: np.ndarray, node_v: np.ndarray) -> dict:
    """The lens file's members before the per-sample arrays (format, scalars, nodes)."""
    return {"format": np.array(FORMAT),
            "format_version": np.array(FORMAT_VERSION, dtype=np.int64),
            "focus_distance_mm": np.array(lens.focus_distance_mm),
            "optical_centre_mm": lens.optical_centre_mm,
            "camera_size": np.array(lens.camera_size, dtype=np.int64),
            "node_u": node_u, "node_v": node_v}


def _trailer(lens: MeasuredLens, transmittance: np.ndarray) -> dict:
    """The lens file's members after the per-sample arrays (the optional ones if set)."""
    out = {"transmittance": transmittance, "interpolation": np.array(lens.interpolation),
           "metadata_json": np.array(json.dumps(lens.metadata))}
    for name in ("camera_matrix", "dist_coeffs", "focus_zones_mm", "aim_offset"):
        if getattr(lens, name) is not None:
            out[name] = getattr(lens, name)
    return out


def save_lens(path: str | Path, lens: MeasuredLens) -> Path:
    """Write a measured lens as one ``.npz`` (no pickle); returns the path written."""
    path = Path(path)
    arrays = {**_header(lens, lens.node_u, lens.node_v),
              "aperture_x_mm": lens.aperture_x_mm, "aperture_y_mm": lens.aperture_y_mm,
              "weights": lens.weights, **_trailer(lens, lens.transmittance)}
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    return path


class LensFileWriter:
    """Writes a lens file (format 1, the layout ``save_lens`` writes) node block by node block,
    so that a lens of any size is never held in memory: the per-node arrays go to ``.npy``
    files in ``<path>.partial/`` as blocks arrive (any order), then ``close`` validates the
    scalar fields and copies everything into one ZIP64 ``.npz`` (members stored, not
    compressed), fsyncs it and renames it to ``path``. ``abort`` removes what was written.

    node_u, node_v : node pixel columns and rows; samples : K.
    """

    NAMES = ("aperture_x_mm", "aperture_y_mm", "weights")
    COPY_BYTES = 1 << 24

    def __init__(self, path: str | Path, node_u: np.ndarray, node_v: np.ndarray,
                 samples: int) -> None:
        self.path = Path(path)
        self.node_u = np.asarray(node_u, dtype=np.float64)
        self.node_v = np.asarray(node_v, dtype=np.float64)
        self.shape = (len(self.node_v), len(self.node_u), int(samples))
        self.part = self.path.with_name(self.path.name + ".partial")
        if self.part.exists():
            import shutil

            shutil.rmtree(self.part)
        self.part.mkdir(parents=True)
        self._files = {}
        self._data_at = {}
        for name in self.NAMES:
            f = open(self.part / f"{name}.npy", "w+b")
            np.lib.format.write_array_header_2_0(
                f, {"descr": "<f8", "fortran_order": False, "shape": self.shape})
            self._data_at[name] = f.tell()
            f.truncate(self._data_at[name] + 8 * int(np.prod(self.shape)))
            self._files[name] = f

    def _offset(self, name: str, j: int, i: int) -> int:
        return self._data_at[name] + 8 * (j * self.shape[1] + i) * self.shape[2]

    def write_nodes(self, j0: int, i0: int, x: np.ndarray, y: np.ndarray,
                    w: np.ndarray) -> None:
        """Samples of the nodes [j0 : j0 + nj, i0 : i0 + ni]: x, y mm and weights, each
        (nj, ni, K). Weights must be finite, >= 0 and sum to 1 per node."""
        w = np.asarray(w, dtype=np.float64)
        k = self.shape[2]
        if w.ndim != 3 or w.shape[2] != k:
            raise LensFileError(f"{self.path}: node block of shape {w.shape}, expected (.., .., "
                                f"{k})")
        for name, a in zip(self.NAMES, (x, y, w)):
            _finite(name, np.asarray(a))
        if np.any(w < 0) or np.any(np.abs(w.sum(axis=2) - 1.0) > WEIGHT_SUM_TOL):
            raise LensFileError(f"{self.path}: field 'weights' of nodes from row {j0}, col {i0} "
                                "are negative or do not sum to 1")
        for name, a in zip(self.NAMES, (x, y, w)):
            a = np.ascontiguousarray(a, dtype="<f8")
            f = self._files[name]
            for r in range(a.shape[0]):
                os.pwrite(f.fileno(), a[r].tobytes(), self._offset(name, j0 + r, i0))

    def read_rows(self, j0: int, j1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The written samples x, y mm and weights (j1 - j0, Gu, K) of node rows j0:j1."""
        _, gu, k = self.shape
        out = []
        for name in self.NAMES:
            f = self._files[name]
            f.flush()
            buf = os.pread(f.fileno(), 8 * (j1 - j0) * gu * k, self._offset(name, j0, 0))
            out.append(np.frombuffer(buf, dtype="<f8").reshape(j1 - j0, gu, k))
        return out[0], out[1], out[2]

    def copy_nodes(self, dst: np.ndarray, src: np.ndarray) -> None:
        """Node (flat index) ``dst[n]`` takes the samples of node ``src[n]``, read back from
        the written ones (sources must not be among the destinations)."""
        nbytes = 8 * self.shape[2]
        gu = self.shape[1]
        for name in self.NAMES:
            fd = self._files[name].fileno()
            for d, s in zip(np.asarray(dst).tolist(), np.asarray(src).tolist()):
                buf = os.pread(fd, nbytes, self._offset(name, s // gu, s % gu))
                os.pwrite(fd, buf, self._offset(name, d // gu, d % gu))

    def close(self, *, focus_distance_mm: float, optical_centre_mm: np.ndarray,
              camera_size: tuple[int, int], transmittance: np.ndarray,
              interpolation: str = "bilinear", camera_matrix: np.ndarray | None = None,
              dist_coeffs: np.ndarray | None = None, metadata: dict | None = None,
              focus_zones_mm: np.ndarray | None = None,
              aim_offset: np.ndarray | None = None) -> Path:
        """Validate the scalar fields, write the ``.npz`` and return its path."""
        gv, gu, _ = self.shape
        # the scalar fields, validated by a one-node stand-in (the per-node arrays were
        # checked per block); then the node positions and the transmittance themselves
        lens = MeasuredLens(focus_distance_mm, optical_centre_mm, camera_size, [0.0], [0.0],
                            np.zeros((1, 1, 1)), np.zeros((1, 1, 1)), np.ones((1, 1, 1)),
                            np.ones((1, 1)), interpolation, camera_matrix, dist_coeffs,
                            metadata or {}, focus_zones_mm)
        w, h = lens.camera_size
        for name, a, size in (("node_u", self.node_u, w), ("node_v", self.node_v, h)):
            _finite(name, a)
            if a.ndim != 1 or len(a) < 1 or np.any(np.diff(a) <= 0) or a[0] < 0 \
                    or a[-1] > size - 1:
                raise LensFileError(f"{self.path}: field '{name}' must increase strictly within "
                                    f"[0, {size - 1}]")
        transmittance = np.asarray(transmittance, dtype=np.float64)
        if transmittance.shape != (gv, gu):
            raise LensFileError(f"{self.path}: field 'transmittance' must have shape ({gv}, "
                                f"{gu}), got {transmittance.shape}")
        _finite("transmittance", transmittance)
        if np.any(transmittance < 0):
            raise LensFileError(f"{self.path}: field 'transmittance' has negative values")
        if aim_offset is not None:
            aim_offset = np.asarray(aim_offset, dtype=np.float64)
            try:
                _check_aim_offset(aim_offset, gv, gu)
            except LensFileError as exc:
                raise LensFileError(f"{self.path}: {exc}") from exc
        small = _header(lens, self.node_u, self.node_v)
        tail = _trailer(lens, transmittance)
        if aim_offset is not None:
            tail["aim_offset"] = aim_offset
        tmp = self.path.with_name(self.path.name + ".tmp")
        with open(tmp, "wb") as raw:
            with zipfile.ZipFile(raw, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
                for name, a in small.items():
                    with zf.open(f"{name}.npy", "w", force_zip64=True) as m:
                        np.lib.format.write_array(m, np.asanyarray(a), allow_pickle=False)
                for name in self.NAMES:
                    f = self._files[name]
                    f.flush()
                    f.seek(0)
                    with zf.open(f"{name}.npy", "w", force_zip64=True) as m:
                        while chunk := f.read(self.COPY_BYTES):
                            m.write(chunk)
                for name, a in tail.items():
                    with zf.open(f"{name}.npy", "w", force_zip64=True) as m:
                        np.lib.format.write_array(m, np.asanyarray(a), allow_pickle=False)
            raw.flush()
            os.fsync(raw.fileno())
        os.replace(tmp, self.path)
        self.abort()
        return self.path

    def abort(self) -> None:
        """Close and remove the partial files."""
        import shutil

        for f in self._files.values():
            f.close()
        self._files = {}
        shutil.rmtree(self.part, ignore_errors=True)
        self.path.with_name(self.path.name + ".tmp").unlink(missing_ok=True)


def read_lens_nodes(path: str | Path,
                    nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples x, y mm and weights (n, K) of flat node indices ``nodes`` (row-major over
    (Gv, Gu)) of a lens file, times its transmittance, reading only those nodes where the
    members are stored uncompressed (``LensFileWriter``), the whole arrays otherwise."""
    nodes = np.asarray(nodes, dtype=np.int64).ravel()
    out = []
    with zipfile.ZipFile(path) as zf:
        for name in ("aperture_x_mm", "aperture_y_mm", "weights", "transmittance"):
            with zf.open(f"{name}.npy") as f:
                version = np.lib.format.read_magic(f)
                read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                        else np.lib.format.read_array_header_2_0)
                shape, fortran, dtype = read(f)
                per = int(np.prod(shape[2:], dtype=np.int64)) if len(shape) > 2 else 1
                if zf.getinfo(f"{name}.npy").compress_type != zipfile.ZIP_STORED or fortran:
                    a = np.lib.format.read_array(zf.open(f"{name}.npy")).reshape(-1, per)
                    out.append(a[nodes])
                    continue
                start = f.tell()
                rows = []
                for n in nodes.tolist():
                    f.seek(start + n * per * dtype.itemsize)
                    rows.append(np.frombuffer(f.read(per * dtype.itemsize), dtype=dtype))
                out.append(np.array(rows, dtype=np.float64).reshape(len(nodes), per))
    x, y, w, t = out
    return x, y, w * t


def _scalar(data: dict, name: str, kind: type):
    a = data[name]
    if a.shape != ():
        raise LensFileError(f"field '{name}' must be a scalar, got shape {a.shape}")
    try:
        return kind(a.item())
    except (TypeError, ValueError) as exc:
        raise LensFileError(f"field '{name}' is not a {kind.__name__}: {a.item()!r}") from exc


def load_lens(path: str | Path) -> MeasuredLens:
    """Read and validate a measured-lens file; errors name the file and the field."""
    path = Path(path)
    if not path.is_file():
        raise LensFileError(f"{path}: no such measured-lens file")
    if not zipfile.is_zipfile(path):
        raise LensFileError(f"{path}: not a readable measured-lens file: not a .npz archive "
                            "as `ltc lens` writes it")
    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
    except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, KeyError,
            NotImplementedError) as exc:  # NotImplementedError: an unknown zip compression
        raise LensFileError(f"{path}: not a readable measured-lens .npz file ({exc})") from exc
    try:
        missing = [k for k in REQUIRED if k not in data]
        if "format" in data and str(data["format"]) != FORMAT:
            raise LensFileError(f"field 'format' is {str(data['format'])!r}, expected {FORMAT!r}")
        if missing:
            raise LensFileError(f"missing field(s) {missing}")
        extra = sorted(set(data) - set(REQUIRED) - set(OPTIONAL))
        if extra:
            raise LensFileError(f"unknown field(s) {extra}")
        version = _scalar(data, "format_version", int)
        if version != FORMAT_VERSION:
            raise LensFileError(f"field 'format_version' is {version}; this reader supports "
                                f"version {FORMAT_VERSION}")
        meta = {}
        if "metadata_json" in data:
            try:
                meta = json.loads(_scalar(data, "metadata_json", str))
            except json.JSONDecodeError as exc:
                raise LensFileError(f"field 'metadata_json' is not JSON ({exc})") from exc
        for name in ("node_u", "node_v", "aperture_x_mm", "aperture_y_mm", "weights",
                     "transmittance", "optical_centre_mm", "camera_matrix", "dist_coeffs",
                     "focus_zones_mm", "aim_offset"):
            dtype = data[name].dtype if name in data else np.dtype(float)
            if not (np.issubdtype(dtype, np.floating) or np.issubdtype(dtype, np.integer)):
                raise LensFileError(f"field '{name}' must be real numbers, got dtype {dtype}")
        size = data["camera_size"]
        if not np.issubdtype(size.dtype, np.integer) or size.shape != (2,):
            raise LensFileError(f"field 'camera_size' must be 2 integers (width, height), got "
                                f"dtype {size.dtype}, shape {size.shape}")
        if not isinstance(meta, dict):
            raise LensFileError(f"field 'metadata_json' must hold a JSON object, got "
                                f"{type(meta).__name__}")
        return MeasuredLens(
            focus_distance_mm=_scalar(data, "focus_distance_mm", float),
            optical_centre_mm=data["optical_centre_mm"],
            camera_size=tuple(data["camera_size"].tolist()),
            node_u=data["node_u"], node_v=data["node_v"],
            aperture_x_mm=data["aperture_x_mm"], aperture_y_mm=data["aperture_y_mm"],
            weights=data["weights"], transmittance=data["transmittance"],
            interpolation=_scalar(data, "interpolation", str),
            camera_matrix=data.get("camera_matrix"), dist_coeffs=data.get("dist_coeffs"),
            metadata=meta, focus_zones_mm=data.get("focus_zones_mm"),
            aim_offset=data.get("aim_offset"),
        )
    except LensFileError as exc:
        raise LensFileError(f"{path}: {exc}") from exc
