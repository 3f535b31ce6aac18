"""The measured lens (docs/optics.md section 4): per pixel, or per node of
a grid of pixels, K aperture samples ``(x_k, y_k)`` mm on the plane of the optical centre with
weights ``w_k`` (sum 1), one focus distance ``z_f`` and, optionally, a focus distance per
pupil zone ``z(rho)`` (spherical aberration: ``focus_zones_mm``).

``MeasuredLens.bundle(xy_n, uv)`` casts ray k of a pixel from ``(x_k, y_k, 0)`` through the
pixel's in-focus point ``((x_n + e_x) z_k, (y_n + e_y) z_k, z_k)`` in the camera frame whose
origin is the optical centre (``z_k = z_f``, or with ``focus_zones_mm`` the zone's focus at
the sample's pupil radius ``rho_k = |(x_k, y_k)|``, linear between rows, clamped at the
ends; ``e`` the node's ``aim_offset``, 0 without one), with weight ``w_k * transmittance``
(relative transmittance: 1 for the brightest pixels, lower where the lens vignettes).
Samples between nodes: ``nearest`` node,
or ``bilinear`` (sample k of the four surrounding nodes blended; the derivation orders
samples the same way at every node, so sample k means the same part of the aperture).

The lens file (one ``.npz``, its fields and their checks) is :mod:`sim.optics.lens_file`; the
moments, the Gaussian equivalent and the smoothed lens are :mod:`sim.optics.lens_moments`.
Their public names stay importable from here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.errors import SimInputError
from sim.optics.lens import RayBundle
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
        from sim.optics.lens_file import save_lens

        return save_lens(path, self)

    @classmethod
    def load(cls, path: str | Path) -> MeasuredLens:
        """Read and validate a lens file (``load_lens``)."""
        from sim.optics.lens_file import load_lens

        return load_lens(path)

    @property
    def samples(self) -> int:
        """K, aperture samples per pixel."""
        return int(self.weights.shape[2])

    def samples_at(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Aperture samples of pixels uv (n, 2): x (n, K), y (n, K) mm and weights (n, K)
        times the relative transmittance."""
        t = _Transmitted(self.transmittance, self.weights)
        x, y, w = self._at((self.aperture_x_mm, self.aperture_y_mm, t), uv)
        return x, y, w

    def aim_offset_at(self, uv: np.ndarray) -> np.ndarray:
        """The aim offset (n, 2) of pixels uv (n, 2), read like the samples; 0 without one."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if self.aim_offset is None:
            return np.zeros((len(uv), 2))
        return self._at((self.aim_offset,), uv)[0]

    def _at(self, arrays: tuple[NodeArray, ...], uv: np.ndarray) -> tuple[np.ndarray, ...]:
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

    def __getitem__(self, index: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        return self.t[index][..., None] * self.w[index]


# a per-node array (Gv, Gu, ...) or what reads like one node by node (``a[j, i]``)
NodeArray = np.ndarray | _Transmitted


def _check_aim_offset(a: np.ndarray, gv: int, gu: int) -> None:
    """An aim offset field must be finite, of shape (Gv, Gu, 2)."""
    if a.shape != (gv, gu, 2):
        raise LensFileError(f"field 'aim_offset' must have shape ({gv}, {gu}, 2), got "
                            f"{a.shape}")
    _finite("aim_offset", a)


def _between_nodes(node_u: np.ndarray, node_v: np.ndarray, interpolation: str,
                   arrays: tuple[NodeArray, ...], uv: np.ndarray) -> tuple[np.ndarray, ...]:
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


_MOVED = {
    "lens_file": "save_lens load_lens read_lens_nodes LensFileWriter",
    "lens_moments": "centre_moments gaussian_equivalent smoothed_lens sample_moments sym_sqrtm "
                    "match_moments",
}
_MOVED_TO = {name: sub for sub, names in _MOVED.items() for name in names.split()}


def __getattr__(name: str) -> object:
    """The lens file's and the moments' names, from the modules that define them."""
    sub = _MOVED_TO.get(name)
    if sub is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"sim.optics.{sub}"), name)
