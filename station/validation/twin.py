"""The virtual scanners a real scan is compared with, and the camera response that makes their
images comparable with the real ones.

Twins: the lens of ``--lenses`` (per camera a measured lens file, or a lens spec in the scene
file's vocabulary: ``kind = "thin" | "aberrated" | "gaussian" | "pinhole"`` and its fields),
named ``ltc`` for measured lenses (else by the spec's kind); for measured lenses also
``gaussian`` (the measured lens's equivalent, or ``gaussian_sigma_mm``); always ``pinhole``.

Response (``counts = gain * radiance + offset + noise``): gain and offset by least squares over
the lit pixels of the real and rendered background A and modulation B maps; the noise from the
dark frame, or from the phase-shift residuals of the real images (read noise and shot gain).
"""

from __future__ import annotations

import json
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from station.validation.folder import (
    BallBarArtefact,
    CadArtefact,
    Pose,
    RealScanError,
    SphereArtefact,
)

if TYPE_CHECKING:
    from sim.fpp.cloud import PointCloud
    from sim.fpp.decode import DecodeSettings, ScanReport
    from sim.optics.lens import LensModel
    from sim.optics.rig import DeviceCalibration, Rig
    from sim.render.fringe_patterns import GrayCodeSet, PhaseShiftSet
    from sim.render.scene import Scene

LIT_FRACTION = 0.2  # pixels whose rendered B exceeds this fraction of its 99th percentile


def load_lens_arg(path: str | Path, camera: DeviceCalibration, index: int) -> LensModel:
    """One camera's lens from ``--lenses``: a measured lens ``.npz`` (checked against the rig
    camera: ``lens_camera_mismatch``) or a TOML / JSON lens spec."""
    from sim.optics.lens_file import load_lens_for
    from sim.optics.measured_lens import LensFileError
    from sim.render.scene import LENS_KINDS, ThinLensSpec

    path = Path(path)
    where = f"camera {index} (every position): --lenses {path}"
    if not path.is_file():
        raise RealScanError(f"{where}: not found")
    if path.suffix == ".npz":
        try:
            return load_lens_for(path, camera)
        except LensFileError as exc:
            raise RealScanError(f"{where}: {exc}") from exc
    try:
        text = path.read_text(encoding="utf-8")
        raw = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (OSError, ValueError) as exc:
        raise RealScanError(f"{where}: not a lens spec (TOML or JSON): {exc}") from exc
    kind = raw.get("kind")
    if kind not in LENS_KINDS or kind == "measured":
        raise RealScanError(f"{where}: field 'kind': {kind!r}, expected one of thin, aberrated, "
                            "gaussian, pinhole (or a measured lens .npz)")
    try:
        spec: Any = LENS_KINDS[kind].model_validate(raw)  # type: ignore[attr-defined]
    except ValueError as exc:
        raise RealScanError(f"{where}: {' '.join(str(exc).split())}") from exc
    model: LensModel = spec.lens() if isinstance(spec, ThinLensSpec) else spec
    return model


def build_twins(rig: Rig, lens_paths: list[str | Path], gaussian_sigma_mm: float | None = None,
                gaussian_samples: int | None = None, smoothing_nodes: float = 0.0
                ) -> dict[str, tuple[LensModel, ...]]:
    """Per twin name the lens of each rig camera (see the module docstring); the first twin
    is the primary one, whose refined pose every twin is rendered at."""
    from sim.optics.lens import GaussianLens, PinholeLens
    from sim.optics.lens_moments import gaussian_equivalent, smoothed_lens
    from sim.optics.measured_lens import MeasuredLens

    if len(lens_paths) != len(rig.cameras):
        raise RealScanError(f"--lenses: {len(lens_paths)} lens(es) for the rig's "
                            f"{len(rig.cameras)} cameras; give one per camera")
    lenses = [load_lens_arg(p, c, i)
              for i, (p, c) in enumerate(zip(lens_paths, rig.cameras, strict=True))]
    ms = [x for x in lenses if isinstance(x, MeasuredLens)]
    if ms and len(ms) != len(lenses):
        raise RealScanError("--lenses: give measured lenses for both cameras or specs for both")
    twins: dict[str, tuple[LensModel, ...]] = {}
    if ms:
        twins["ltc"] = tuple(smoothed_lens(m, smoothing_nodes) if smoothing_nodes else m
                             for m in ms)
        if gaussian_sigma_mm is None:
            twins["gaussian"] = tuple(gaussian_equivalent(m, gaussian_samples) for m in ms)
    else:
        kinds = {getattr(x, "kind", "lens") for x in lenses}
        name = "thin" if kinds == {"aberrated"} and all(
            getattr(x, "spherical_mm", 0) == 0 and getattr(x, "vignetting_shift_mm", 0) == 0
            for x in lenses) else \
            "_".join(sorted(kinds))
        twins[name] = tuple(lenses)
    if gaussian_sigma_mm is not None:
        focus = [getattr(x, "focus_distance_mm", None) for x in lenses]
        if any(f is None for f in focus):
            raise RealScanError("--gaussian-sigma needs lenses with a focus distance")
        twins["gaussian"] = tuple(GaussianLens(sigma_mm=gaussian_sigma_mm, focus_distance_mm=f,
                                               samples=gaussian_samples or 64) for f in focus)
    twins.setdefault("pinhole", (PinholeLens(), PinholeLens()))
    return twins


def scene_at(artefact: SphereArtefact | BallBarArtefact | CadArtefact, pose: Pose, name: str,
             mesh_path: Path | None = None) -> Scene:
    """The ``sim`` scene of the artefact at ``pose``."""
    from sim.render.scene import BallBarObject, MeshObject, Scene, SphereObject

    p = {"t": list(pose.t), "R": [list(r) for r in pose.R]}
    if isinstance(artefact, BallBarArtefact):
        obj: BallBarObject | MeshObject | SphereObject = BallBarObject(
            name=name, diameter_mm=artefact.ball_diameter_mm,
            centre_distance_mm=artefact.centre_distance_mm, pose=p)
    elif isinstance(artefact, CadArtefact):
        obj = MeshObject(name=name, path=mesh_path, smooth_angle_deg=30.0, pose=p)
    else:
        obj = SphereObject(name=name, diameter_mm=artefact.diameter_mm, pose=p)
    return Scene(objects=[obj])


@dataclass(frozen=True)
class Response:
    """Per camera ``counts = gain * radiance + offset``, noise ``sqrt(read^2 + shot * signal)``
    DN; ``source`` says where the noise came from; ``bits`` the ADC depth the images are
    rounded to (None: not rounded)."""

    gain: tuple[float, ...]
    offset: tuple[float, ...]
    read_noise_dn: tuple[float, ...]
    shot_dn: tuple[float, ...]
    bits: int | None
    source: str

    def to_json(self) -> dict[str, Any]:
        return {"gain": list(self.gain), "offset": list(self.offset),
                "read_noise_dn": list(self.read_noise_dn), "shot_dn": list(self.shot_dn),
                "bits": self.bits, "source": self.source}

    def apply(self, radiance: np.ndarray, index: int, rng: np.random.Generator | None
              ) -> np.ndarray:
        """Counts (n, H, W) float of one camera's radiance; noise only with ``rng``."""
        x = self.gain[index] * np.asarray(radiance, np.float64) + self.offset[index]
        if rng is not None:
            sd = np.sqrt(self.read_noise_dn[index] ** 2
                         + self.shot_dn[index] * np.maximum(x - self.offset[index], 0.0))
            x = x + rng.standard_normal(x.shape) * sd
        if self.bits is not None:
            x = np.clip(np.rint(x), 0, 2 ** self.bits - 1)
        return x


def _ab(images: np.ndarray, patterns: PhaseShiftSet | GrayCodeSet,
        projector_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Background A and modulation B (H, W) over the phase-shift groups, and the residual
    variance per image of the N-step model (DN^2, per pixel (H, W))."""
    from collections import defaultdict

    descs = patterns.descriptors(projector_size)
    groups: dict[tuple[str | None, float | None], list[int]] = defaultdict(list)
    for d in sorted(descs, key=lambda d: d.shift or 0):
        if d.kind == "phase":
            groups[(d.direction, d.period_px)].append(d.index)
    x = np.asarray(images, np.float64)
    A = B = R = np.zeros(x.shape[1:])
    dof = 0
    for idx in groups.values():
        n = len(idx)
        s = x[idx]
        k = np.arange(n)[:, None, None]
        c, sn = np.cos(2 * np.pi * k / n), np.sin(2 * np.pi * k / n)
        a = s.mean(axis=0)
        C, S = (2 / n) * (s * c).sum(axis=0), (2 / n) * (s * sn).sum(axis=0)
        fit = a + C * c + S * sn
        A, B = A + a, B + np.hypot(C, S)
        R = R + ((s - fit) ** 2).sum(axis=0)
        dof += n - 3
    g = max(len(groups), 1)
    return A / g, B / g, R / max(dof, 1)


def estimate_response(real: list[np.ndarray], rendered_radiance: list[np.ndarray],
                      patterns: PhaseShiftSet | GrayCodeSet, projector_size: tuple[int, int],
                      dark: list[np.ndarray] | None = None,
                      bits: int | None = None) -> Response:
    """Camera response per camera from the real images (n, H, W) and the noise-free rendered
    radiance at the refined pose: gain and offset by least squares over the pixels lit in the
    render (B above ``LIT_FRACTION`` of its 99th percentile) of ``A_real = g A_rad + o`` and
    ``B_real = g B_rad``; noise from the ``dark`` frames (offset-free read noise) or from the
    real images' phase-shift residual variance regressed on the signal (read^2 + shot * A)."""
    gains, offsets, reads, shots = [], [], [], []
    for i, (r, v) in enumerate(zip(real, rendered_radiance, strict=True)):
        Ar, Br, var = _ab(r, patterns, projector_size)
        Av, Bv, _ = _ab(v, patterns, projector_size)
        top = np.percentile(Bv, 99)
        lit = (Bv > LIT_FRACTION * top) & (Br > 0)
        if lit.sum() < 20:
            raise RealScanError(f"camera {i}: the twin lights only {int(lit.sum())} pixels "
                                "the real images also show: is the artefact in view?")
        n = int(lit.sum())
        M = np.zeros((2 * n, 2))
        M[:n, 0], M[:n, 1], M[n:, 0] = Av[lit], 1.0, Bv[lit]
        y = np.concatenate([Ar[lit], Br[lit]])
        (g, o), *_ = np.linalg.lstsq(M, y, rcond=None)
        gains.append(float(g))
        offsets.append(float(o))
        if dark is not None:
            d = np.asarray(dark[i], np.float64)
            reads.append(float(d.std()))
            offsets[-1] = float(d.mean()) if abs(o - d.mean()) > 0 else offsets[-1]
            sig = Ar[lit] - d.mean()
            shot = float(np.clip(np.median((var[lit] - d.var()) / np.maximum(sig, 1e-9)), 0,
                                 None))
        else:
            sig = Ar[lit] - o
            X = np.stack([np.ones(n), np.maximum(sig, 0)], axis=1)
            (r2, shot), *_ = np.linalg.lstsq(X, var[lit], rcond=None)
            reads.append(float(np.sqrt(max(r2, 0.0))))
            shot = float(max(shot, 0.0))
        shots.append(shot)
    return Response(tuple(gains), tuple(offsets), tuple(reads), tuple(shots), bits,
                    "dark frame" if dark is not None else "phase-shift residuals")


@dataclass
class TwinScan:
    """One twin's render and scan at one pose: ``cloud``, ``report`` (``ScanReport``),
    per camera the noise-free ``radiance`` (n, H, W) and the truth maps' ``lit``, seconds."""

    cloud: PointCloud
    report: ScanReport
    radiance: list[np.ndarray]
    lit: list[np.ndarray]
    render_s: float
    scan_s: float


def supersampled(rig: Rig, f: int) -> Rig:
    """The rig with every camera pixel split into ``f`` x ``f`` subpixels (same field of view,
    pixel centres at integer coordinates: ``c' = f c + (f - 1) / 2``)."""
    from sim.optics.rig import DeviceCalibration, Rig

    if f == 1:
        return rig
    cams = []
    for c in rig.cameras:
        K = c.K_array.copy()
        K[:2, :2] *= f
        K[0, 2], K[1, 2] = f * K[0, 2] + (f - 1) / 2, f * K[1, 2] + (f - 1) / 2
        dist = np.asarray(c.dist, np.float64)
        if np.any(dist != 0):
            raise RealScanError(f"camera '{c.name}': pixel_samples > 1 needs a rig without "
                                "distortion (the subpixel rig would need the same distortion "
                                "in subpixel units)")
        cams.append(DeviceCalibration(name=c.name, K=K, dist=c.dist, R=c.R, T=c.T,
                                      size=(c.size[0] * f, c.size[1] * f)))
    return Rig(cameras=cams, projector=rig.projector)


def binned(a: np.ndarray, f: int) -> np.ndarray:
    """The mean over ``f`` x ``f`` blocks of the last two axes."""
    if f == 1:
        return np.asarray(a)
    a = np.asarray(a, np.float64)
    *lead, h, w = a.shape
    return a.reshape(*lead, h // f, f, w // f, f).mean(axis=(-3, -1))


def render_scan(rig: Rig, lenses: tuple[LensModel, ...], patterns: PhaseShiftSet | GrayCodeSet,
                scene: Scene, name: str, response: Response | None, decode: DecodeSettings,
                seed: int = 0, projector: dict[str, Any] | None = None,
                pixel_samples: int = 1) -> TwinScan:
    """Render a twin at a scene (radiance, noise-free), apply ``response`` (None: the
    radiance itself) and scan as ``ltc scan`` does with ``decode``. ``pixel_samples``: each
    camera pixel integrates ``pixel_samples`` x ``pixel_samples`` subpixels (as a camera's
    pixel averages its area; 1: the pixel centre)."""
    from sim.fpp.decode import scan_with_report
    from sim.render.images import RenderSettings
    from sim.scanner import Scanner

    settings = RenderSettings.model_validate({
        "projector": projector or {"input_bits": 8},
        "camera": {"exposure_e": 4095.0, "full_well_e": 4095.0, "bit_depth": 16,
                   "quantize": False, "shot_noise": False, "read_noise_e": 0.0}})
    f = int(pixel_samples)
    s = Scanner(supersampled(rig, f), tuple(lenses), patterns, scene, settings,
                where=f"position {name}")
    t0 = time.perf_counter()
    res = s.render()
    radiance = [binned(c.radiance, f) for c in res.cameras]
    lit = [binned(c.lit.astype(np.float64), f) > 0.5 for c in res.cameras]
    t1 = time.perf_counter()
    rng = np.random.default_rng(seed)
    stacks = [r * 65535.0 if response is None else response.apply(r, i, rng)
              for i, r in enumerate(radiance)]
    try:
        cloud, report = scan_with_report(stacks, patterns, rig, decode)
    except ValueError as exc:
        raise RealScanError(f"position {name}: the twin's scan failed: {exc}") from exc
    return TwinScan(cloud, report, radiance, lit, t1 - t0, time.perf_counter() - t1)
