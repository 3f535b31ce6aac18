"""One sample: a pure function from its scene description to numpy arrays.

Trace once, pattern many: each camera is traced once (``sim.render.images.render_camera``,
every lens ray's projector coordinate and weight) and every pattern of the set is gathered
from that one trace; the ground-truth maps come from the same trace's chief rays.

Per camera (``H x W`` pixels, ``n`` patterns, ``F`` phase-shift frequencies in the set's
order), with ``I_k = A + B cos(phi - 2 pi k / N)`` (Feng, Zuo et al. 2019):

====================  ==============  ===========================================================
``images``            (n, H, W)       the fringe images (uint8/uint16 DN, or float32 DN)
``numerator``         (F, H, W) f32   ``M = sum_k I_k sin(2 pi k / N)`` of the noise-free,
                                      unquantised images (DN)
``denominator``       (F, H, W) f32   ``D = sum_k I_k cos(2 pi k / N)``
``wrapped_phase``     (F, H, W) f32   ``atan2(M, D)`` in [0, 2 pi), rad
``background``        (F, H, W) f32   ``A = sum_k I_k / N``, DN
``modulation``        (F, H, W) f32   ``B = 2 sqrt(M^2 + D^2) / N``, DN
``absolute_phase``    (H, W) f32      ``2 pi u_p / p`` of the finest period ``p``, from the chief
                                      ray's projector coordinate (geometry, not the images), rad
``fringe_order``      (H, W) int32    ``floor(absolute_phase / 2 pi)``, -1 where none
``projector_uv``      (H, W, 2) f32   chief ray's projector pixel (u_p, v_p), NaN where none
``depth_mm``          (H, W) f32      chief ray's hit z in the camera frame, mm; NaN: nothing
``normals``           (H, W, 3) f32   unit surface normal, camera frame, facing the camera
``mask``              (H, W) uint8    0 nothing hit, 1 valid (lit), 2 shadowed, 3 outside the
                                      projector's image
====================  ==============  ===========================================================

The numerator and the rest are labels: computed from the noise-free radiance through the
camera's exposure, full well, gain and black level, before noise and rounding. With a
defocused lens they carry the defocus (the blur of the fringes), the geometric truth maps do
not: their difference is the defocus-induced phase error.
"""

from __future__ import annotations

import hashlib
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from sim.dataset import kernels
from sim.dataset.objects import Parts, from_file, procedural
from sim.dataset.randomise import MeasuredLensDraw, SampleObject, SampleScene
from sim.errors import SimInputError
from sim.optics.rig import DeviceCalibration
from sim.render.fringe_patterns import GrayCodeSet
from sim.render.images import project_patterns, render_camera
from sim.render.pattern_stack import ALONG_U, PatternStack
from sim.render.trace import TraceGeometry, normalized_grid

MASK_NONE, MASK_VALID, MASK_SHADOWED, MASK_OUTSIDE = 0, 1, 2, 3
CAMERA_KEYS = ("images", "numerator", "denominator", "wrapped_phase", "background",
               "modulation", "absolute_phase", "fringe_order", "projector_uv", "depth_mm",
               "normals", "mask")
TWO_PI = 2.0 * np.pi
POISSON_EXACT_BELOW_E = 64.0  # electrons: shot noise drawn exactly below, as a normal above


_SCRATCH = threading.local()


def _scratch(key: str, shape: tuple, dtype) -> np.ndarray:
    """A scratch array of this thread (its content undefined), reused from sample to sample:
    fresh pages cost a first touch each, as much as the pass that fills them."""
    cache = _SCRATCH.__dict__
    a = cache.get(key)
    if a is None or a.shape != tuple(shape) or a.dtype != np.dtype(dtype):
        a = cache[key] = np.empty(shape, dtype)
    return a


@dataclass
class Sample:
    """A generated sample: its scene and, per camera, the arrays of ``CAMERA_KEYS``."""

    scene: SampleScene
    cameras: list[dict[str, np.ndarray]]

    @property
    def index(self) -> int:
        return self.scene.index

    def checksum(self) -> str:
        """sha256 (hex) of the scene description and every array (name, dtype, shape, bytes)."""
        return checksum(self.scene.model_dump_json(), self.cameras)


def checksum(scene_json: str, cameras: list[dict[str, np.ndarray]]) -> str:
    """The sample checksum of a scene description (JSON text) and per-camera arrays."""
    h = hashlib.sha256(scene_json.encode())
    for i, cam in enumerate(cameras):
        for key in CAMERA_KEYS:
            a = np.ascontiguousarray(cam[key])
            h.update(f"{i}/{key}/{a.dtype.str}/{a.shape}".encode())
            h.update(a.data.cast("B"))
    return h.hexdigest()


def object_parts(obj: SampleObject) -> Parts:
    """An object of a sample in its normalised frame."""
    if obj.kind == "procedural":
        return procedural(obj.family or "", list(obj.seed or []), obj.size_mm)
    if obj.kind == "mesh":
        return from_file(Path(obj.path or ""), obj.size_mm)
    w, h = obj.extent_mm or (1.0, 1.0)
    v = np.array([[-w / 2, -h / 2, 0], [w / 2, -h / 2, 0], [w / 2, h / 2, 0], [-w / 2, h / 2, 0]])
    return Parts([trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)], np.zeros((0, 4)))


def scene_geometry(objects: list[SampleObject]) -> TraceGeometry:
    """Every object of a sample as one ``TraceGeometry`` (world mm; exact spheres kept)."""
    verts, faces, normals, albedo, obj_id, face_sph = [], [], [], [], [], []
    spheres: list[list[float]] = []  # rows (cx, cy, cz, r) mm
    nv = 0
    for i, o in enumerate(objects):
        parts = object_parts(o)
        R, t = np.asarray(o.pose.R), np.asarray(o.pose.t)
        first_sphere = len(spheres)
        for j, m in enumerate(parts.meshes):
            verts.append(np.asarray(m.vertices) @ R.T + t)
            normals.append(np.asarray(m.vertex_normals) @ R.T)
            faces.append(np.asarray(m.faces, dtype=np.int64) + nv)
            nv += len(m.vertices)
            nf = len(m.faces)
            albedo.append(np.full(nf, o.albedo))
            obj_id.append(np.full(nf, i, np.int32))
            face_sph.append(np.full(nf, first_sphere + j if len(parts.spheres) else -1, np.int64))
        for s in parts.spheres:
            spheres.append([*(R @ s[:3] + t), s[3]])
    return TraceGeometry(np.concatenate(verts), np.concatenate(faces), np.concatenate(normals),
                         np.concatenate(albedo), np.concatenate(obj_id),
                         np.asarray(spheres, dtype=np.float64).reshape(-1, 4),
                         np.concatenate(face_sph))


def build_lens(draw, camera: DeviceCalibration):
    """The lens model of a drawn lens (a measured lens file loaded and its pupil scaled)."""
    if not isinstance(draw, MeasuredLensDraw):
        return draw
    from dataclasses import replace

    from sim.optics.measured_lens import load_lens

    lens = _load_lens_cached(draw.path, load_lens)
    if tuple(lens.camera_size) != tuple(camera.size):
        raise SimInputError(f"lens file {draw.path} is for a {lens.camera_size} camera, camera "
                         f"'{camera.name}' is {tuple(camera.size)} (width, height)")
    if draw.pupil_scale == 1.0:
        return lens
    return replace(lens, aperture_x_mm=lens.aperture_x_mm * draw.pupil_scale,
                   aperture_y_mm=lens.aperture_y_mm * draw.pupil_scale)


_LENSES: dict[str, object] = {}


def _load_lens_cached(path: str, load):
    if path not in _LENSES:
        if len(_LENSES) >= 4:
            _LENSES.pop(next(iter(_LENSES)))
        _LENSES[path] = load(path)
    return _LENSES[path]


def phase_groups(scene: SampleScene) -> list[tuple[float, list[int], int]]:
    """(period px, image indices in shift order, N) of each phase-shift frequency, in the
    pattern set's order."""
    descs = scene.patterns.descriptors(scene.rig.projector.size)
    groups: dict[float, list] = {}
    for d in descs:
        if d.kind == "phase":
            assert d.period_px is not None, "a phase pattern has a period"
            groups.setdefault(float(d.period_px), []).append(d)
    return [(p, [d.index for d in sorted(ds, key=lambda d: d.shift)], ds[0].steps)
            for p, ds in groups.items()]


def _labels(radiance: np.ndarray, camera, groups) -> dict[str, np.ndarray]:
    """Feng/Zuo labels (F, H, W) float32 of the noise-free, unquantised images of radiance
    ``radiance`` (n, H, W) float32 through the camera's exposure, full well, gain and black
    level (compiled passes for the images and A; M and D by BLAS, numpy's arctan2 and
    hypot, as the numpy reference does)."""
    f32 = np.float32
    n_f = len(groups)
    shape = (n_f, *radiance.shape[1:])
    out = {k: np.empty(shape, f32) for k in ("numerator", "denominator", "wrapped_phase",
                                              "background", "modulation")}
    rad = radiance.reshape(len(radiance), -1)
    two_pi = f32(TWO_PI)
    for j, (_, idx, n) in enumerate(groups):
        d = TWO_PI * np.arange(n) / n
        dn = _scratch(f"dn{n}", (n, rad.shape[1]), f32)
        kernels.noise_free_dn(rad, np.asarray(idx, np.int64), f32(camera.exposure_e),
                              f32(camera.full_well_e), f32(camera.dn_per_e),
                              f32(camera.black_level_dn), dn)
        # M and D through BLAS as before (its summation order is its own, n > 4 shows it)
        out["numerator"][j] = np.tensordot(np.sin(d).astype(f32), dn, axes=1).reshape(shape[1:])
        out["denominator"][j] = np.tensordot(np.cos(d).astype(f32), dn,
                                             axes=1).reshape(shape[1:])
        kernels.mean(dn, f32(n), out["background"][j].reshape(-1))
        ph = out["wrapped_phase"][j]
        np.arctan2(out["numerator"][j], out["denominator"][j], out=ph)
        kernels.wrap_phase(ph.reshape(-1), two_pi)
        mod = out["modulation"][j]
        np.hypot(out["numerator"][j], out["denominator"][j], out=mod)
        np.multiply(f32(2.0 / n), mod, out=mod)
    return out


def _noisy_images(radiance: np.ndarray, camera, rng: np.random.Generator) -> np.ndarray:
    """The camera's digital images of noise-free radiance (n, H, W) float32 with shot and
    read noise (``sim.optics.sensor``'s model: Poisson electrons, full-well clip, Gaussian read
    noise, then gain, black level, clip and rounding). Dark pixels draw no Poisson deviate
    (Poisson(0) is 0); pixels of ``POISSON_EXACT_BELOW_E`` electrons or more draw shot and read
    noise as one normal deviate of their summed variance, then the full-well clip
    (``Sensor.expose_gaussian``'s approximation, 7x faster than Poisson), the others an exact
    Poisson deviate plus the read noise."""
    f32 = np.float32
    rad = np.ascontiguousarray(radiance, dtype=f32).reshape(-1)
    z = rng.standard_normal(dtype=f32, out=_scratch("z", (rad.size,), f32))
    quantize = bool(camera.quantize)
    dtype = (np.uint8 if camera.bit_depth == 8 else np.uint16) if quantize else f32
    out = np.empty(rad.size, dtype)
    low = _scratch("low", (rad.size,), np.int64)
    r2 = f32(camera.read_noise_e**2)
    k = kernels.expose(rad, z, f32(camera.exposure_e), r2, bool(camera.shot_noise),
                       f32(POISSON_EXACT_BELOW_E), f32(camera.full_well_e),
                       f32(camera.dn_per_e), f32(camera.black_level_dn), f32(camera.max_dn),
                       quantize, out, low)
    if k:
        idx = low[:k]
        e = rng.poisson(rad[idx] * f32(camera.exposure_e)).astype(f32) + np.sqrt(r2) * z[idx]
        e = np.minimum(e, f32(camera.full_well_e)) * f32(camera.dn_per_e) \
            + f32(camera.black_level_dn)
        dn = np.clip(e, f32(0.0), f32(camera.max_dn))
        out[idx] = np.rint(dn) if quantize else dn
    return out.reshape(radiance.shape)


def _normals(points: np.ndarray, obj: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) float32 of camera-frame points (H, W, 3) float32 from neighbour
    differences within the same object (central where both neighbours are, else one-sided),
    facing the camera; NaN where a pixel has no same-object neighbour along a row or a
    column."""
    out = np.empty(points.shape, np.float32)
    kernels.normals(np.ascontiguousarray(points, np.float32), np.ascontiguousarray(obj), out)
    return out


def _pixel_xy(cam: DeviceCalibration) -> np.ndarray:
    """Undistorted normalised coordinates (H, W, 2) of every pixel."""
    w, h = cam.size
    grid = normalized_grid(cam)
    if grid is not None:
        return grid.reshape(h, w, 2)
    K = cam.K_array
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    y = (v - K[1, 2]) / K[1, 1]
    return np.stack([(u - K[0, 2] - K[0, 1] * y) / K[0, 0], y], axis=-1)


def _camera_arrays(res, cam: DeviceCalibration, scene: SampleScene, groups) -> dict:
    c = scene.camera
    out = {"images": res.images, **_labels(res.radiance, c, groups)}
    fine = min(p for p, _, _ in groups)
    w, h = cam.size
    out["absolute_phase"] = np.empty((h, w), np.float32)
    out["fringe_order"] = np.empty((h, w), np.int32)
    out["projector_uv"] = np.empty((h, w, 2), np.float32)
    out["depth_mm"] = np.empty((h, w), np.float32)
    out["mask"] = np.empty((h, w), np.uint8)
    pts = np.empty((h, w, 3), np.float32)
    xy = np.ascontiguousarray(_pixel_xy(cam), np.float64)
    kernels.truth(np.ascontiguousarray(res.projector_map, np.float64).reshape(-1, 2),
                  np.ascontiguousarray(res.depth, np.float64).reshape(-1),
                  np.ascontiguousarray(res.object_id).reshape(-1),
                  np.ascontiguousarray(res.lit).reshape(-1), xy.reshape(-1, 2), float(fine),
                  TWO_PI, out["absolute_phase"].reshape(-1), out["fringe_order"].reshape(-1),
                  out["projector_uv"].reshape(-1, 2), out["depth_mm"].reshape(-1),
                  pts.reshape(-1, 3), out["mask"].reshape(-1))
    out["normals"] = _normals(pts, res.object_id)
    return out


def pattern_stack(scene: SampleScene) -> PatternStack:
    """The sample's patterns as rows (they vary along u only): the images of a one-row
    projector, exactly the rows of the full images, without making the full images."""
    w, h = scene.rig.projector.size
    rows = scene.patterns.images((w, 1))[:, 0, :]
    n = len(rows)
    return PatternStack((w, h), np.full(n, ALONG_U, np.int8), np.arange(n, dtype=np.int64),
                        np.zeros((0, h, w), np.float32), np.ascontiguousarray(rows),
                        np.zeros((0, h), np.float32))


def _render_scratch(i: int, cam: DeviceCalibration, n: int):
    """This thread's last rendering of camera ``i``, when it fits (name, size, patterns)."""
    res = _SCRATCH.__dict__.get(f"render{i}")
    w, h = cam.size
    if res is None or res.name != cam.name or res.radiance.shape != (n, h, w):
        return None
    return res


def render_sample(scene: SampleScene, geometry: TraceGeometry | None = None,
                  timings: dict[str, float] | None = None) -> Sample:
    """The arrays of a sample from its description alone (a pure function of ``scene``).
    ``timings``: seconds of each stage are added to it (``geometry_s``; ``trace_s`` and
    ``gather_s`` of the rendering, ``render_s`` its whole; ``noise_s``, ``labels_s``)."""
    clock = time.perf_counter
    t = {k: 0.0 for k in ("geometry_s", "trace_s", "gather_s", "render_s", "noise_s",
                          "labels_s")}
    t0 = clock()
    rig = scene.rig
    geom = geometry if geometry is not None else scene_geometry(scene.objects)
    t["geometry_s"] = clock() - t0
    projected = project_patterns(pattern_stack(scene), scene.projector)
    groups = phase_groups(scene)
    if not groups:
        raise SimInputError("the pattern set has no phase-shift images")
    if isinstance(scene.patterns, GrayCodeSet):
        groups = groups[:1]
    noisy = scene.camera.sensor.noisy
    quiet = scene.camera.model_copy(update={"shot_noise": False, "read_noise_e": 0.0})

    cams = []
    for i, cam in enumerate(rig.cameras):
        lens = build_lens(scene.lenses[i], cam)
        t0 = clock()
        # its outputs are scratch (reused) when the images are the noisy ones made here
        res = render_camera(geom, rig, i, lens, projected, quiet, None,
                            where=f"sample {scene.index}",
                            out=_render_scratch(i, cam, len(projected)) if noisy else None)
        t1 = clock()
        arrays = _camera_arrays(res, cam, scene, groups)
        t2 = clock()
        if noisy:  # (res.images, scratch, are the noise-free ones: not part of the sample)
            _SCRATCH.__dict__[f"render{i}"] = res
            arrays["images"] = _noisy_images(res.radiance, scene.camera,
                                             np.random.default_rng([*scene.noise_seed, i]))
        cams.append(arrays)
        t["render_s"] += t1 - t0
        t["trace_s"] += res.timings.get("trace_s", 0.0)
        t["gather_s"] += res.timings.get("gather_s", 0.0)
        t["labels_s"] += t2 - t1
        t["noise_s"] += clock() - t2
    if timings is not None:
        for k, v in t.items():
            timings[k] = timings.get(k, 0.0) + v
    return Sample(scene, cams)


def generate_sample(cfg, rig, index: int) -> Sample:
    """Sample ``index`` of a data set: its scene drawn from (config, seed, index), rendered."""
    from sim.dataset.randomise import draw_scene

    return render_sample(draw_scene(cfg, rig, index))
