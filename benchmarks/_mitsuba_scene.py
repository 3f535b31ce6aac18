"""The Mitsuba 3 side of the render benchmark: our scene, camera, projector and lens as a
Mitsuba scene, rendered one fringe image at a time, and Mitsuba's radiance converted to ours.

Mitsuba is an optional benchmark dependency (``scripts/bench_setup.sh``); nothing here imports
it at import time, and the test suite never needs it.

Conventions matched here (benchmarks/README.md, section "Rendering"):

- Frames. Mitsuba's device frame has x to the image's left and y up, OpenCV's x right and
  y down (both z forward), so ``to_world = [R^T diag(-1, -1, 1) | c]`` with ``R`` our
  world-to-device rotation and ``c`` the device centre. Images then come out in OpenCV
  orientation (row 0 at the top, world +x on the right for a camera looking along +z, y down).
- Pixels. Mitsuba's perspective sensor and projector put the optical axis at the centre of
  the image, ``((W - 1) / 2, (H - 1) / 2)`` in our pixel-centre-at-integer convention, with
  ``f = W / (2 tan(fov_x / 2))`` for both axes; neither has distortion and the projector and
  the thin lens have no principal-point offset. ``check_ideal_pinhole`` refuses devices that
  differ. Mitsuba's bilinear texture lookup (``wrap_mode = clamp``) matches our gather.
- Radiance. A diffuse surface of albedo ``rho`` lit by Mitsuba's projector has radiance
  ``rho (N.L) T scale / (z_p^2 cos theta_p)`` (``T`` the texture value, ``z_p`` the point's depth
  in the projector frame, ``theta_p`` its angle off the projector's axis); ours is
  ``rho (N.L) T`` (``sim.render.images``: no distance fall-off). ``to_our_radiance`` multiplies by
  ``z_p^3 / (|x_p| scale)``.
- Lens. Our ideal thin lens (``AberratedLens`` without vignetting and aberrations) is
  Mitsuba's ``thinlens`` with ``aperture_radius = pupil_diameter / 2`` and the same focus
  plane ``z = focus_distance`` of the camera frame; both weight aperture points uniformly.
  Mitsuba also spreads its samples over each pixel's footprint (box filter); ours trace
  through the pixel centre.
"""

from __future__ import annotations

import importlib.util
import os
from types import ModuleType

import numpy as np

from sim.optics.lens import AberratedLens, PinholeLens
from sim.optics.rig import DeviceCalibration
from sim.render.scene import PlaneObject, Scene, SphereObject

CV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0])  # OpenCV device axes -> Mitsuba's (x left, y up)
PROJECTOR_ID = "projector"
IRRADIANCE_KEY = f"{PROJECTOR_ID}.irradiance.data"
NEAR_CLIP_MM = 1.0
FAR_CLIP_MM = 1.0e5
SAMPLERS = ("independent", "stratified", "multijitter", "ldsampler")


def unavailable_reason(variant: str) -> str | None:
    """Why Mitsuba cannot run here with ``variant`` (None when it can be tried)."""
    if importlib.util.find_spec("mitsuba") is None:
        return "mitsuba is not installed in this environment: run scripts/bench_setup.sh"
    if variant.startswith("llvm") and not os.environ.get("DRJIT_LIBLLVM_PATH"):
        return (f"Mitsuba variant '{variant}' needs LLVM 19: set DRJIT_LIBLLVM_PATH to the libLLVM-19.so "
                "that scripts/bench_setup.sh prints (Debian's libllvm19), or use --variant scalar_rgb")
    return None


def load_mitsuba(variant: str) -> ModuleType:
    """Import Mitsuba and select ``variant``; clear errors when it cannot run here."""
    reason = unavailable_reason(variant)
    if reason:
        raise RuntimeError(reason)
    import mitsuba as mi
    if variant not in mi.variants():
        raise RuntimeError(f"Mitsuba has no variant '{variant}'; available: {', '.join(mi.variants())}")
    mi.set_variant(variant)
    return mi


def check_ideal_pinhole(dev: DeviceCalibration, role: str) -> None:
    """Raise ``ValueError`` unless ``dev`` is what Mitsuba can model: square pixels, no skew,
    principal point at the image centre ``((W-1)/2, (H-1)/2)``, no distortion."""
    K, (w, h) = dev.K_array, dev.size
    problems = []
    if not np.isclose(K[0, 0], K[1, 1], rtol=1e-9, atol=0.0):
        problems.append(f"fx = {K[0, 0]:g} differs from fy = {K[1, 1]:g}")
    if K[0, 1] != 0.0:
        problems.append(f"skew {K[0, 1]:g} is not 0")
    if not (np.isclose(K[0, 2], (w - 1) / 2, atol=1e-9) and np.isclose(K[1, 2], (h - 1) / 2, atol=1e-9)):
        problems.append(f"principal point ({K[0, 2]:g}, {K[1, 2]:g}) is not the image centre "
                        f"({(w - 1) / 2:g}, {(h - 1) / 2:g})")
    if np.any(dev.dist_array != 0.0):
        problems.append(f"distortion {dev.dist_array.tolist()} is not zero")
    if problems:
        raise ValueError(f"{role} '{dev.name}' cannot be modelled by Mitsuba's ideal centred pinhole: "
                         + "; ".join(problems))


def to_world_matrix(dev: DeviceCalibration) -> np.ndarray:
    """Mitsuba's ``to_world`` (4, 4) of one of our devices (see the module docstring)."""
    m = np.eye(4)
    m[:3, :3] = dev.R_array.T @ CV_TO_MITSUBA
    m[:3, 3] = dev.centre_world
    return m


def fov_x_deg(dev: DeviceCalibration) -> float:
    """Horizontal field of view, degrees, of a device with centred principal point."""
    return float(np.degrees(2.0 * np.arctan(dev.width / (2.0 * dev.K_array[0, 0]))))


def irradiance_scale_at(projector: DeviceCalibration, point_world: np.ndarray) -> float:
    """The projector ``scale`` that makes Mitsuba's radiance equal ours at ``point_world`` (3,):
    ``z_p^3 / |x_p|`` (mm^2) of the point in the projector frame."""
    xp = projector.to_device(np.asarray(point_world, dtype=np.float64).reshape(1, 3))[0]
    return float(xp[2] ** 3 / np.linalg.norm(xp))


def to_our_radiance(image: np.ndarray, points_world: np.ndarray, projector: DeviceCalibration,
                    scale: float) -> np.ndarray:
    """Mitsuba radiance (H, W) in our convention, given each pixel's surface point (H, W, 3)
    world mm (NaN where none: the result is NaN there)."""
    xp = projector.to_device(np.asarray(points_world).reshape(-1, 3)).reshape(np.shape(points_world))
    factor = xp[..., 2] ** 3 / (np.linalg.norm(xp, axis=-1) * scale)
    return np.asarray(image, dtype=np.float64) * factor


def _bsdf(albedo: float) -> dict:
    return {"type": "twosided", "material": {"type": "diffuse",
                                             "reflectance": {"type": "rgb", "value": [albedo] * 3}}}


def _shapes(mi: ModuleType, scene: Scene) -> dict:
    shapes = {}
    for i, o in enumerate(scene.objects):
        if isinstance(o, SphereObject):
            shapes[f"object_{i}"] = {"type": "sphere", "center": list(o.pose.t),
                                     "radius": o.diameter_mm / 2, "bsdf": _bsdf(o.albedo)}
        elif isinstance(o, PlaneObject):
            m = np.eye(4)
            m[:3, :3] = np.asarray(o.pose.R) @ np.diag([o.size_mm[0] / 2, o.size_mm[1] / 2, 1.0])
            m[:3, 3] = o.pose.t
            shapes[f"object_{i}"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f(m.tolist()),
                                     "bsdf": _bsdf(o.albedo)}
        else:
            raise ValueError(f"objects[{i}]: kind '{o.kind}' has no Mitsuba counterpart in this "
                             "benchmark; use sphere or plane objects")
    return shapes


def _sensor(mi: ModuleType, camera: DeviceCalibration, lens, spp: int, sampler: str) -> dict:
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler must be one of {', '.join(SAMPLERS)}, got '{sampler}'")
    sensor = {"fov": fov_x_deg(camera), "fov_axis": "x", "near_clip": NEAR_CLIP_MM, "far_clip": FAR_CLIP_MM,
              "to_world": mi.ScalarTransform4f(to_world_matrix(camera).tolist()),
              "sampler": {"type": sampler, "sample_count": int(spp)},
              "film": {"type": "hdrfilm", "width": camera.width, "height": camera.height,
                       "rfilter": {"type": "box"}, "pixel_format": "luminance",
                       "component_format": "float32"}}
    if isinstance(lens, PinholeLens):
        return {"type": "perspective", **sensor}
    if isinstance(lens, AberratedLens):
        if lens.vignetting_shift_mm or lens.vignetting_radius_ratio < 1 or lens.spherical_mm or lens.coma_mm:
            raise ValueError("lens: Mitsuba's thinlens is an ideal thin lens; give an AberratedLens "
                             "without vignetting, spherical aberration or coma")
        return {"type": "thinlens", "aperture_radius": lens.pupil_radius_mm,
                "focus_distance": lens.focus_distance_mm, **sensor}
    raise ValueError(f"lens: {type(lens).__name__} has no Mitsuba counterpart; "
                     "use PinholeLens or an ideal thin lens")


class MitsubaFringeRenderer:
    """One camera, one projector and a scene of spheres and planes in Mitsuba 3 (``direct``
    integrator: one projector sample per camera sample, no BSDF sampling, no interreflection).

    ``render(pattern)`` sets the projector's texture and renders ``spp`` samples per pixel.
    ``irradiance_scale`` is the projector's ``scale`` (see ``irradiance_scale_at``).
    """

    def __init__(self, scene: Scene, camera: DeviceCalibration, projector: DeviceCalibration, lens,
                 spp: int, variant: str = "llvm_ad_rgb", sampler: str = "stratified",
                 irradiance_scale: float = 1.0) -> None:
        if spp < 1:
            raise ValueError(f"spp must be >= 1, got {spp}")
        check_ideal_pinhole(camera, "camera")
        check_ideal_pinhole(projector, "projector")
        self.mi = load_mitsuba(variant)
        mi = self.mi
        self.camera, self.projector, self.spp = camera, projector, int(spp)
        wp, hp = projector.size
        scene_dict = {
            "type": "scene",
            "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
            "sensor": _sensor(mi, camera, lens, spp, sampler),
            PROJECTOR_ID: {"type": "projector", "fov": fov_x_deg(projector), "fov_axis": "x",
                           "scale": float(irradiance_scale),
                           "to_world": mi.ScalarTransform4f(to_world_matrix(projector).tolist()),
                           "irradiance": {"type": "bitmap", "raw": True, "filter_type": "bilinear",
                                          "wrap_mode": "clamp",
                                          "data": mi.TensorXf(np.ones((hp, wp, 1), np.float32))}},
            **_shapes(mi, scene),
        }
        self.scene = mi.load_dict(scene_dict)
        self.params = mi.traverse(self.scene)

    def render(self, pattern: np.ndarray, seed: int = 0) -> np.ndarray:
        """Radiance (H, W) float32, Mitsuba's units, of one pattern image (Hp, Wp) in [0, 1]."""
        wp, hp = self.projector.size
        pattern = np.asarray(pattern, dtype=np.float32)
        if pattern.shape != (hp, wp):
            raise ValueError(f"pattern image is {pattern.shape}, the projector is {wp} x {hp} "
                             f"(expected ({hp}, {wp}))")
        self.params[IRRADIANCE_KEY] = self.mi.TensorXf(np.ascontiguousarray(pattern[..., None]))
        self.params.update()
        img = self.mi.render(self.scene, spp=self.spp, seed=seed)
        return np.array(img, dtype=np.float32).reshape(self.camera.height, self.camera.width, -1)[..., 0]

    def render_all(self, patterns: np.ndarray, seed: int = 0,
                   out: np.ndarray | None = None) -> np.ndarray:
        """Radiance (n, H, W) float32 of pattern images (n, Hp, Wp), seeds ``seed + i``; into
        ``out`` (an earlier result) when given."""
        return np.stack([self.render(p, seed + i) for i, p in enumerate(patterns)], out=out)
