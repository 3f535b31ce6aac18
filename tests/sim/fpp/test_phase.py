"""sim.fpp.phase: wrapped phase, quality mask and temporal unwrapping, against analytic fringes, the
renderer's projector-coordinate truth maps, and OpenCV's structured_light PSP decoding."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sim.fpp.decode import DecodeSettings, decode_view
from sim.fpp.phase import (
    TWO_PI,
    WrappedPhase,
    absolute_phase_to_projector,
    beat,
    fringe_order_error,
    gray_bits,
    gray_to_index,
    quality_mask,
    unwrap_gray_code,
    unwrap_heterodyne,
    unwrap_hierarchical,
    unwrap_with_reference,
    wrapped_phase,
)
from sim.optics.lens import PinholeLens
from sim.optics.rig import DeviceCalibration, Rig, small_rig
from sim.render.fringe_patterns import GrayCodeSet, PhaseShiftSet
from sim.render.images import CameraResponse, RenderSettings, render_views
from sim.render.scene import PlaneObject, Pose, Scene, SphereObject


def fringes(u: np.ndarray, period: float, steps: int, a=100.0, b=60.0) -> np.ndarray:
    """Analytic N-step images (N, ...) of projector coordinates ``u``."""
    d = TWO_PI * np.arange(steps) / steps
    phi = TWO_PI * u / period
    return a + b * np.cos(phi[None] - d.reshape((-1,) + (1,) * u.ndim))


def circ(a: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * a))


# ---------------------------------------------------------------- wrapped phase and quality


@pytest.mark.parametrize("steps", [3, 4, 5, 8])
def test_wrapped_phase_recovers_phase_modulation_offset(steps):
    rng = np.random.default_rng(steps)
    phi = rng.uniform(-10, 10, (7, 9))
    a = rng.uniform(50, 150, phi.shape)
    b = rng.uniform(5, 40, phi.shape)
    d = TWO_PI * np.arange(steps) / steps
    imgs = a + b * np.cos(phi[None] - d[:, None, None])
    wp = wrapped_phase(imgs)
    assert np.all((wp.phase >= 0) & (wp.phase < TWO_PI))
    np.testing.assert_allclose(circ(wp.phase - phi), 0, atol=1e-12)
    np.testing.assert_allclose(wp.modulation, b, rtol=1e-12)
    np.testing.assert_allclose(wp.offset, a, rtol=1e-12)


def test_wrapped_phase_rejects_bad_stacks():
    with pytest.raises(ValueError, match="at least 3 images, got 2"):
        wrapped_phase(np.zeros((2, 4, 4)))
    with pytest.raises(ValueError, match=r"must be \(N, H, W\)"):
        wrapped_phase(np.zeros((4, 4)))


def test_quality_mask_thresholds():
    mod = np.array([[1.0, 10.0, 10.0, 10.0]])
    off = np.array([[50.0, 50.0, 200.0, 50.0]])
    wp = WrappedPhase(np.zeros((1, 4)), mod, off)
    peak = np.array([[60.0, 60.0, 210.0, 255.0]])
    assert quality_mask(wp, 5.0).tolist() == [[False, True, True, True]]
    assert quality_mask(wp, 5.0, min_contrast=0.1).tolist() == [[False, True, False, True]]
    assert quality_mask(wp, 5.0, saturation=255, max_intensity=peak).tolist() == [
        [False, True, True, False]
    ]
    with pytest.raises(ValueError, match="must be >= 0"):
        quality_mask(wp, -1.0)
    with pytest.raises(ValueError, match="saturation given without max_intensity"):
        quality_mask(wp, 1.0, saturation=255)


# ---------------------------------------------------------------- temporal unwrapping (analytic)

EXTENT = 1000
U_ALL = np.linspace(-0.5, EXTENT - 0.5, 20001)  # the projector's whole range, both edges


def test_hierarchical_recovers_every_coordinate_with_noise():
    periods = [1200, 100, 10]  # the coarsest period leaves 100 px of slack at each edge
    rng = np.random.default_rng(1)
    phases = [np.mod(TWO_PI * U_ALL / p + rng.normal(0, 0.02, U_ALL.shape), TWO_PI) for p in periods]
    absph, oerr = unwrap_hierarchical(phases, periods, EXTENT, return_order_error=True)
    u = absolute_phase_to_projector(absph, 10)
    assert np.abs(u - U_ALL).max() < 10 * 0.02 * 5 / TWO_PI  # 5 sigma of the finest level only
    assert oerr.max() < 0.25


def test_hierarchical_coarsest_period_equal_to_extent_is_exact_without_noise():
    periods = [1000, 100, 10]  # any order
    exact = [np.mod(TWO_PI * U_ALL / p, TWO_PI) for p in periods]
    u = absolute_phase_to_projector(unwrap_hierarchical(exact[::-1], periods[::-1], EXTENT), 10)
    np.testing.assert_allclose(u[:-1], U_ALL[:-1], atol=1e-9)  # the far edge aliases to -0.5


def test_hierarchical_errors():
    ph = [np.zeros(3), np.zeros(3)]
    with pytest.raises(ValueError, match="must be at least the projector extent"):
        unwrap_hierarchical(ph, [500, 10], EXTENT)
    with pytest.raises(ValueError, match="one wrapped phase per period"):
        unwrap_hierarchical(ph, [1000], EXTENT)
    with pytest.raises(ValueError, match="differ in shape"):
        unwrap_hierarchical([np.zeros(3), np.zeros(4)], [1000, 10], EXTENT)
    with pytest.raises(ValueError, match="periods must be > 0"):
        unwrap_hierarchical(ph, [1000, 0], EXTENT)


def test_beat_period_and_phase():
    u = np.linspace(0, 300, 50)
    b, pb = beat(np.mod(TWO_PI * u / 17, TWO_PI), 17, np.mod(TWO_PI * u / 16, TWO_PI), 16)
    assert pb == pytest.approx(272.0)
    np.testing.assert_allclose(circ(b - TWO_PI * u / 272), 0, atol=1e-12)
    with pytest.raises(ValueError, match="two different periods"):
        beat(u, 16, u, 16)


@pytest.mark.parametrize("periods", [[16.0, 17.0], [21.0, 16.0, 18.0]])
def test_heterodyne_two_and_three_frequency(periods):
    extent = 256  # beats: 16/17 -> 272; 16/18 -> 144, 18/21 -> 126, their beat -> 1008
    u = np.linspace(-0.5, extent - 0.5, 5001)
    rng = np.random.default_rng(2)
    phases = [np.mod(TWO_PI * u / p + rng.normal(0, 0.002, u.shape), TWO_PI) for p in periods]
    absph, oerr = unwrap_heterodyne(phases, periods, extent, return_order_error=True)
    assert np.abs(absolute_phase_to_projector(absph, 16.0) - u).max() < 0.05
    assert oerr.max() < 0.3


def test_heterodyne_errors():
    z = np.zeros(3)
    with pytest.raises(ValueError, match="takes 2 or 3 periods, got 4"):
        unwrap_heterodyne([z] * 4, [16, 17, 18, 19], 100)
    with pytest.raises(ValueError, match="must be at least the projector extent"):
        unwrap_heterodyne([z, z], [16, 17], 1000)  # beat 272 < 1000


def test_gray_code_index_and_robust_unwrapping():
    n = np.arange(64)
    codes = n ^ (n >> 1)
    bits = ((codes[None, :] >> np.arange(5, -1, -1)[:, None]) & 1).astype(bool)
    np.testing.assert_array_equal(gray_to_index(bits), n)
    with pytest.raises(ValueError, match="at least one bit plane"):
        gray_to_index(np.zeros((0, 3), bool))
    # stripes of half a period, decoded with edge errors of up to 1.5 px into the neighbour
    period, w = 16.0, 8.0
    u = np.linspace(-0.5, 511.5, 40001)
    rng = np.random.default_rng(3)
    shift = rng.uniform(-1.5, 1.5, u.shape)
    index = np.floor((u + shift + 0.5) / w).astype(int)
    absph, oerr = unwrap_gray_code(np.mod(TWO_PI * u / period, TWO_PI), period, index, w,
                                   return_order_error=True)
    np.testing.assert_allclose(absolute_phase_to_projector(absph, period), u, atol=1e-9)
    assert oerr.max() <= 0.25 + 1.5 / period + 1e-9
    with pytest.raises(ValueError, match="must be narrower than the phase period"):
        unwrap_gray_code(u, 16.0, index, 16.0)


def test_gray_bits_thresholds_and_errors():
    imgs = np.array([[[10.0, 90.0]], [[90.0, 10.0]]])
    inv = 100.0 - imgs
    assert gray_bits(imgs, inverse=inv).tolist() == [[[False, True]], [[True, False]]]
    assert gray_bits(imgs, threshold=np.full((1, 2), 50.0)).tolist() == [[[False, True]], [[True, False]]]
    with pytest.raises(ValueError, match="inverse Gray images have shape"):
        gray_bits(imgs, inverse=inv[:1])
    with pytest.raises(ValueError, match="threshold image has shape"):
        gray_bits(imgs, threshold=np.zeros(3))
    with pytest.raises(ValueError, match="either a threshold image or the inverse"):
        gray_bits(imgs)


def test_unwrap_with_reference_and_order_error():
    u = np.array([3.0, 40.0, 77.9])
    ref = u + np.array([7.9, -7.9, 0.0])
    absph = unwrap_with_reference(np.mod(TWO_PI * u / 16, TWO_PI), 16.0, ref)
    np.testing.assert_allclose(absolute_phase_to_projector(absph, 16.0), u, atol=1e-12)
    np.testing.assert_allclose(fringe_order_error(absph, 16.0, ref), [7.9 / 16, -7.9 / 16, 0], atol=1e-12)


# ---------------------------------------------------------------- rendered scenes


def _step_scene() -> Scene:
    """A wall 150 mm behind a sphere, and a small plate 80 mm in front: depth steps of 5-20
    projector pixels at this scale, several fringes of period 8."""
    return Scene(objects=[
        PlaneObject(size_mm=(600, 400), pose=Pose(t=[0, 0, 150])),
        SphereObject(pose=Pose(t=[20, 10, 0])),
        PlaneObject(size_mm=(60, 60), pose=Pose(t=[-60, -20, -80])),
    ])


@pytest.fixture(scope="module")
def step_renders():
    rig = small_rig(0.1)  # cameras 410 x 217, projector 192 x 108, the default rig's geometry
    geom = _step_scene().trace_geometry()
    sets = {
        "hierarchical": PhaseShiftSet(periods_px=[192, 32, 8], steps=4),
        "heterodyne": PhaseShiftSet(periods_px=[16, 17], steps=4),
        "heterodyne3": PhaseShiftSet(periods_px=[16, 18, 21], steps=4),
        "gray": GrayCodeSet(period_px=8, steps=4),
    }
    settings = RenderSettings(camera=CameraResponse(quantize=False))
    out = {}
    for name, ps in sets.items():
        res = render_views(geom, rig, [PinholeLens()] * 2, ps.images(rig.projector.size), settings)
        out[name] = (ps, res.cameras[0])
    return rig, out


@pytest.mark.parametrize("method", ["hierarchical", "heterodyne", "heterodyne3", "gray"])
def test_unwrapping_is_right_on_every_valid_pixel_of_a_stepped_scene(step_renders, method):
    rig, out = step_renders
    ps, cam = out[method]
    view = decode_view(cam.images, ps, rig.projector.size)
    truth = cam.projector_map[..., 0]
    u = view.coord["u"]
    valid = np.isfinite(u)
    assert valid.sum() > 0.9 * cam.lit.sum()  # nearly every lit pixel decodes
    assert np.all(cam.lit[valid])
    err = np.abs(u[valid] - truth[valid])
    assert err.max() < 0.02, f"{method}: worst error {err.max():.3g} px"  # no fringe-order jumps
    # the scene does have depth steps of more than half a period between neighbouring pixels
    jumps = np.abs(np.diff(truth, axis=1))
    assert np.nanmax(jumps) > 8


def test_decode_rejects_wrong_count_and_dark_images(step_renders):
    rig, out = step_renders
    ps, cam = out["gray"]
    with pytest.raises(ValueError, match=r"left: 17 images, but the pattern set has 18 patterns"):
        decode_view(cam.images[:-1], ps, rig.projector.size, where="left")
    with pytest.raises(ValueError, match="the images are dark or show no fringes"):
        decode_view(np.zeros_like(cam.images), ps, rig.projector.size)
    with pytest.raises(ValueError, match=r"must be a stack \(n, H, W\)"):
        decode_view(cam.images[0], ps, rig.projector.size)
    ps1 = PhaseShiftSet(periods_px=[8.0], steps=4)
    with pytest.raises(ValueError, match="1 period\\(s\\) along 'u' cannot be unwrapped"):
        decode_view(cam.images[:4], ps1, rig.projector.size)
    with pytest.raises(ValueError, match="hierarchical unwrapping needs a period of at least 192 px"):
        decode_view(cam.images[:4], ps1, rig.projector.size, DecodeSettings(unwrap="hierarchical"))


def _crop(cam: DeviceCalibration, size: tuple[int, int]) -> DeviceCalibration:
    """The central ``size`` window of a camera: same geometry, smaller sensor."""
    k = cam.K_array.copy()
    k[0, 2] -= (cam.width - size[0]) // 2
    k[1, 2] -= (cam.height - size[1]) // 2
    return cam.model_copy(update={"K": k.tolist(), "size": size})


def test_wrapped_phase_agrees_with_opencv_psp():
    """OpenCV's PSP = its 3-step formula after a Fourier band-pass around the fringe carrier;
    on the same rendered 8-bit images the formula agrees with ours to rounding, the band-passed
    result (the library's output) to about 0.01 rad away from the image border."""
    base = small_rig(0.25)
    rig = Rig(cameras=[_crop(c, (256, 256)) for c in base.cameras], projector=base.projector)
    ps = PhaseShiftSet(periods_px=[16.0], steps=3)
    geom = Scene(objects=[PlaneObject(size_mm=(600, 400))]).trace_geometry()
    res = render_views(geom, rig, [PinholeLens()] * 2, ps.images(rig.projector.size), RenderSettings())
    imgs = res.cameras[0].images  # 8-bit
    ours = wrapped_phase(imgs).phase
    sl = cv2.structured_light
    params = sl.SinusoidalPattern.Params()
    params.methodId, params.width, params.height = sl.PSP, 256, 256
    # OpenCV's shifts advance the phase: our images in the order 0, 2, 1
    cv_phase, shadow = sl.SinusoidalPattern.create(params).computePhaseMap([imgs[0], imgs[2], imgs[1]])
    assert np.all(shadow > 0)
    d = np.abs(circ(cv_phase.astype(np.float64) - ours))[20:-20, 20:-20]
    assert np.median(d) < 0.015 and np.percentile(d, 95) < 0.04 and d.max() < 0.1
    i1, i2, i3 = (imgs[k].astype(np.float64) for k in (0, 2, 1))
    s = TWO_PI / 3
    formula = np.arctan2((1 - np.cos(s)) * (i3 - i2), np.sin(s) * (2 * i1 - i2 - i3))
    np.testing.assert_allclose(circ(formula - ours), 0, atol=1e-12)
