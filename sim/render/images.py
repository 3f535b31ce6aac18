"""Fringe images from a light transport: projector response, gather, camera response (the
writers are in ``sim.render.image_files`` and re-exported here).

Signal chain for pattern image ``P`` (values in [0, 1]) and camera pixel ``p``:

1. projector (``ProjectorResponse``): input quantised to ``input_bits``, then
   ``black + (1 - black) * P ** gamma``, then defocus: a Gaussian blur of ``defocus_sigma_px``
   projector pixels (edges replicated);
2. gather: ``radiance_p = sum_k w_k * P'(u_k, v_k)`` with ``P'`` sampled bilinearly (pixel
   centres at integers, clamped to the edge pixels) at each ray's projector coordinate;
3. camera (``CameraResponse``, the sensor model ``sim.optics.sensor`` shared with the fake
   station camera): electrons ``e = exposure_e * radiance``, Poisson shot noise,
   clipped at the full well, plus Gaussian read noise; ``DN = gain * (2^bits - 1) / full_well_e
   * e + black_level_dn``, clipped to ``[0, 2^bits - 1]`` (saturation) and rounded.

Radiance 1 is a white pattern on an albedo-1 surface facing the projector (N.L = 1) seen by an
unvignetted pixel; there is no distance fall-off (docs/optics.md section 3).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from tqdm import tqdm

from sim.errors import SimInputError
from sim.optics.lens import LensModel, hit_plane
from sim.optics.rig import Rig
from sim.optics.sensor import Sensor
from sim.render.image_files import write_png as write_png  # re-exported
from sim.render.image_files import write_pngs as write_pngs
from sim.render.image_files import write_zarr as write_zarr
from sim.render.image_kernels import BLOCK_RAYS, IDENTITY, digitise, gather_rows
from sim.render.pattern_stack import PatternStack
from sim.render.trace import TraceGeometry, Transport, trace_camera

TILE_RAYS = 1 << 22  # rays traced per tile in render_views (about 50 MB of transport)


class ProjectorResponse(BaseModel):
    """How the projector turns pattern values into light."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    input_bits: int | None = Field(8, ge=1, le=16,
                                   description="pattern quantisation, bits (None: exact)")
    gamma: float = Field(1.0, gt=0, description="light = value ** gamma")
    black_level: float = Field(0.0, ge=0, lt=1, description="light of a black pixel, fraction of white")
    defocus_sigma_px: float = Field(0.0, ge=0,
                                    description="Gaussian defocus of the image, projector px")


class CameraResponse(BaseModel):
    """Exposure, noise and digitisation of the cameras."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    exposure_e: float = Field(8000.0, ge=0,
                              description="electrons collected at radiance 1 in the exposure")
    full_well_e: float = Field(10000.0, gt=0, description="full-well capacity, electrons")
    gain: float = Field(1.0, gt=0, description="gain; 1 maps the full well to the largest DN")
    shot_noise: bool = Field(False, description="Poisson photon noise")
    read_noise_e: float = Field(0.0, ge=0, description="read noise, electrons rms")
    black_level_dn: float = Field(0.0, ge=0, description="offset added to every pixel, DN")
    bit_depth: Literal[8, 12, 16] = Field(8, description="output bits per pixel")
    quantize: bool = Field(True, description="round to integers (False: float32 DN)")

    @property
    def max_dn(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def dn_per_e(self) -> float:
        return self.gain * self.max_dn / self.full_well_e

    @property
    def sensor(self) -> Sensor:
        """The sensor model (``sim.optics.sensor``) of these cameras."""
        return Sensor(full_well_e=self.full_well_e, dn_per_e=self.dn_per_e,
                      black_level_dn=self.black_level_dn, bit_depth=self.bit_depth,
                      shot_noise=self.shot_noise, read_noise_e=self.read_noise_e)


class RenderSettings(BaseModel):
    """Projector and camera response of a rendering."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    projector: ProjectorResponse = Field(default_factory=ProjectorResponse)
    camera: CameraResponse = Field(default_factory=CameraResponse)


def project_patterns(patterns: np.ndarray | PatternStack,
                     projector: ProjectorResponse) -> PatternStack:
    """Projected light of pattern images (n, H, W) in [0, 1] (or their ``PatternStack``), each
    pattern kept in its cheapest exact form (a row or column profile where it varies along one
    axis only)."""
    stack = as_stack(patterns)
    lo, hi = stack.value_range()
    if not (lo >= 0 and hi <= 1):
        raise SimInputError(f"pattern values must lie in [0, 1], got [{lo:g}, {hi:g}]")
    if projector.input_bits is not None:
        q = np.float32((1 << projector.input_bits) - 1)
        stack = stack.map(lambda p: np.round(p * q) / q)
    if projector.gamma != 1:
        stack = stack.map(lambda p: p ** np.float32(projector.gamma))
    if projector.black_level > 0:
        b = np.float32(projector.black_level)
        stack = stack.map(lambda p: b + (1 - b) * p)
    s = projector.defocus_sigma_px
    if s > 0:
        k = 2 * math.ceil(4 * s) + 1
        stack = stack.map(lambda p: cv2.GaussianBlur(p, (k, k), s, sigmaY=s,
                                                     borderType=cv2.BORDER_REPLICATE))
    return stack


def as_stack(patterns: np.ndarray | PatternStack) -> PatternStack:
    """``patterns`` itself if it is a ``PatternStack``, else the stack of images (n, H, W)."""
    return patterns if isinstance(patterns, PatternStack) else PatternStack.from_images(patterns)


def _split(n: int, threads: int | None, min_part: int) -> list[tuple[int, int]]:
    """``[first, last)`` ranges splitting ``range(n)`` into parts of at least ``min_part``, a few
    per thread."""
    nt = threads or os.cpu_count() or 1
    step = max(min_part, -(-n // (4 * nt)))
    return [(a, min(a + step, n)) for a in range(0, n, step)]


def _run(kernel, parts: list[tuple[int, int]], threads: int | None, *args) -> None:
    """``kernel(*args, first, last)`` for every part, on ``threads`` threads (every core)."""
    if len(parts) <= 1:
        for a, b in parts:
            kernel(*args, a, b)
        return
    with ThreadPoolExecutor(threads or os.cpu_count() or 1) as ex:
        list(ex.map(lambda ab: kernel(*args, *ab), parts))


def _check_patterns(tr: Transport, projected: np.ndarray | PatternStack) -> PatternStack:
    stack = as_stack(projected)
    if stack.size != tuple(tr.projector_size):
        w, h = stack.size
        raise SimInputError(f"projected patterns are {w} x {h} px, expected the transport's "
                         f"{tr.projector_size[0]} x {tr.projector_size[1]} projector")
    return stack


def _check_array(what: str, a: np.ndarray, shape: tuple, dtype: type) -> None:
    """Raise if ``a`` is not a C-contiguous array of ``shape`` and ``dtype``; ``what`` names it."""
    want = f"{np.dtype(dtype).name} {tuple(shape)}"
    if not isinstance(a, np.ndarray) or a.shape != tuple(shape) or a.dtype != dtype \
            or not a.flags.c_contiguous:
        got = f"{a.dtype.name} {a.shape}" if isinstance(a, np.ndarray) else type(a).__name__
        raise SimInputError(f"{what}: expected a C-contiguous {want} array, got {got}")


def gather_into(tr: Transport, projected: np.ndarray | PatternStack, out: np.ndarray,
                threads: int | None = None) -> None:
    """Write the radiance of the transport's pixels for projected patterns (``project_patterns``,
    or images (n, Hp, Wp) of light) into ``out[:, tr.pixels]`` of images ``out`` (n, H * W)
    float32."""
    p = _check_patterns(tr, projected)
    _check_array("gather_into out", out, (len(p), tr.camera_size[0] * tr.camera_size[1]),
                 np.float32)
    _gather_rows(tr, tr.pixels, p, out, threads)


def gather(tr: Transport, projected: np.ndarray | PatternStack,
           threads: int | None = None) -> np.ndarray:
    """Radiance (n_patterns, n_pixels) float32 of the transport's pixels for projected patterns
    (``project_patterns``, or images (n, Hp, Wp) of light), on every core."""
    p = _check_patterns(tr, projected)
    n = len(tr.pixels)
    out = np.empty((len(p), n), np.float32)
    _gather_rows(tr, np.arange(n, dtype=np.int64), p, out, threads)
    return out


def _gather_rows(tr: Transport, dest: np.ndarray, stack: PatternStack, out: np.ndarray,
                 threads: int | None, resp: tuple = IDENTITY, quantize: bool = False) -> None:
    """``gather_rows`` over every row of the transport on every core; row i goes to column
    ``dest[i]`` of ``out`` through ``response(radiance, *resp)``, rounded if ``quantize``."""
    rows = max(1, BLOCK_RAYS // tr.weight.shape[1])
    c = np.ascontiguousarray
    _run(gather_rows, _split(len(dest), threads, rows), threads, dest, tr.proj_uv, tr.weight,
         stack.form, stack.slot, c(stack.full), c(stack.rows), c(stack.cols), resp, quantize, out)


def _response_args(camera: CameraResponse, electrons: bool = False) -> tuple:
    """Arguments of ``sim.render.image_kernels.response`` for the camera (rounding is
    ``camera.quantize``): from radiance, or from electrons already exposed and clipped
    (``electrons``)."""
    f32 = np.float32
    scale, low, high = ((f32(1.0), f32(-np.inf), f32(np.inf)) if electrons else
                        (f32(camera.exposure_e), f32(0.0), f32(camera.full_well_e)))
    return scale, low, high, f32(camera.dn_per_e), f32(camera.black_level_dn), f32(camera.max_dn)


def _image_dtype(camera: CameraResponse) -> type:
    return np.float32 if not camera.quantize else np.uint8 if camera.bit_depth == 8 else np.uint16


def camera_response(radiance: np.ndarray, camera: CameraResponse,
                    rng: np.random.Generator | None = None, threads: int | None = None,
                    out: np.ndarray | None = None) -> np.ndarray:
    """Digital images (same shape) of radiance: uint8 (8 bits), uint16 (12, 16) or float32 DN;
    written into ``out`` (C-contiguous, that shape and type) when given."""
    sensor = camera.sensor
    noisy = sensor.noisy
    if noisy and rng is None:
        raise SimInputError("camera_response: rng is required when shot_noise or read_noise_e is "
                            "on")
    x = np.ascontiguousarray(radiance, dtype=np.float32)
    if noisy:
        e = np.maximum(x * np.float32(camera.exposure_e), np.float32(0.0))
        x = np.ascontiguousarray(sensor.expose(e, rng, np.float32))
    if out is None:
        out = np.empty(x.shape, _image_dtype(camera))
    else:
        _check_array("camera_response out", out, x.shape, _image_dtype(camera))
    _run(digitise, _split(x.size, threads, 1 << 16), threads, x.reshape(-1),
         _response_args(camera, electrons=noisy), camera.quantize, out.reshape(-1))
    return out


def render(tr: Transport, pattern_images: np.ndarray | PatternStack, settings: RenderSettings,
           rng: np.random.Generator | None = None) -> np.ndarray:
    """Camera images (n, H, W) of a transport for pattern images (n, Hp, Wp) in [0, 1] (or their
    ``PatternStack``); pixels the transport does not cover get radiance 0. A noise-free camera's
    response is applied as the radiance is gathered (the same values as ``camera_response``)."""
    projected = _check_patterns(tr, project_patterns(pattern_images, settings.projector))
    w, h = tr.camera_size
    cam = settings.camera
    if cam.sensor.noisy:
        rad = np.zeros((len(projected), w * h), np.float32)
        gather_into(tr, projected, rad)
        return camera_response(rad.reshape(-1, h, w), cam, rng)
    resp = _response_args(cam)
    shape, dtype = (len(projected), w * h), _image_dtype(cam)
    out: np.ndarray = np.empty(shape, dtype)
    if len(tr.pixels) < w * h:  # the response to radiance 0
        out[:] = camera_response(np.zeros(1, np.float32), cam, None, 1)[0]
    _gather_rows(tr, tr.pixels, projected, out, None, resp, cam.quantize)
    return out.reshape(-1, h, w)


@dataclass
class CameraImages:
    """One camera's rendering: images (n, H, W), noise-free radiance (n, H, W) float32, truth
    maps (see ``Transport``), timings in seconds and the number of rays traced."""

    name: str
    images: np.ndarray
    radiance: np.ndarray
    depth: np.ndarray
    projector_map: np.ndarray
    lit: np.ndarray
    object_id: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    n_rays: int = 0
    transport: tuple[Transport, ...] | None = None  # the traced tiles, when kept (render_camera)


@dataclass
class RenderResult:
    """Every camera's rendering, and timings (s) of what is shared (``patterns_s``, ``total_s``)."""

    cameras: list[CameraImages]
    timings: dict[str, float] = field(default_factory=dict)


def render_camera(geom: TraceGeometry, rig: Rig, index: int, lens: LensModel,
                  projected: np.ndarray | PatternStack,
                  camera: CameraResponse, rng: np.random.Generator | None, progress: bool = False,
                  where: str = "scene", out: CameraImages | None = None,
                  transport: Transport | Sequence[Transport] | None = None,
                  keep_transport: bool = False) -> CameraImages:
    """Trace camera ``index`` of the rig tile by tile (``TILE_RAYS`` rays: memory stays bounded
    whatever the lens), gather the projected patterns (``project_patterns``) from each tile's
    transport, then apply the camera response. Errors name ``where``.

    ``keep_transport``: the result keeps the traced tiles in ``.transport`` (memory then grows
    with the lens's rays). ``transport``: such tiles (or one ``Transport``) of this camera
    covering every pixel, from an earlier call with the same scene, lens and projector: nothing
    is traced, the patterns are gathered from it (trace once, render many pattern sets; the
    result carries it on).

    ``out``: an earlier result of the same camera, pattern count and camera response, whose
    arrays are overwritten and which is returned: a sequence of renders (scene poses, lenses)
    then reuses its memory instead of asking the system for some 300 MB of fresh pages a
    full-size render (their first touch can cost as much as the gather)."""
    projected = as_stack(projected)
    cam = rig.cameras[index]
    w, h = cam.size
    res = _camera_outputs(out, cam.name, len(projected), w, h, _image_dtype(camera))
    rad = res.radiance.reshape(len(projected), w * h)
    depth, pmap = res.depth.reshape(-1), res.projector_map.reshape(-1, 2)
    lit, obj = res.lit.reshape(-1), res.object_id.reshape(-1)
    tiles = _transport_tiles(transport, cam.name, (w, h), rig.projector.size)
    t_trace = t_gather = 0.0
    n_rays = 0
    bar = tqdm(total=w * h, desc=f"render {cam.name}", unit="px", unit_scale=True,
               disable=not progress)
    kept: list[Transport] = []
    pixels, dark = None, None
    if tiles is None:
        pixels, dark = _pixels_to_trace(geom, rig, index, lens)
        if dark is not None:  # the pixels no lens ray can bring light to: the chief pass's
            rad[:, dark.pixels] = 0.0
            p = dark.pixels
            depth[p], pmap[p], lit[p], obj[p] = dark.depth, dark.proj_chief, dark.lit, \
                dark.object_id
            t_trace, n_rays = dark.seconds, dark.rays
            if keep_transport:
                kept.append(dark)
            bar.update(len(p))
    for tr in tiles if tiles is not None else _traced_tiles(geom, rig, index, lens, pixels):
        if tiles is None and geom.boards:  # printed calibration boards (sim.render.board)
            from sim.render.board import apply_boards

            apply_boards(tr, geom.boards, cam, rig.projector)
        t0 = time.perf_counter()
        gather_into(tr, projected, rad)
        t_gather += time.perf_counter() - t0
        t_trace += tr.seconds if tiles is None else 0.0
        n_rays += tr.rays
        p = tr.pixels
        depth[p], pmap[p], lit[p], obj[p] = tr.depth, tr.proj_chief, tr.lit, tr.object_id
        if keep_transport and tiles is None:
            kept.append(tr)
        bar.update(len(tr.pixels))
    bar.close()
    if not np.any(obj >= 0):
        raise SimInputError(f"{where}: camera {index} ('{cam.name}') sees none of the scene objects; "
                         "check the rig's R and T (field 'rig') and the objects' poses")
    t0 = time.perf_counter()
    camera_response(res.radiance, camera, rng, out=res.images)
    res.timings = {"trace_s": t_trace, "gather_s": t_gather,
                   "response_s": time.perf_counter() - t0}
    res.n_rays = n_rays
    res.transport = tiles if tiles is not None else tuple(kept) if keep_transport else None
    return res


def _traced_tiles(geom: TraceGeometry, rig: Rig, index: int, lens: LensModel,
                  pixels: np.ndarray | None = None):
    """The transports of camera ``index``, tile by tile (``TILE_RAYS`` rays each), in pixel
    order; they cover the frame, or the flat pixel indices ``pixels``."""
    cam = rig.cameras[index]
    w, h = cam.size
    pix = np.arange(w * h, dtype=np.int64) if pixels is None else pixels
    k = lens.bundle(np.zeros((1, 2)), np.zeros((1, 2))).weights.shape[1]
    step = max(1, TILE_RAYS // (k + 1))
    for s in range(0, len(pix), step):
        yield trace_camera(geom, cam, rig.projector, lens, pixels=pix[s : s + step])


def _subset(tr: Transport, rows: np.ndarray) -> Transport:
    """The transport of some of its pixels (row indices)."""
    return Transport(tr.camera_size, tr.projector_size, tr.pixels[rows], tr.proj_uv[rows],
                     tr.weight[rows], tr.depth[rows], tr.proj_chief[rows], tr.lit[rows],
                     tr.object_id[rows], tr.seconds, tr.rays)


def blur_reach_px(camera, lens: LensModel, z_mm: tuple[float, float], step_px: int = 8) -> float:
    """How far from its pixel (px, through the pinhole) a lens ray of weight > 0 can cross any
    depth in ``z_mm`` (camera frame, both > 0): the largest such distance over a grid of
    pixels every ``step_px`` (and the last row and column) and, for a measured lens, every
    node. A ray's offset from its pixel's chief ray is affine in depth, so seen from the
    pinhole it is largest at one of the two depths."""
    from sim.optics.projection import pixel_to_normalized

    w, h = camera.size
    us = np.unique(np.r_[np.arange(0, w, step_px), w - 1])
    vs = np.unique(np.r_[np.arange(0, h, step_px), h - 1])
    uv = np.stack(np.meshgrid(us, vs), axis=-1).reshape(-1, 2).astype(np.float64)
    if hasattr(lens, "node_u") and hasattr(lens, "node_v"):  # a measured lens: every node too
        # (pixels between nodes interpolate their rays, whose offsets are then bounded by the nodes')
        nodes = np.stack(np.meshgrid(lens.node_u, lens.node_v), axis=-1).reshape(-1, 2)
        uv = np.concatenate([uv, nodes.astype(np.float64)])
    f = np.abs(np.diag(camera.K_array)[:2])
    k = lens.bundle(np.zeros((1, 2)), np.zeros((1, 2))).weights.shape[1]
    per = max(1, (1 << 20) // k)
    reach = 0.0
    for a in range(0, len(uv), per):
        xy = pixel_to_normalized(uv[a : a + per], camera.K_array, camera.dist_array)
        b = lens.bundle(xy, uv[a : a + per])
        ok = b.weights > 0
        for z in z_mm:
            with np.errstate(divide="ignore", invalid="ignore"):
                off = (hit_plane(b.origins, b.directions, z) / z - xy[:, None, :]) * f
            d = np.hypot(off[..., 0], off[..., 1])
            if np.any(ok & ~np.isfinite(d)):
                return math.inf
            if np.any(ok):
                reach = max(reach, float(d[ok].max()))
    return reach


REACH_MARGIN = (1.25, 2.0)  # the traced region: blur_reach_px x 1.25 + 2 px around the scene


def _pixels_to_trace(geom: TraceGeometry, rig: Rig, index: int, lens: LensModel):
    """(pixels, dark): the flat pixels whose lens rays can meet the scene and the chief-ray
    transport of the others, or (None, None) to trace every pixel (a pinhole lens, a scene
    reaching the camera's plane, or nothing in view).

    Every pixel's chief ray is traced; a lens ray of weight > 0 crosses the scene's depths
    within ``blur_reach_px`` of its pixel, where the chief ray of the pixel it is seen at
    meets the scene (up to the pixel grid at the silhouette: ``REACH_MARGIN``). So pixels
    farther than that from every pixel whose chief ray meets the scene receive no light, and
    are not traced with the lens: their radiance is 0 and their truth maps are the chief
    ray's, as a full trace would give them."""
    from scipy.ndimage import distance_transform_edt

    from sim.optics.lens import PinholeLens

    if isinstance(lens, PinholeLens):
        return None, None
    cam = rig.cameras[index]
    z = cam.to_device(geom.vertices)[:, 2]
    z_lo, z_hi = float(z.min()), float(z.max())
    if len(geom.spheres):
        zc = cam.to_device(geom.spheres[:, :3])[:, 2]
        z_lo = min(z_lo, float((zc - geom.spheres[:, 3]).min()))
        z_hi = max(z_hi, float((zc + geom.spheres[:, 3]).max()))
    if z_lo <= 0:
        return None, None
    w, h = cam.size
    chief = trace_camera(geom, cam, rig.projector, PinholeLens())
    seen = (chief.object_id >= 0).reshape(h, w)
    if not seen.any():
        return None, None
    reach = blur_reach_px(cam, lens, (z_lo, z_hi)) * REACH_MARGIN[0] + REACH_MARGIN[1]
    if not math.isfinite(reach):
        return None, None
    near = (distance_transform_edt(~seen) <= reach).ravel()
    return np.flatnonzero(near), _subset(chief, np.flatnonzero(~near))


def _transport_tiles(transport: Transport | Sequence[Transport] | None, name: str,
                     camera_size: tuple[int, int],
                     projector_size: tuple[int, int]) -> tuple[Transport, ...] | None:
    """``transport`` as a tuple of tiles, checked to be of this camera and projector and to
    cover each of the camera's pixels once; None stays None."""
    if transport is None:
        return None
    tiles = (transport,) if isinstance(transport, Transport) else tuple(transport)
    w, h = camera_size
    seen = np.zeros(w * h, np.int64)
    for tr in tiles:
        if tuple(tr.camera_size) != tuple(camera_size) or \
                tuple(tr.projector_size) != tuple(projector_size):
            raise SimInputError(f"render_camera transport: it is of a {tr.camera_size} camera and "
                             f"{tr.projector_size} projector, camera '{name}' is {camera_size} "
                             f"and the projector {projector_size}")
        np.add.at(seen, tr.pixels, 1)
    if not np.all(seen == 1):
        raise SimInputError(f"render_camera transport: its tiles must cover each pixel of camera "
                         f"'{name}' once ({int(np.sum(seen == 0))} missing, "
                         f"{int(np.sum(seen > 1))} repeated)")
    return tiles


def _camera_outputs(out: CameraImages | None, name: str, n: int, w: int, h: int,
                    dtype: type) -> CameraImages:
    """``out``, checked against camera ``name`` of ``w`` x ``h`` px, ``n`` patterns and image
    type ``dtype``; or new arrays for it."""
    shapes = {"images": ((n, h, w), dtype), "radiance": ((n, h, w), np.float32),
              "depth": ((h, w), np.float64), "projector_map": ((h, w, 2), np.float64),
              "lit": ((h, w), np.bool_), "object_id": ((h, w), np.int32)}
    if out is None:
        new: dict[str, np.ndarray] = {key: np.empty(*sd) for key, sd in shapes.items()}
        return CameraImages(name, images=new["images"], radiance=new["radiance"],
                            depth=new["depth"], projector_map=new["projector_map"],
                            lit=new["lit"], object_id=new["object_id"])
    if out.name != name:
        raise SimInputError(f"render_camera out: it holds camera '{out.name}', not '{name}'")
    for key, (shape, dt) in shapes.items():
        _check_array(f"render_camera out, field '{key}' of camera '{name}'", getattr(out, key),
                     shape, dt)
    return out


def render_views(geom: TraceGeometry, rig: Rig, lenses: list[LensModel], pattern_images: np.ndarray,
                 settings: RenderSettings, rng: np.random.Generator | None = None,
                 progress: bool = False, where: str = "scene") -> RenderResult:
    """Render pattern images (n, Hp, Wp) in [0, 1] (or their ``PatternStack``) on every camera
    of ``rig`` with one lens per camera: images plus timings (``patterns_s``, ``total_s``; per
    camera ``trace_s``, ``gather_s``, ``response_s``). Errors name ``where``."""
    t0 = time.perf_counter()
    if len(lenses) != len(rig.cameras):
        raise SimInputError(f"{where}: {len(lenses)} lenses for {len(rig.cameras)} cameras")
    stack = as_stack(pattern_images)
    if stack.size != tuple(rig.projector.size):
        raise SimInputError(f"{where}: pattern images are {stack.size[0]} x {stack.size[1]} px, "
                         f"the projector is {rig.projector.size[0]} x {rig.projector.size[1]}")
    projected = project_patterns(stack, settings.projector)
    t_pat = time.perf_counter() - t0
    cams = [render_camera(geom, rig, i, lens, projected, settings.camera, rng, progress, where)
            for i, lens in enumerate(lenses)]
    return RenderResult(cams, {"patterns_s": t_pat, "total_s": time.perf_counter() - t0})
