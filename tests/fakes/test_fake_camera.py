"""FakeCamera and the fake bench against geometry and the noise model."""

import numpy as np
import pytest

from drivers.camera import CameraTimeout
from drivers.display import OffscreenDisplay
from fakes.bench import BenchConfig, FakeBench
from fakes.camera import FakeCamera, NoiseModel
from fakes.lcd import FakeLCD, PanelResponse

IDEAL = BenchConfig.small(vignetting_shift_mm=0.0, spherical_mm=0.0, pupil_samples=600,
                          subpixels=4)
NOISE_FREE = NoiseModel(enabled=False, bit_depth=16, black_level_adu=0.0)


@pytest.fixture(scope="module")
def lcd():
    with FakeLCD(OffscreenDisplay(IDEAL.lcd_size)) as display:
        yield display


def _one_lit_pixel(size, i, j):
    img = np.zeros((size[1], size[0]), np.uint8)
    img[j, i] = 255
    return img


def _second_moment_diameter(img, box_px):
    yy, xx = np.mgrid[: img.shape[0], : img.shape[1]]
    s = img.sum()
    mx, my = (img * xx).sum() / s, (img * yy).sum() / s
    var = 0.5 * ((img * (xx - mx) ** 2).sum() + (img * (yy - my) ** 2).sum()) / s
    return 4.0 * np.sqrt(var - 1 / 12 - box_px**2 / 12)


def test_one_lit_lcd_pixel_images_to_the_geometric_blur_disk(lcd):
    bench = FakeBench(IDEAL)
    cam = FakeCamera(bench, lcd, lambda: 0.0, NOISE_FREE)
    lcd.show(_one_lit_pixel(IDEAL.lcd_size, 48, 36))
    img = cam.capture().image.astype(np.float64)
    c = IDEAL
    d = c.lcd_distance_at_zero_mm
    f_px = c.focal_length_mm / (c.pixel_pitch_um * 1e-3)
    aperture = c.focal_length_mm / c.f_number
    expected = aperture * abs(d - c.focus_distance_mm) / c.focus_distance_mm * f_px / d
    measured = _second_moment_diameter(img, c.lcd_pitch_mm * f_px / d)
    assert expected > 10  # a real blur disk, not a pixel
    assert measured == pytest.approx(expected, rel=0.02)
    # image sum equals the true LTC's prediction for that LCD pixel
    column = bench.true_ltc(0.0)[:, [36 * c.lcd_size[0] + 48]].sum()
    rate = NOISE_FREE.electrons_per_ms_white() * cam.exposure_ms
    assert img.sum() == pytest.approx(NOISE_FREE.gain_adu_per_e * rate * column, rel=1e-4)


def test_noise_mean_and_variance_match_the_model(lcd):
    bench = FakeBench(BenchConfig.small(pupil_samples=64, subpixels=1))
    noise = NoiseModel()
    cam = FakeCamera(bench, lcd, lambda: 60.0, noise, seed=7)
    rng = np.random.default_rng(3)
    lcd.show(rng.integers(60, 200, size=(IDEAL.lcd_size[1], IDEAL.lcd_size[0]), dtype=np.uint8))
    frames = np.stack([cam.capture().image for _ in range(300)]).astype(np.float64)
    e = cam.expected_electrons()
    lit = e > 100
    mean_model = noise.mean_adu(e)[lit]
    var_model = noise.variance_adu(e)[lit]
    mean = frames.mean(axis=0)[lit]
    var = frames.var(axis=0, ddof=1)[lit]
    assert np.median(np.abs(mean - mean_model) / mean_model) < 0.01
    assert np.mean(mean) == pytest.approx(np.mean(mean_model), rel=0.05)
    assert np.mean(var) == pytest.approx(np.mean(var_model), rel=0.05)


def test_frames_of_one_scene_have_noise_of_their_own_and_the_first_is_the_scenes(lcd):
    """seed_per_scene: the first frame of a scene depends on the scene alone (a resumed run
    recaptures it exactly); further frames of the unchanged scene (frames averaged per
    pattern) draw their own noise, with the model's variance, and a garbage-fault frame does
    not count; a new scene starts again from its first frame."""
    bench = FakeBench(BenchConfig.small(pupil_samples=64, subpixels=1))
    noise = NoiseModel()
    rng = np.random.default_rng(5)
    a = rng.integers(60, 200, size=(IDEAL.lcd_size[1], IDEAL.lcd_size[0]), dtype=np.uint8)
    b = 255 - a

    def camera():
        return FakeCamera(bench, lcd, lambda: 60.0, noise, seed=11, seed_per_scene=True)

    cam = camera()
    lcd.show(a)
    e = cam.expected_electrons()
    frames = [cam.capture().image for _ in range(3)]
    cam.faults.garbage = 1
    assert (cam.capture().image == 2 ** (noise.bit_depth - 1)).all()
    frames.append(cam.capture().image)
    later = [cam.capture().image.astype(np.float64) for _ in range(200)]
    lcd.show(b)
    other = cam.capture().image
    lcd.show(a)
    again = cam.capture().image
    fresh = camera()
    lcd.show(a)
    np.testing.assert_array_equal(fresh.capture().image, frames[0])
    fresh.capture(), fresh.capture()
    np.testing.assert_array_equal(fresh.capture().image, frames[3])  # the garbage not counted
    lcd.show(b)
    np.testing.assert_array_equal(fresh.capture().image, other)
    np.testing.assert_array_equal(again, frames[0])
    lit = e > 100
    for i in range(3):
        assert np.count_nonzero(frames[i][lit] != frames[i + 1][lit]) > 0.9 * lit.sum()
    stack = np.stack(later)
    var = stack.var(axis=0, ddof=1)[lit]
    assert np.mean(var) == pytest.approx(np.mean(noise.variance_adu(e)[lit]), rel=0.05)


def test_saturation_clips_at_full_scale(lcd):
    noise = NoiseModel(white_fraction=3.0)
    cam = FakeCamera(FakeBench(BenchConfig.small(pupil_samples=16, subpixels=1)), lcd,
                     lambda: 60.0, noise)
    lcd.show(np.full((IDEAL.lcd_size[1], IDEAL.lcd_size[0]), 255, np.uint8))
    img = cam.capture().image
    assert img.dtype == np.uint16 and img.max() == 4095
    assert np.mean(img == 4095) > 0.5


def test_vignetting_makes_corner_ltc_non_circular():
    bench = FakeBench(BenchConfig.small(spherical_mm=0.0))
    m = bench.true_ltc(40.0, normalise=True)
    w, h = bench.config.camera_size
    lw = bench.config.lcd_size[0]

    def axis_ratio(u, v):
        row = m[[v * w + u], :]
        x, y = row.indices % lw, row.indices // lw
        p = row.data / row.data.sum()
        mx, my = (p * x).sum(), (p * y).sum()
        cov = np.cov(np.stack([x - mx, y - my]), aweights=p)
        ev = np.linalg.eigvalsh(cov)
        return ev[0] / ev[1]

    assert axis_ratio(w // 2, h // 2) > 0.9
    assert axis_ratio(0, 0) < 0.7
    assert axis_ratio(w - 1, h - 1) < 0.7
    t = bench.true_ltc(40.0).sum(axis=1)
    assert t[0] < 0.8 * t[(h // 2) * w + w // 2]  # the cat's eye also loses light


def test_camera_fault_switches(lcd):
    cam = FakeCamera(FakeBench(BenchConfig.small(pupil_samples=16, subpixels=1)), lcd,
                     lambda: 60.0, NoiseModel())
    first = cam.capture()
    cam.faults.stale = 1
    assert cam.capture() is first
    cam.faults.drop = 2
    assert cam.capture().frame_id == first.frame_id + 3
    cam.faults.timeout = 1
    with pytest.raises(CameraTimeout, match="no frame within 0.050 s"):
        cam.capture(timeout=0.05)
    assert cam.capture().frame_id == first.frame_id + 4


def test_lcd_repeat_previous_fault_keeps_old_image_on_screen(lcd):
    a = np.zeros((IDEAL.lcd_size[1], IDEAL.lcd_size[0]), np.uint8)
    b = np.full_like(a, 255)
    lcd.show(a)
    lcd.faults.repeat_previous = 1
    shown = lcd.show(b)
    assert shown.frame_code is None and lcd.luminance().max() == 0.0
    lcd.show(b)
    assert lcd.luminance().min() == 1.0


def test_panel_gamma_response():
    r = PanelResponse(gamma=2.2, black_level=0.01)
    np.testing.assert_allclose(r.luminance(np.array([0, 255, 128])),
                               [0.01, 1.0, 0.01 + 0.99 * (128 / 255) ** 2.2], rtol=1e-6)


def test_bad_bench_and_camera_settings_are_rejected(lcd):
    with pytest.raises(ValueError, match="camera_size must be positive"):
        BenchConfig.small(camera_size=(0, 10))
    with pytest.raises(ValueError, match="differs from bench lcd_size"):
        FakeCamera(FakeBench(BenchConfig.small(lcd_size=(50, 50))), lcd, lambda: 0.0)
    cam = FakeCamera(FakeBench(IDEAL), lcd, lambda: 0.0)
    with pytest.raises(ValueError, match="exposure_ms must be > 0"):
        cam.exposure_ms = 0.0


def test_fake_camera_ltc_equals_the_virtual_scanners_for_the_same_pixel_and_depth():
    """One ground-truth lens: the virtual scanner's tracer (``sim.render.trace``, with the fake bench's
    ``AberratedLens``, K and pose) looking at the LCD plane gives the fake camera's true LTC.
    The LCD is stood in for by a projector 1 km away on its axis with f = D / pitch, so
    projector pixel = LCD pixel and N.L = 1 to 1e-9; each ray's weight is spread over the LCD
    pixels its pixel's footprint (a square of the pixel's size at the plane's depth) overlaps."""
    from sim.optics.rig import DeviceCalibration
    from sim.render.scene import PlaneObject, Pose, Scene
    from sim.render.trace import trace_camera

    c = BenchConfig.small(pupil_samples=64, subpixels=1)  # subpixels=1: the pixel centre's rays
    bench = FakeBench(c)
    z_mm = 40.0
    R, t = bench.camera_pose_in_lcd(z_mm)  # X_lcd = R X_cam + t
    (w, h), (lw, lh), pitch = c.camera_size, c.lcd_size, c.lcd_pitch_mm
    cam = DeviceCalibration(name="cam", K=bench.K, dist=np.zeros(5), R=R.T, T=-R.T @ t, size=(w, h))
    d = 1e6
    lcd_as_projector = DeviceCalibration(name="lcd", K=[[d / pitch, 0, 0], [0, d / pitch, 0], [0, 0, 1]],
                                         dist=np.zeros(5), R=np.eye(3), T=[0.0, 0.0, d], size=(lw, lh))
    plane = PlaneObject(size_mm=(4 * lw * pitch, 4 * lh * pitch), albedo=1.0,
                        pose=Pose(t=[(lw - 1) / 2 * pitch, (lh - 1) / 2 * pitch, 0.0]))
    pixels = np.array([0, w - 1, (h // 2) * w + w // 2, (h - 1) * w + 3, h * w - 1])
    tr = trace_camera(Scene(objects=[plane]).trace_geometry(), cam, lcd_as_projector, bench.lens,
                      pixels=pixels)
    truth = bench.true_ltc(z_mm)[pixels].toarray()
    steps = np.arange(-2, 3)
    for row, uv, wt, depth, want in zip(range(len(pixels)), tr.proj_uv, tr.weight, tr.depth,
                                        truth, strict=True):
        half = 0.5 * depth / (bench.K[0, 0] * pitch)  # the footprint's half-width, LCD px
        assert half < 2.5
        uv = uv.astype(np.float64)
        cells, frac = [], []
        for a in range(2):
            c = np.rint(uv[:, a])[:, None] + steps
            over = np.minimum(uv[:, a, None] + half, c + 0.5) - np.maximum(uv[:, a, None] - half,
                                                                          c - 0.5)
            cells.append(c)
            frac.append(np.clip(over, 0, None) / (2 * half))
        i = np.broadcast_to(cells[0][:, None, :], (len(uv), 5, 5))
        j = np.broadcast_to(cells[1][:, :, None], (len(uv), 5, 5))
        spread = wt[:, None, None] * frac[1][:, :, None] * frac[0][:, None, :]
        on_lcd = (spread > 0) & (i >= 0) & (i < lw) & (j >= 0) & (j < lh)
        got = np.bincount((j * lw + i)[on_lcd].astype(int), spread[on_lcd], minlength=lw * lh)
        assert np.count_nonzero(want) > 10, row  # defocused: the pixel sees a patch of the LCD
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-7)
    sums = truth.sum(axis=1)
    assert sums.min() < 0.8 * sums.max()  # vignetting at the corners is part of what agrees


def test_the_bench_keeps_its_true_ltcs_within_the_memory_budget(monkeypatch):
    import fakes.bench

    bench = FakeBench(BenchConfig.small(pupil_samples=64, subpixels=1))
    first = bench.true_ltc(10.0)
    one = first.data.nbytes + first.indices.nbytes + first.indptr.nbytes
    assert bench.true_ltc(10.0) is first  # kept
    monkeypatch.setattr(fakes.bench, "LTC_CACHE_BYTES", int(1.5 * one))
    bench.true_ltc(20.0)
    # over the budget: the older depth was dropped, and computed again it is the same LTC
    again = bench.true_ltc(10.0)
    assert again is not first and (again != first).nnz == 0
    assert bench.true_ltc(10.0) is again  # the latest is always kept
