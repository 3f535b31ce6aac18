"""The lens file of a :class:`sim.optics.measured_lens.MeasuredLens`.

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

Written durably (temporary file, fsync, rename: :mod:`sim.storage.durable`), by
:func:`save_lens` whole or by :class:`LensFileWriter` node block by node block.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from sim.optics.measured_lens import (
    FORMAT,
    FORMAT_VERSION,
    OPTIONAL,
    REQUIRED,
    LensFileError,
    MeasuredLens,
    _check_aim_offset,
    _finite,
    lens_camera_mismatch,
)
from sim.storage.durable import durable_file
from sim.tolerances import WEIGHT_SUM_TOL


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
    with durable_file(path, "wb") as f:
        np.savez_compressed(f, **arrays)
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
        self.existed = self.path.exists()  # checked again before the rename into place
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
        for name, a in zip(self.NAMES, (x, y, w), strict=True):
            _finite(name, np.asarray(a))
        if np.any(w < 0) or np.any(np.abs(w.sum(axis=2) - 1.0) > WEIGHT_SUM_TOL):
            raise LensFileError(f"{self.path}: field 'weights' of nodes from row {j0}, col {i0} "
                                "are negative or do not sum to 1")
        for name, a in zip(self.NAMES, (x, y, w), strict=True):
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
            for d, s in zip(np.asarray(dst).tolist(), np.asarray(src).tolist(), strict=True):
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
        lens = MeasuredLens(focus_distance_mm, optical_centre_mm, camera_size,
                            np.array([0.0]), np.array([0.0]),
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
        # an output that was not there when this writer started and is there now was
        # written by another writer meanwhile: refused, not replaced
        with durable_file(self.path, "wb", exclusive=not self.existed) as raw:
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
        self.abort()
        return self.path

    def abort(self) -> None:
        """Close and remove the partial files."""
        import shutil

        for f in self._files.values():
            f.close()
        self._files = {}
        shutil.rmtree(self.part, ignore_errors=True)


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


def load_lens_for(path: str | Path, camera) -> MeasuredLens:
    """``load_lens``, refused (``LensFileError`` naming the file) where the lens is not the rig
    ``camera``'s (a ``DeviceCalibration``: ``lens_camera_mismatch``)."""
    lens = load_lens(path)
    why = lens_camera_mismatch(lens, camera)
    if why is not None:
        raise LensFileError(f"lens file {path}: {why}")
    return lens
