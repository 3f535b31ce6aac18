"""Fringe images from a light transport: projector response, gather, camera response, writers.

Signal chain for pattern image ``P`` (values in [0, 1]) and camera pixel ``p``:

1. projector (``ProjectorResponse``): input quantised to ``input_bits``, then
   ``black + (1 - black) * P ** gamma``, then defocus: a Gaussian blur of ``defocus_sigma_px``
   projector pixels (edges replicated);
2. gather: ``radiance_p = sum_k w_k * P'(u_k, v_k)`` with ``P'`` sampled bilinearly (pixel
   centres at integers, clamped to the edge pixels) at each ray's projector coordinate;
3. camera (``CameraResponse``): electrons ``e = exposure_e * radiance``, Poisson shot noise,
   clipped at the full well, plus Gaussian read noise; ``DN = gain * (2^bits - 1) / full_well_e
   * e + black_level_dn``, clipped to ``[0, 2^bits - 1]`` (saturation) and rounded.

Radiance 1 is a white pattern on an albedo-1 surface facing the projector (N.L = 1) seen by an
unvignetted pixel; there is no distance fall-off (OPTICS.md section 4).
"""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import scipy.sparse as sp
import zarr
from pydantic import BaseModel, ConfigDict, Field
from tqdm import tqdm

from sim.lens import LensModel
from sim.rig import Rig
from sim.trace import TraceGeometry, Transport, trace_camera

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


class RenderSettings(BaseModel):
    """Projector and camera response of a rendering."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    projector: ProjectorResponse = Field(default_factory=ProjectorResponse)
    camera: CameraResponse = Field(default_factory=CameraResponse)


def project_patterns(patterns: np.ndarray, projector: ProjectorResponse) -> np.ndarray:
    """Projected light (n, H, W) float32 of pattern images (n, H, W) in [0, 1]."""
    p = np.asarray(patterns, dtype=np.float32)
    if p.ndim != 3:
        raise ValueError(f"pattern images must be (n, H, W), got shape {p.shape}")
    if p.size and (p.min() < 0 or p.max() > 1):
        raise ValueError(f"pattern values must lie in [0, 1], got [{p.min():g}, {p.max():g}]")
    if projector.input_bits is not None:
        q = float((1 << projector.input_bits) - 1)
        p = np.round(p * q) / q
    p = projector.black_level + (1.0 - projector.black_level) * p**projector.gamma
    s = projector.defocus_sigma_px
    if s > 0:
        k = 2 * math.ceil(4 * s) + 1
        p = np.stack([cv2.GaussianBlur(im, (k, k), s, sigmaY=s, borderType=cv2.BORDER_REPLICATE)
                      for im in p])
    return np.ascontiguousarray(p, dtype=np.float32)


def transport_matrix(tr: Transport, rows: slice = slice(None)) -> sp.csr_array:
    """Sparse (n_pixels, Hp * Wp) float32 matrix of the bilinear weights of every lit ray
    (of the pixel ``rows`` of the transport, when given)."""
    wp, hp = tr.projector_size
    weight = tr.weight[rows]
    n, k = weight.shape
    w = weight.reshape(-1)
    keep = np.flatnonzero(w > 0)
    uv = tr.proj_uv[rows].reshape(-1, 2)
    u, v, wk = uv[keep, 0], uv[keep, 1], w[keep]
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = u - iu, v - iv
    iu, iv = iu.astype(np.int32), iv.astype(np.int32)
    ia, ib = np.clip(iu, 0, wp - 1), np.clip(iu + 1, 0, wp - 1)
    ja, jb = np.clip(iv, 0, hp - 1) * wp, np.clip(iv + 1, 0, hp - 1) * wp
    a, b = wk * (1 - fu), wk * fu
    cols = np.stack([ja + ia, ja + ib, jb + ia, jb + ib], axis=1).ravel()
    vals = np.stack([a * (1 - fv), b * (1 - fv), a * fv, b * fv], axis=1).ravel()
    indptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(keep // k, minlength=n) * 4, out=indptr[1:])
    return sp.csr_array((vals, cols, indptr), shape=(n, wp * hp))


def pattern_columns(projected: np.ndarray) -> np.ndarray:
    """Projected patterns (n, Hp, Wp) as the (Hp * Wp, n) float32 matrix the gather multiplies."""
    p = np.asarray(projected, dtype=np.float32)
    return np.ascontiguousarray(p.reshape(len(p), -1).T)


def gather(tr: Transport, columns: np.ndarray, threads: int | None = None) -> np.ndarray:
    """Radiance (n_pixels, n_patterns) float32 of the transport's pixels for ``pattern_columns``;
    the sparse matrix is built and applied in row blocks on every core."""
    wp, hp = tr.projector_size
    if columns.shape[0] != wp * hp:
        raise ValueError(f"patterns have {columns.shape[0]} pixels, the projector {wp} x {hp}")
    n = len(tr.pixels)
    nt = threads or os.cpu_count() or 1
    step = max(1, min(n, max(1, (1 << 16) // tr.weight.shape[1])))
    out = np.empty((n, columns.shape[1]), np.float32)

    def part(a: int) -> None:
        rows = slice(a, min(a + step, n))
        out[rows] = transport_matrix(tr, rows) @ columns

    with ThreadPoolExecutor(nt) as ex:
        list(ex.map(part, range(0, n, step)))
    return out


def camera_response(radiance: np.ndarray, camera: CameraResponse,
                    rng: np.random.Generator | None = None) -> np.ndarray:
    """Digital images (same shape) of radiance: uint8 (8 bits), uint16 (12, 16) or float32 DN."""
    if (camera.shot_noise or camera.read_noise_e > 0) and rng is None:
        raise ValueError("camera_response: rng is required when shot_noise or read_noise_e is on")
    e = np.asarray(radiance, dtype=np.float32) * np.float32(camera.exposure_e)
    np.maximum(e, 0.0, out=e)
    if camera.shot_noise:
        e = rng.poisson(e).astype(np.float32)
    np.minimum(e, np.float32(camera.full_well_e), out=e)
    if camera.read_noise_e > 0:
        e += np.float32(camera.read_noise_e) * rng.standard_normal(e.shape, dtype=np.float32)
    dn = e * np.float32(camera.dn_per_e) + np.float32(camera.black_level_dn)
    np.clip(dn, 0.0, camera.max_dn, out=dn)
    if not camera.quantize:
        return dn
    return np.rint(dn, out=dn).astype(np.uint8 if camera.bit_depth == 8 else np.uint16)


def render(tr: Transport, pattern_images: np.ndarray, settings: RenderSettings,
           rng: np.random.Generator | None = None) -> np.ndarray:
    """Camera images (n, H, W) of a transport for pattern images (n, Hp, Wp) in [0, 1]
    (pixels the transport does not cover get radiance 0)."""
    cols = pattern_columns(project_patterns(pattern_images, settings.projector))
    w, h = tr.camera_size
    rad = np.zeros((w * h, cols.shape[1]), np.float32)
    rad[tr.pixels] = gather(tr, cols)
    return camera_response(rad.T.reshape(-1, h, w), settings.camera, rng)


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


@dataclass
class RenderResult:
    """Every camera's rendering, and timings (s) of what is shared (``patterns_s``, ``total_s``)."""

    cameras: list[CameraImages]
    timings: dict[str, float] = field(default_factory=dict)


def render_camera(geom: TraceGeometry, rig: Rig, index: int, lens: LensModel, columns: np.ndarray,
                  camera: CameraResponse, rng: np.random.Generator | None, progress: bool = False,
                  where: str = "scene") -> CameraImages:
    """Trace camera ``index`` of the rig tile by tile (``TILE_RAYS`` rays: memory stays bounded
    whatever the lens), gather the patterns ``columns`` (``pattern_columns``) from each tile's
    transport, then apply the camera response. Errors name ``where``."""
    cam = rig.cameras[index]
    w, h = cam.size
    k = lens.bundle(np.zeros((1, 2)), np.zeros((1, 2))).weights.shape[1]
    step = max(1, TILE_RAYS // (k + 1))
    rad = np.zeros((w * h, columns.shape[1]), np.float32)
    depth, pmap = np.full(w * h, np.nan), np.full((w * h, 2), np.nan)
    lit, obj = np.zeros(w * h, bool), np.full(w * h, -1, np.int32)
    t_trace = t_gather = 0.0
    n_rays = 0
    bar = tqdm(total=w * h, desc=f"render {cam.name}", unit="px", unit_scale=True,
               disable=not progress)
    for s in range(0, w * h, step):
        pix = np.arange(s, min(s + step, w * h))
        tr = trace_camera(geom, cam, rig.projector, lens, pixels=pix)
        t0 = time.perf_counter()
        rad[pix] = gather(tr, columns)
        t_gather += time.perf_counter() - t0
        t_trace += tr.seconds
        n_rays += tr.rays
        depth[pix], pmap[pix], lit[pix], obj[pix] = tr.depth, tr.proj_chief, tr.lit, tr.object_id
        bar.update(len(pix))
    bar.close()
    if not np.any(obj >= 0):
        raise ValueError(f"{where}: camera {index} ('{cam.name}') sees none of the scene objects; "
                         "check the rig's R and T (field 'rig') and the objects' poses")
    t0 = time.perf_counter()
    radiance = np.ascontiguousarray(rad.T).reshape(-1, h, w)
    images = camera_response(radiance, camera, rng)
    t_resp = time.perf_counter() - t0
    return CameraImages(cam.name, images, radiance, depth.reshape(h, w), pmap.reshape(h, w, 2),
                        lit.reshape(h, w), obj.reshape(h, w),
                        {"trace_s": t_trace, "gather_s": t_gather, "response_s": t_resp}, n_rays)


def render_views(geom: TraceGeometry, rig: Rig, lenses: list[LensModel], pattern_images: np.ndarray,
                 settings: RenderSettings, rng: np.random.Generator | None = None,
                 progress: bool = False, where: str = "scene") -> RenderResult:
    """Render pattern images (n, Hp, Wp) in [0, 1] on every camera of ``rig`` with one lens
    per camera: images plus timings (``patterns_s``, ``total_s``; per camera ``trace_s``,
    ``gather_s``, ``response_s``). Errors name ``where``."""
    t0 = time.perf_counter()
    if len(lenses) != len(rig.cameras):
        raise ValueError(f"{where}: {len(lenses)} lenses for {len(rig.cameras)} cameras")
    wp, hp = rig.projector.size
    if np.shape(pattern_images)[1:] != (hp, wp):
        raise ValueError(f"{where}: pattern images are {np.shape(pattern_images)}, "
                         f"the projector is {wp} x {hp}")
    cols = pattern_columns(project_patterns(pattern_images, settings.projector))
    t_pat = time.perf_counter() - t0
    cams = [render_camera(geom, rig, i, lens, cols, settings.camera, rng, progress, where)
            for i, lens in enumerate(lenses)]
    return RenderResult(cams, {"patterns_s": t_pat, "total_s": time.perf_counter() - t0})


def write_png(path: str | Path, image: np.ndarray, bit_depth: int) -> None:
    """Write one image (H, W): 8 bits as 8-bit PNG; 12 and 16 bits as 16-bit PNG holding the
    DN values unscaled (a 12-bit image keeps 0..4095, it is not shifted to the top bits)."""
    image = np.asarray(image)
    want = {8: np.uint8, 12: np.uint16, 16: np.uint16}.get(bit_depth)
    if want is None:
        raise ValueError(f"write_png: bit_depth must be 8, 12 or 16, got {bit_depth}")
    if image.ndim != 2 or image.dtype != want or (bit_depth == 12 and image.max(initial=0) > 4095):
        raise ValueError(f"write_png {path}: expected a 2-D {np.dtype(want).name} image with values "
                         f"< 2^{bit_depth}, got {image.dtype} {image.shape}")
    if not cv2.imwrite(str(path), image):
        raise OSError(f"write_png: could not write {path}")


def write_pngs(directory: str | Path, images: np.ndarray, bit_depth: int) -> list[Path]:
    """Write images (n, H, W) as ``directory/pattern_000.png`` ...; returns the paths."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    paths = [d / f"pattern_{i:03d}.png" for i in range(len(images))]
    for p, im in zip(paths, images):
        write_png(p, im, bit_depth)
    return paths


def write_zarr(path: str | Path, result: RenderResult, attrs: dict | None = None,
               radiance: bool = False) -> None:
    """Write a zarr v3 stack: group ``camera_<i>`` per camera with ``images`` (n, H, W, one
    chunk per image), ``depth`` (H, W) mm, ``projector_map`` (H, W, 2) projector px,
    ``lit`` (H, W), ``object_id`` (H, W) and, if asked, ``radiance`` (n, H, W) float32;
    ``attrs`` (JSON-able) go on the root group, the camera name and timings on each group."""
    root = zarr.open_group(str(path), mode="w", attributes=attrs or {})
    for i, c in enumerate(result.cameras):
        g = root.create_group(f"camera_{i}", attributes={"name": c.name, "timings": c.timings,
                                                             "rays": c.n_rays})
        h, w = c.depth.shape
        g.create_array("images", data=c.images, chunks=(1, h, w))
        if radiance:
            g.create_array("radiance", data=c.radiance, chunks=(1, h, w))
        g.create_array("depth", data=c.depth, chunks=(h, w))
        g.create_array("projector_map", data=c.projector_map, chunks=(h, w, 2))
        g.create_array("lit", data=c.lit, chunks=(h, w))
        g.create_array("object_id", data=c.object_id, chunks=(h, w))
