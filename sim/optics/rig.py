"""Calibrated FPP rig: two cameras and one projector with OpenCV intrinsics and extrinsics.

Conventions (docs/architecture.md): ``R, T`` map world to device, ``X_dev = R X_world + T`` (mm);
``K`` is the 3x3 intrinsic matrix, ``dist`` the OpenCV coefficients ``k1 k2 p1 p2 k3``; pixel
centres at integer coordinates, ``size = (width, height)``.

File formats (chosen by the extension):

- ``.json``: ``Rig.model_dump_json()``: ``{"cameras": [device, device], "projector": device}``,
  each device ``{"name", "K", "dist", "R", "T", "size"}``.
- ``.yaml`` / ``.yml`` / ``.xml``: OpenCV FileStorage, read and written with ``cv2.FileStorage``.
  Top-level maps ``camera_0``, ``camera_1`` and ``projector``, each holding the nodes
  ``name`` (string, optional: the node name when absent), ``image_width``, ``image_height``
  (int), ``camera_matrix`` (3x3), ``distortion_coefficients`` (5 values, 1x5 or 5x1), ``R``
  (3x3) and ``T`` (3 values, mm); a flat sequence of numbers is accepted for any matrix.
  The intrinsic node names are those written by OpenCV's calibration sample, so its output
  pastes in per device. A stereo calibration (``cv2.stereoCalibrate``: R, T from camera 0 to
  camera 1 or to the projector) drops in with the world frame on camera 0: its R = I, T = 0.
  Only the 5-coefficient distortion model is supported (rational and thin-prism models are
  refused with an error naming the node).
- The same FileStorage files in the names OpenCV's ``stereoCalibrate`` sample writes
  (``intrinsics.yml`` and ``extrinsics.yml`` pasted into one file): ``M1 D1`` (camera 0),
  ``M2 D2`` (camera 1), ``R T`` (camera 0 to camera 1), and the projector calibrated as a
  third camera against camera 0: ``M3 D3 R3 T3``. Sizes: ``image_width image_height`` (or
  ``imageSize`` / ``image_size`` = [width, height]) for the cameras, ``projector_width
  projector_height`` (or ``projector_size``) for the projector. The world frame is camera 0's.
  ``D1 D2 D3`` may hold 4, 5, 8, 12 or 14 coefficients; beyond the fifth they must be zero.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import ClassVar, overload

import cv2
import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from sim.errors import SimInputError
from sim.optics.projection import (
    camera_to_world,
    directions_to_world,
    pixel_to_normalized,
    project_points,
)
from sim.storage.durable import durable_file
from sim.tolerances import LOOK_AT_PARALLEL_TOL, ROTATION_TOL
from sim.validation import format_validation_error

YAML_SUFFIXES = (".yaml", ".yml", ".xml")
DEVICE_NODES = ("camera_0", "camera_1", "projector")
OPENCV_DTYPES = ("u", "c", "w", "s", "i", "f", "d")  # opencv-matrix element types, one channel


def _matrix(value, shape: tuple[int, ...], what: str) -> list:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise SimInputError(f"{what} must be {math.prod(shape)} numbers {shape}, got "
                            f"{value!r}") from None
    if a.size != math.prod(shape):
        raise SimInputError(f"{what} must have {math.prod(shape)} values {shape}, got shape "
                            f"{a.shape}")
    a = a.reshape(shape)
    if not np.all(np.isfinite(a)):
        raise SimInputError(f"{what} must be finite, got {a.tolist()}")
    return a.tolist()


class _Float64View:
    """Read-only attribute ``<field>_array``: the list field ``<field>`` as a float64 array."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.field = name.removesuffix("_array")

    @overload
    def __get__(self, obj: None, owner: type | None = None) -> _Float64View: ...

    @overload
    def __get__(self, obj: object, owner: type | None = None) -> np.ndarray: ...

    def __get__(self, obj: object | None, owner: type | None = None) -> _Float64View | np.ndarray:
        return self if obj is None else np.asarray(getattr(obj, self.field), dtype=np.float64)


class DeviceCalibration(BaseModel):
    """Intrinsics, distortion and pose of one camera or projector."""

    model_config = ConfigDict(extra="forbid", frozen=True, ignored_types=(_Float64View,))
    name: str = Field(min_length=1, description="device name, unique in the rig")
    K: list[list[float]] = Field(description="3x3 intrinsic matrix, pixels")
    dist: list[float] = Field(description="OpenCV distortion k1 k2 p1 p2 k3 (5 values)")
    R: list[list[float]] = Field(description="3x3 rotation, world to device")
    T: list[float] = Field(description="translation, world to device, mm (3 values)")
    size: tuple[int, int] = Field(description="(width, height) in pixels")

    @field_validator("K", "R", mode="before")
    @classmethod
    def _mat3(cls, v, info):
        return _matrix(v, (3, 3), info.field_name)

    @field_validator("dist", mode="before")
    @classmethod
    def _dist(cls, v):
        return _matrix(v, (5,), "dist (k1 k2 p1 p2 k3)")

    @field_validator("T", mode="before")
    @classmethod
    def _vec3(cls, v):
        return _matrix(v, (3,), "T")

    @model_validator(mode="after")
    def _check(self) -> DeviceCalibration:
        K = self.K_array
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise SimInputError(f"K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
                             f"got {self.K}")
        R = self.R_array
        if not np.allclose(R @ R.T, np.eye(3), atol=ROTATION_TOL) or np.linalg.det(R) <= 0:
            raise SimInputError("R must be a proper rotation matrix (R R^T = I, det +1), got "
                                f"{self.R}")
        if self.size[0] < 1 or self.size[1] < 1:
            raise SimInputError(f"size must be (width, height) >= 1 pixel, got {self.size}")
        return self

    K_array: ClassVar[_Float64View] = _Float64View()  # K, dist, R, T as float64 arrays
    dist_array: ClassVar[_Float64View] = _Float64View()
    R_array: ClassVar[_Float64View] = _Float64View()
    T_array: ClassVar[_Float64View] = _Float64View()

    @property
    def width(self) -> int:
        return self.size[0]

    @property
    def height(self) -> int:
        return self.size[1]

    @property
    def centre_world(self) -> np.ndarray:
        """Optical centre in world coordinates, (3,) mm: ``-R^T T``."""
        return camera_to_world(np.zeros(3), self.R_array, self.T_array)

    def to_device(self, points_world: np.ndarray) -> np.ndarray:
        """World points (n, 3) mm in the device frame, (n, 3) mm."""
        return np.asarray(points_world, dtype=np.float64) @ self.R_array.T + self.T_array

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """Pixels (n, 2) of world points (n, 3) mm, with distortion."""
        return project_points(points_world, self.K_array, self.dist_array, self.R_array, self.T_array)

    def normalized(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates (n, 2) of pixels (n, 2)."""
        return pixel_to_normalized(uv, self.K_array, self.dist_array)

    def pixel_rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pinhole rays of pixels (n, 2): world origins (n, 3) mm and unit directions (n, 3)."""
        xy = self.normalized(uv)
        d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        origins = np.broadcast_to(self.centre_world, d.shape).copy()
        return origins, directions_to_world(d, self.R_array)


    def backproject(self, uv: np.ndarray, depth_mm: np.ndarray) -> np.ndarray:
        """World points (n, 3) mm of pixels (n, 2) at device-frame depths ``z`` (n,) mm (e.g. a
        truth depth map); NaN depths give NaN points."""
        xy = self.normalized(uv)
        z = np.asarray(depth_mm, dtype=np.float64).reshape(-1, 1)
        return camera_to_world(np.concatenate([xy * z, z], axis=1), self.R_array, self.T_array)


class Rig(BaseModel):
    """Two cameras and one projector in one world frame."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    cameras: list[DeviceCalibration] = Field(min_length=2, max_length=2,
                                             description="the two cameras")
    projector: DeviceCalibration = Field(description="the projector (pattern pixels)")

    @model_validator(mode="after")
    def _unique_names(self) -> Rig:
        names = [c.name for c in self.cameras] + [self.projector.name]
        if len(set(names)) != len(names):
            raise SimInputError(f"device names must be unique, got {names}")
        return self

    @classmethod
    def load(cls, path: str | Path) -> Rig:
        """Read a rig from JSON or OpenCV FileStorage YAML/XML (see the module docstring)."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"rig file {path} not found")
        suffix = path.suffix.lower()
        if suffix == ".json":
            try:
                return cls.model_validate_json(path.read_bytes())
            except ValidationError as exc:
                raise SimInputError(format_validation_error(str(path), exc)) from exc
        if suffix in YAML_SUFFIXES:
            return _read_filestorage(path)
        raise SimInputError(f"rig file {path}: unknown extension '{path.suffix}', "
                         "expected .json, .yaml, .yml or .xml")

    def save(self, path: str | Path) -> None:
        """Write the rig as JSON or OpenCV FileStorage YAML/XML, chosen by the extension."""
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix == ".json":
            with durable_file(path) as f:
                f.write(self.model_dump_json(indent=2))
        elif suffix in YAML_SUFFIXES:
            _write_filestorage(self, path)
        else:
            raise SimInputError(f"rig file {path}: unknown extension '{path.suffix}', "
                         "expected .json, .yaml, .yml or .xml")


def _write_filestorage(rig: Rig, path: Path) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise OSError(f"rig file {path}: cannot open for writing")
    for node, dev in zip(DEVICE_NODES, [*rig.cameras, rig.projector], strict=True):
        fs.startWriteStruct(node, cv2.FileNode_MAP)
        fs.write("name", dev.name)
        fs.write("image_width", int(dev.width))
        fs.write("image_height", int(dev.height))
        fs.write("camera_matrix", dev.K_array)
        fs.write("distortion_coefficients", dev.dist_array.reshape(1, 5))
        fs.write("R", dev.R_array)
        fs.write("T", dev.T_array.reshape(3, 1))
        fs.endWriteStruct()
    fs.release()


def _path(where: str, key: str) -> str:
    return f"{where}/{key}" if where else key


def _node(parent: cv2.FileNode, key: str, path: Path, where: str) -> cv2.FileNode:
    node = parent.getNode(key)
    if node.empty() or node.isNone():
        raise SimInputError(f"rig file {path}: node '{_path(where, key)}' is missing")
    return node


def _node_matrix(parent: cv2.FileNode, key: str, path: Path, where: str, n: int) -> np.ndarray:
    """An opencv-matrix node, or a flat sequence of numbers, with ``n`` values."""
    node = _node(parent, key, path, where)
    if node.isSeq():
        m = _numbers(node, path, _path(where, key))
    elif node.isMap():
        # read rows, cols, dt and data here: OpenCV's FileNode.mat() aborts the process on
        # some malformed matrices (found by tests/sim/test_sim_opener_fuzz.py)
        at = _path(where, key)
        rows, cols = _node_int(node, "rows", path, at), _node_int(node, "cols", path, at)
        dt = node.getNode("dt")
        if not dt.isString() or dt.string() not in OPENCV_DTYPES:
            raise SimInputError(f"rig file {path}: node '{at}/dt' must be one of "
                             f"{', '.join(OPENCV_DTYPES)} (one channel)")
        m = _numbers(_node(node, "data", path, at), path, f"{at}/data")
        if rows < 0 or cols < 0 or rows * cols != m.size:
            raise SimInputError(f"rig file {path}: node '{at}' is not a valid opencv-matrix: rows "
                             f"{rows} x cols {cols} but "
                             f"{m.size} data values")
    else:
        raise SimInputError(f"rig file {path}: node '{_path(where, key)}' must be an opencv-matrix "
                            "or a sequence")
    if m is None or m.size != n:
        shape = None if m is None else m.shape
        raise SimInputError(f"rig file {path}: node '{_path(where, key)}' must have {n} values, "
                         f"got shape {shape}")
    return m.astype(np.float64).ravel()


def _numbers(node: cv2.FileNode, path: Path, where: str) -> np.ndarray:
    if not node.isSeq():
        raise SimInputError(f"rig file {path}: node '{where}' must be a sequence of numbers")
    items = [node.at(i) for i in range(node.size())]
    if not all(it.isReal() or it.isInt() for it in items):
        raise SimInputError(f"rig file {path}: node '{where}' must hold numbers only")
    return np.array([it.real() for it in items], dtype=np.float64)


def _node_int(parent: cv2.FileNode, key: str, path: Path, where: str) -> int:
    node = _node(parent, key, path, where)
    if not node.isInt():
        raise SimInputError(f"rig file {path}: node '{_path(where, key)}' must be an integer")
    return int(node.real())


STEREO_CALIBRATE_NODES = ("M1", "D1", "M2", "D2", "R", "T", "M3", "D3", "R3", "T3")


def _present(parent: cv2.FileNode, key: str) -> bool:
    node = parent.getNode(key)
    return not (node.empty() or node.isNone())


def _node_dist(parent: cv2.FileNode, key: str, path: Path) -> np.ndarray:
    """OpenCV distortion of 4, 5, 8, 12 or 14 coefficients as the 5 used (the rest must be 0)."""
    node = _node(parent, key, path, "")
    for n in (4, 5, 8, 12, 14):
        try:
            d = _node_matrix(parent, key, path, "", n)
        except ValueError:
            continue
        if np.any(d[5:] != 0):
            raise SimInputError(f"rig file {path}: node '{key}' has non-zero coefficients beyond k3 "
                             f"({d[5:].tolist()}): only k1 k2 p1 p2 k3 are supported")
        return np.concatenate([d, np.zeros(5)])[:5] if n == 4 else d[:5]
    shape = node.mat().shape if node.isMap() and node.mat() is not None else "?"
    raise SimInputError(f"rig file {path}: node '{key}' must have 4, 5, 8, 12 or 14 distortion "
                     f"coefficients, got shape {shape}")


def _node_size(fs: cv2.FileNode, names: tuple[str, str], joint: tuple[str, ...], path: Path,
               what: str) -> tuple[int, int]:
    if all(_present(fs, n) for n in names):
        return (_node_int(fs, names[0], path, ""), _node_int(fs, names[1], path, ""))
    for key in joint:
        if _present(fs, key):
            v = _node_matrix(fs, key, path, "", 2)
            return (int(v[0]), int(v[1]))
    raise SimInputError(f"rig file {path}: the {what} size is missing: give '{names[0]}' and "
                     f"'{names[1]}' (or '{joint[0]}' = [width, height])")


def _read_stereo_calibrate(fs: cv2.FileStorage, path: Path) -> Rig:
    """A rig in ``cv2.stereoCalibrate`` naming (see the module docstring)."""
    root = fs.root()
    missing = [k for k in STEREO_CALIBRATE_NODES if not _present(root, k)]
    if missing:
        raise SimInputError(f"rig file {path}: stereoCalibrate naming (M1 D1 M2 D2 R T, projector "
                         f"M3 D3 R3 T3) but node(s) {', '.join(missing)} missing")
    cam_size = _node_size(root, ("image_width", "image_height"), ("imageSize", "image_size"),
                          path, "camera")
    proj_size = _node_size(root, ("projector_width", "projector_height"), ("projector_size",),
                           path, "projector")
    eye, zero = np.eye(3), np.zeros(3)
    spec = [("camera_0", "M1", "D1", eye, zero, cam_size),
            ("camera_1", "M2", "D2", _node_matrix(root, "R", path, "", 9).reshape(3, 3),
             _node_matrix(root, "T", path, "", 3), cam_size),
            ("projector", "M3", "D3", _node_matrix(root, "R3", path, "", 9).reshape(3, 3),
             _node_matrix(root, "T3", path, "", 3), proj_size)]
    devices = []
    for name, m, d, r, t, size in spec:
        try:
            devices.append(DeviceCalibration(
                name=name, K=_node_matrix(root, m, path, "", 9).reshape(3, 3),
                dist=_node_dist(root, d, path), R=r, T=t, size=size))
        except ValidationError as exc:
            raise SimInputError(format_validation_error(f"rig file {path}: nodes {m} {d}", exc)) from exc
    fs.release()
    return Rig(cameras=devices[:2], projector=devices[2])


def _read_filestorage(path: Path) -> Rig:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # the binding wraps parse errors in SystemError
        cause = str(exc.__cause__ or exc).strip().splitlines()[-1]
        raise SimInputError(f"rig file {path}: not a readable OpenCV FileStorage file: "
                            f"{cause}") from exc
    try:
        return _rig_from_filestorage(fs, path)
    except (cv2.error, UnicodeDecodeError) as exc:  # a string node that is not UTF-8
        cause = " ".join(str(exc).split())
        raise SimInputError(f"rig file {path}: not a readable OpenCV FileStorage rig: "
                            f"{cause}") from exc
    finally:
        fs.release()


def _rig_from_filestorage(fs: cv2.FileStorage, path: Path) -> Rig:
    if not fs.root().isMap():
        raise SimInputError(f"rig file {path}: the top level must be a map of the nodes "
                         f"{', '.join(DEVICE_NODES)}")
    if _present(fs.root(), "M1") and not _present(fs.root(), "camera_0"):
        return _read_stereo_calibrate(fs, path)
    devices = []
    for where in DEVICE_NODES:
        dev = _node(fs.root(), where, path, "")
        if not dev.isMap():
            raise SimInputError(f"rig file {path}: node '{where}' must be a map")
        name_node = dev.getNode("name")
        if not (name_node.empty() or name_node.isNone() or name_node.isString()):
            raise SimInputError(f"rig file {path}: node '{where}/name' must be a string")
        fields = {
            "name": name_node.string() if name_node.isString() else where,
            "size": (_node_int(dev, "image_width", path, where),
                  _node_int(dev, "image_height", path, where)),
            "K": _node_matrix(dev, "camera_matrix", path, where, 9).reshape(3, 3),
            "dist": _node_matrix(dev, "distortion_coefficients", path, where, 5),
            "R": _node_matrix(dev, "R", path, where, 9).reshape(3, 3),
            "T": _node_matrix(dev, "T", path, where, 3),
        }
        try:
            devices.append(DeviceCalibration(**fields))
        except ValidationError as exc:
            raise SimInputError(format_validation_error(f"rig file {path}: node '{where}'", exc)) from exc
    try:
        return Rig(cameras=devices[:2], projector=devices[2])
    except ValidationError as exc:
        raise SimInputError(format_validation_error(f"rig file {path}", exc)) from exc


def look_at(centre_mm: np.ndarray, target_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-device ``R, T`` of a device at ``centre_mm`` (3,) whose optical axis points at
    ``target_mm`` (3,), image rows along world +y as far as possible (world y down)."""
    c = np.asarray(centre_mm, dtype=np.float64)
    z = np.asarray(target_mm, dtype=np.float64) - c
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    if np.linalg.norm(x) < LOOK_AT_PARALLEL_TOL:
        raise SimInputError("look_at: the optical axis is parallel to world y; choose another "
                            "target")
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ c


def _device(name: str, size: tuple[int, int], f_px: float, centre: np.ndarray,
            dist: list[float]) -> DeviceCalibration:
    R, T = look_at(centre, np.zeros(3))
    w, h = size
    K = [[f_px, 0.0, (w - 1) / 2], [0.0, f_px, (h - 1) / 2], [0.0, 0.0, 1.0]]
    return DeviceCalibration(name=name, K=K, dist=dist, R=R, T=T, size=size)


# Reference system (docs/optics.md section 1): 16 mm lenses on 3.45 um pixels, cameras 760 mm from the
# world origin (centre of the measurement volume) converging at +-15 degrees, projector between.
WORKING_DISTANCE_MM = 760.0
CAMERA_FOCAL_MM = 16.0
CAMERA_PITCH_MM = 0.00345
CONVERGENCE_DEG = 15.0
PROJECTOR_FOCAL_PX = 3040.0  # 1920 px cover ~480 mm at 760 mm
CAMERA_DIST = [-0.08, 0.12, 2e-4, -1e-4, 0.0]
PROJECTOR_DIST = [0.02, -0.03, 0.0, 0.0, 0.0]


def _scaled_rig(camera_size: tuple[int, int], projector_size: tuple[int, int], scale: float,
                distortion: bool) -> Rig:
    a = np.radians(CONVERGENCE_DEG)
    cam_c = [np.array([s * WORKING_DISTANCE_MM * np.sin(a), 0.0, -WORKING_DISTANCE_MM * np.cos(a)])
             for s in (-1.0, 1.0)]
    f_cam = CAMERA_FOCAL_MM / CAMERA_PITCH_MM * scale
    cd = CAMERA_DIST if distortion else [0.0] * 5
    pd = PROJECTOR_DIST if distortion else [0.0] * 5
    cams = [_device(n, camera_size, f_cam, c, cd) for n, c in zip(("left", "right"), cam_c, strict=True)]
    proj = _device("projector", projector_size, PROJECTOR_FOCAL_PX * scale,
                   np.array([0.0, 0.0, -WORKING_DISTANCE_MM]), pd)
    return Rig(cameras=cams, projector=proj)


def default_rig(distortion: bool = True) -> Rig:
    """The reference system: two 4096 x 2168 cameras (16 mm, 3.45 um pixels) at 760 mm,
    converging at +-15 degrees on the world origin, and a 1920 x 1080 projector between them.
    World frame: origin at the centre of the measurement volume, z away from the rig, y down."""
    return _scaled_rig((4096, 2168), (1920, 1080), 1.0, distortion)


def small_rig(scale: float = 0.04, distortion: bool = True) -> Rig:
    """``default_rig`` with every image size and focal length multiplied by ``scale``
    (0.04: cameras 164 x 87, projector 77 x 43): same poses, nearly the same fields of view."""
    if not 0 < scale <= 1:
        raise SimInputError(f"small_rig: scale must be in (0, 1], got {scale}")
    cam = (max(1, round(4096 * scale)), max(1, round(2168 * scale)))
    proj = (max(1, round(1920 * scale)), max(1, round(1080 * scale)))
    return _scaled_rig(cam, proj, scale, distortion)


def relative_to_camera_0(rig: Rig) -> Rig:
    """The same rig with the world frame moved onto camera 0 (its R = I, T = 0)."""
    R0, T0 = rig.cameras[0].R_array, rig.cameras[0].T_array
    devs = []
    for d in [*rig.cameras, rig.projector]:
        R = d.R_array @ R0.T
        devs.append(d.model_copy(update={"R": R.tolist(), "T": (d.T_array - R @ T0).tolist()}))
    return Rig(cameras=devs[:2], projector=devs[2])


def save_stereo_calibrate(rig: Rig, path: str | Path) -> None:
    """Write the rig in ``cv2.stereoCalibrate`` naming (module docstring): ``M1 D1 M2 D2 R T``
    (camera 0 to camera 1), ``M3 D3 R3 T3`` (camera 0 to the projector), ``image_width
    image_height`` and ``projector_width projector_height``; the world frame becomes camera 0's.
    Written to a temporary file beside ``path`` then renamed over it."""

    path = Path(path)
    if path.suffix.lower() not in YAML_SUFFIXES:
        raise ValueError(f"rig file {path}: stereoCalibrate naming needs .yaml, .yml or .xml")
    if tuple(rig.cameras[0].size) != tuple(rig.cameras[1].size):
        raise ValueError(f"rig file {path}: stereoCalibrate naming has one camera size, the "
                         f"cameras are {rig.cameras[0].size} and {rig.cameras[1].size}")
    rel = relative_to_camera_0(rig)
    fs = cv2.FileStorage(f"rig{path.suffix}", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    c0, c1, p = rel.cameras[0], rel.cameras[1], rel.projector
    fs.write("image_width", int(c0.width))
    fs.write("image_height", int(c0.height))
    fs.write("projector_width", int(p.width))
    fs.write("projector_height", int(p.height))
    for key, dev in (("1", c0), ("2", c1), ("3", p)):
        fs.write(f"M{key}", dev.K_array)
        fs.write(f"D{key}", dev.dist_array.reshape(1, 5))
    fs.write("R", c1.R_array)
    fs.write("T", c1.T_array.reshape(3, 1))
    fs.write("R3", p.R_array)
    fs.write("T3", p.T_array.reshape(3, 1))
    text = fs.releaseAndGetString()
    with durable_file(path) as f:
        f.write(text)
