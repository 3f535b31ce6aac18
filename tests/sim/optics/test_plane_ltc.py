"""sim.optics.plane_ltc: exact LTC of a camera looking at a pixelated plane, against geometry."""

import numpy as np
import pytest

from sim.optics.lens import AberratedLens, PinholeLens
from sim.optics.plane_ltc import plane_ltc, subpixel_offsets

W, H, F_PX = 40, 30, 640.0
K = np.array([[F_PX, 0, (W - 1) / 2], [0, F_PX, (H - 1) / 2], [0, 0, 1.0]])
PITCH = 0.2715
PLANE = (96, 72)


def _pose(distance_mm):
    centre = np.array([(PLANE[0] - 1) / 2 * PITCH, (PLANE[1] - 1) / 2 * PITCH, -distance_mm])
    return np.eye(3), centre


def _image_of_plane_pixel(m, i, j):
    return m[:, [j * PLANE[0] + i]].toarray().reshape(H, W)


def _moment_diameter_px(img, box_px):
    """Diameter of a uniform disk from an image's second moments, less two pixel boxes."""
    yy, xx = np.mgrid[: img.shape[0], : img.shape[1]]
    s = img.sum()
    mx, my = (img * xx).sum() / s, (img * yy).sum() / s
    var = 0.5 * ((img * (xx - mx) ** 2).sum() + (img * (yy - my) ** 2).sum()) / s
    return 4.0 * np.sqrt(var - 1.0 / 12.0 - box_px**2 / 12.0)


def test_subpixel_grid_is_centred():
    o = subpixel_offsets(3)
    assert o.shape == (9, 2)
    np.testing.assert_allclose(o.mean(axis=0), 0.0, atol=1e-15)
    assert np.abs(o).max() == pytest.approx(1 / 3)
    with pytest.raises(ValueError, match="n >= 1"):
        subpixel_offsets(0)


def test_thin_lens_blur_disk_of_one_plane_pixel():
    z_f, d = 250.0, 150.0
    lens = AberratedLens(pupil_diameter_mm=8.0, focus_distance_mm=z_f, samples=600)
    R, t = _pose(d)
    m = plane_ltc(K, None, (W, H), lens, R, t, PLANE, PITCH, subpixels=4)
    img = _image_of_plane_pixel(m, 48, 36)
    expected = 8.0 * abs(d - z_f) / z_f * F_PX / d
    measured = _moment_diameter_px(img, PITCH * F_PX / d)
    assert measured == pytest.approx(expected, rel=0.02)


def test_rows_conserve_light_when_plane_fills_view():
    lens = AberratedLens(pupil_diameter_mm=8.0, focus_distance_mm=250.0, samples=64)
    R, t = _pose(200.0)
    m = plane_ltc(K, None, (W, H), lens, R, t, PLANE, PITCH, subpixels=2)
    np.testing.assert_allclose(m.sum(axis=1), 1.0, atol=1e-12)


def test_pinhole_centroid_is_projection_of_pixel_centre():
    R, t = _pose(180.0)
    m = plane_ltc(K, None, (W, H), PinholeLens(), R, t, PLANE, PITCH, subpixels=16)
    cols = np.arange(PLANE[0] * PLANE[1])
    cx = (m @ (cols % PLANE[0]).astype(float)).reshape(H, W)
    u = np.arange(W)
    expected = (t[0] + (u - K[0, 2]) / F_PX * 180.0) / PITCH
    # the footprint (1.04 plane px) is binned to plane pixels: centroid within 0.05 px
    np.testing.assert_allclose(cx[H // 2], expected, atol=0.05)


def test_selected_pixels_only_and_plane_behind_camera_is_dark():
    lens = AberratedLens(pupil_diameter_mm=4.0, focus_distance_mm=250.0, samples=16)
    R, t = _pose(200.0)
    m = plane_ltc(K, None, (W, H), lens, R, t, PLANE, PITCH, subpixels=1, pixels=[5, 77])
    assert set(np.flatnonzero(np.diff(m.indptr))) == {5, 77}
    t_behind = t.copy()
    t_behind[2] = 200.0
    dark = plane_ltc(K, None, (W, H), lens, R, t_behind, PLANE, PITCH, subpixels=1)
    assert dark.nnz == 0


def test_pinhole_ltc_is_the_area_overlap_of_the_pixels_footprint():
    """Through a pinhole a camera pixel sees a square of F_PX^-1 d mm on a plane facing it: its
    LTC is that square's area overlap with each plane pixel (analytic), whatever the
    subpixel grid (the subpixels' footprints tile the pixel's)."""
    d = 200.0
    R, t = _pose(d)
    side = d / F_PX / PITCH  # the footprint's side, plane pixels (1.15)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    cx = (t[0] + (u - K[0, 2]) / F_PX * d) / PITCH
    cy = (t[1] + (v - K[1, 2]) / F_PX * d) / PITCH
    cells = np.arange(-3, 4)

    def overlap(centre):  # (H, W, 7): overlap of [centre +- side/2] with cells c +- 0.5
        c = np.rint(centre)[..., None] + cells
        over = np.minimum(centre[..., None] + side / 2, c + 0.5) - \
            np.maximum(centre[..., None] - side / 2, c - 0.5)
        return c, np.clip(over, 0, None) / side

    (ix, fx), (iy, fy) = overlap(cx), overlap(cy)
    want = np.zeros((H * W, PLANE[0] * PLANE[1]))
    rows = np.broadcast_to(np.arange(H * W).reshape(H, W, 1, 1), (H, W, 7, 7))
    col = (iy[..., :, None] * PLANE[0] + ix[..., None, :]).astype(int)
    np.add.at(want, (rows.ravel(), col.ravel()), (fy[..., :, None] * fx[..., None, :]).ravel())
    for n in (1, 2, 3):
        m = plane_ltc(K, None, (W, H), PinholeLens(), R, t, PLANE, PITCH, subpixels=n)
        np.testing.assert_allclose(m.toarray(), want, atol=1e-12)


def test_a_footprint_too_wide_for_the_kernel_asks_for_more_subpixels():
    # at 3 m a camera pixel's footprint is 17 plane pixels wide: one subpixel's is refused,
    # 2 x 2 subpixels' (8.6 plane pixels) deposit the centre pixel's whole light on the plane
    R, t = _pose(3000.0)
    with pytest.raises(ValueError, match="more subpixels"):
        plane_ltc(K, None, (W, H), PinholeLens(), R, t, PLANE, PITCH, subpixels=1)
    m = plane_ltc(K, None, (W, H), PinholeLens(), R, t, PLANE, PITCH, subpixels=2)
    centre = (H // 2) * W + W // 2
    assert m[[centre], :].sum() == pytest.approx(1.0, abs=1e-12)
