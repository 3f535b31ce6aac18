"""Point clouds as PLY files: points, normals and per-point scalar fields.

Written as ``binary_little_endian`` with ``double x y z``, ``float nx ny nz`` and one ``float
scalar_<name>`` per extra (``scalar_quality`` and every entry of ``PointCloud.fields``, e.g.
``scalar_camera scalar_u scalar_v scalar_phase_error scalar_uncertainty_mm``): the ``scalar_``
prefix is what CloudCompare and most viewers pick up as scalar fields. Double coordinates keep
sub-micrometre detail far from the origin. Read: ASCII and binary PLY (either endianness)
whose first element is ``vertex`` with scalar properties ``x y z`` (any numeric type) and
optionally ``nx ny nz``, ``quality`` or ``scalar_quality``, and any other ``scalar_<name>``
(into ``fields[name]``); any later elements (faces) are ignored. Lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.errors import SimInputError
from sim.storage.durable import durable_file

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
MAX_HEADER_LINES = 10_000  # a header longer than this is not a PLY header
FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass(frozen=True)
class PointCloud:
    """Points (n, 3) mm in the world frame, with optional unit normals (n, 3), quality (n,) and
    named per-point fields (n,) (e.g. ``camera``, ``u``, ``v``: the reference camera and its
    pixel; ``modulation``; ``phase_error``; ``uncertainty_mm``)."""

    points: np.ndarray
    normals: np.ndarray | None = None
    quality: np.ndarray | None = None
    fields: dict[str, np.ndarray] = field(default_factory=dict)


def write_ply(path: str | Path, cloud: PointCloud) -> None:
    """Write ``cloud`` (points (n, 3), optional normals (n, 3), quality (n,) and fields) as
    binary PLY (see the module docstring)."""
    pts = np.asarray(cloud.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise SimInputError(f"write_ply {path}: points must be (n, 3), got shape {pts.shape}")
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    cols = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}
    if cloud.normals is not None:
        n = np.asarray(cloud.normals)
        if n.shape != pts.shape:
            raise SimInputError(f"write_ply {path}: normals have shape {n.shape}, points "
                                f"{pts.shape}")
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        cols.update(nx=n[:, 0], ny=n[:, 1], nz=n[:, 2])
    extras = dict(cloud.fields)
    if cloud.quality is not None:
        extras = {"quality": cloud.quality, **extras}
    for name, values in extras.items():
        q = np.asarray(values).ravel()
        if len(q) != len(pts):
            raise SimInputError(f"write_ply {path}: {len(q)} {name} values for {len(pts)} points")
        if not name.replace("_", "").isalnum():
            raise SimInputError(f"write_ply {path}: field name '{name}' must be letters, digits "
                                "and _")
        fields.append((f"scalar_{name}", "<f4"))
        cols[f"scalar_{name}"] = q
    rec = np.empty(len(pts), dtype=fields)
    for name, _ in fields:
        rec[name] = cols[name]
    names = {"<f8": "double", "<f4": "float"}
    header = ["ply", "format binary_little_endian 1.0", "comment written by sim.fpp.cloud",
              f"element vertex {len(pts)}"]
    header += [f"property {names[t]} {name}" for name, t in fields]
    header.append("end_header")
    with durable_file(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(rec.tobytes())


def _parse_header(f, path: Path) -> tuple[str, int, list[tuple[str, str]]]:
    if f.readline().strip() != b"ply":
        raise SimInputError(f"{path}: not a PLY file (no 'ply' magic line)")
    fmt, count, element = None, None, None
    props: list[tuple[str, str]] = []
    for number in range(2, MAX_HEADER_LINES):
        line = f.readline()
        if not line:
            raise SimInputError(f"{path}: PLY header has no end_header")
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        where = f"{path}: PLY header line {number} {' '.join(words)!r}"
        if words[0] == "format":
            fmt = words[1] if len(words) > 1 else ""
            if fmt not in FORMATS:
                raise SimInputError(f"{path}: unknown PLY format '{fmt}'")
        elif words[0] == "element":
            if len(words) != 3:
                raise SimInputError(f"{where}: expected 'element NAME COUNT'")
            if element is None and words[1] != "vertex":
                raise SimInputError(f"{path}: the first PLY element must be 'vertex', got "
                                    f"'{words[1]}'")
            element = words[1]
            if element == "vertex":
                if not words[2].isdigit():
                    raise SimInputError(f"{where}: the vertex count must be an integer >= 0")
                count = int(words[2])
        elif words[0] == "property" and element == "vertex":
            if len(words) >= 2 and words[1] == "list":
                raise SimInputError(f"{path}: list property '{words[-1]}' in the vertex element")
            if len(words) != 3:
                raise SimInputError(f"{where}: expected 'property TYPE NAME'")
            if words[1] not in PLY_TYPES:
                raise SimInputError(f"{path}: unknown PLY type '{words[1]}' of property "
                                    f"'{words[2]}'")
            if words[2] in [n for n, _ in props]:
                raise SimInputError(f"{path}: vertex property '{words[2]}' appears twice")
            props.append((words[2], PLY_TYPES[words[1]]))
    else:
        raise SimInputError(f"{path}: PLY header has no end_header in {MAX_HEADER_LINES} lines")
    if fmt is None or count is None:
        raise SimInputError(f"{path}: PLY header lacks a format line or a vertex element")
    if count == 0:
        raise SimInputError(f"{path}: the PLY file has 0 vertices; a point cloud needs at least one "
                         "point")
    return fmt, count, props


def _ascii_rows(f, path: Path, count: int, n: int) -> np.ndarray:
    """``count`` ASCII vertex rows of ``n`` values, read until the count or the end of the
    file (a count larger than the file never loops past its end)."""
    rows: list[list[bytes]] = []  # the split lines of a binary-mode file
    for line in f:
        if len(rows) == count:
            break
        values = line.split()
        if len(values) != n:
            raise SimInputError(f"{path}: vertex row {len(rows)} has {len(values)} values, the "
                             f"header declares {n} properties")
        rows.append(values)
    if len(rows) < count:
        raise SimInputError(f"{path}: file ends after {len(rows)} of {count} vertex rows")
    try:
        return np.array(rows, dtype=np.float64).reshape(count, n)
    except ValueError as exc:
        raise SimInputError(f"{path}: malformed ASCII vertex rows: {exc}") from exc


def read_ply(path: str | Path) -> PointCloud:
    """Read a PLY point cloud (see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"point cloud {path} not found")
    with open(path, "rb") as f:
        fmt, count, props = _parse_header(f, path)
        names = [n for n, _ in props]
        if not {"x", "y", "z"} <= set(names):
            raise SimInputError(f"{path}: the vertex element needs properties x, y and z, has "
                                f"{names}")
        byte_order = FORMATS[fmt]
        if byte_order is None:
            data = _ascii_rows(f, path, count, len(props))
            col = {n: data[:, i] for i, n in enumerate(names)}
        else:
            dt = np.dtype([(n, byte_order + t) for n, t in props])
            raw = f.read(dt.itemsize * count)
            if len(raw) < dt.itemsize * count:
                raise SimInputError(f"{path}: file ends after {len(raw) // dt.itemsize} of {count} "
                                    "vertices")
            rec = np.frombuffer(raw, dtype=dt)
            col = {n: rec[n].astype(np.float64) for n in names}
    pts = np.stack([col["x"], col["y"], col["z"]], axis=1)
    normals = np.stack([col["nx"], col["ny"], col["nz"]], axis=1) if {"nx", "ny", "nz"} <= set(col) else None
    quality = col.get("scalar_quality", col.get("quality"))
    extras = {n[len("scalar_"):]: v for n, v in col.items()
              if n.startswith("scalar_") and n != "scalar_quality"}
    return PointCloud(pts, normals, quality, extras)
