"""The measured-lens model file: exact round trip, ray geometry, interpolation, validation."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from sim.optics.lens import hit_plane
from sim.optics.measured_lens import FORMAT, LensFileError, MeasuredLens, load_lens, save_lens
from sim.optics.projection import pixel_to_normalized

K = np.array([[500.0, 0.0, 9.5], [0.0, 500.0, 7.5], [0.0, 0.0, 1.0]])


def make_lens(**over) -> MeasuredLens:
    """A 20 x 16 camera with nodes every 4th pixel (plus the last), K = 5 samples per node
    whose x, y encode the node (x = u / 10 + k, y = v / 10 - k) and weights (1..5) / 15."""
    nu = np.array([0.0, 4, 8, 12, 16, 19])
    nv = np.array([0.0, 4, 8, 12, 15])
    k = np.arange(5)
    x = nu[None, :, None] / 10 + k + 0 * nv[:, None, None]
    y = nv[:, None, None] / 10 - k + 0 * nu[None, :, None]
    w = np.broadcast_to((k + 1) / 15.0, x.shape).copy()
    args = {"focus_distance_mm": 250.0, "optical_centre_mm": np.array([1.0, 2.0, -100.0]),
            "camera_size": (20, 16), "node_u": nu, "node_v": nv, "aperture_x_mm": x,
            "aperture_y_mm": y, "weights": w, "transmittance": np.full((5, 6), 0.8),
            "interpolation": "bilinear", "camera_matrix": K, "dist_coeffs": np.zeros(5),
            "metadata": {"source": "test"}}
    args.update(over)
    return MeasuredLens(**args)


def test_round_trip_is_identical(tmp_path):
    lens = make_lens()
    back = load_lens(save_lens(tmp_path / "lens.npz", lens))
    for name in ("optical_centre_mm", "node_u", "node_v", "aperture_x_mm", "aperture_y_mm",
                 "weights", "transmittance", "camera_matrix", "dist_coeffs"):
        np.testing.assert_array_equal(getattr(back, name), getattr(lens, name), err_msg=name)
    assert (back.focus_distance_mm, back.camera_size, back.interpolation, back.metadata) == (
        lens.focus_distance_mm, lens.camera_size, lens.interpolation, lens.metadata)
    uv = np.array([[3.3, 5.1], [19.0, 15.0]])
    b1, b2 = lens.bundle(pixel_to_normalized(uv, K), uv), back.bundle(
        pixel_to_normalized(uv, K), uv)
    np.testing.assert_array_equal(b1.directions, b2.directions)


def test_round_trip_without_optional_fields(tmp_path):
    lens = make_lens(camera_matrix=None, dist_coeffs=None, interpolation="nearest")
    back = load_lens(save_lens(tmp_path / "lens.npz", lens))
    assert back.camera_matrix is None and back.dist_coeffs is None
    np.testing.assert_array_equal(back.aperture_x_mm, lens.aperture_x_mm)


def test_bundle_rays_start_on_samples_and_meet_at_the_in_focus_point():
    lens = make_lens()
    uv = np.array([[4.0, 8.0], [12.0, 0.0]])  # exactly on nodes
    xy_n = pixel_to_normalized(uv, K)
    b = lens.bundle(xy_n, uv)
    k = np.arange(5)
    np.testing.assert_allclose(b.origins[..., 0], uv[:, :1] / 10 + k, atol=1e-12)
    np.testing.assert_allclose(b.origins[..., 1], uv[:, 1:] / 10 - k, atol=1e-12)
    np.testing.assert_array_equal(b.origins[..., 2], 0.0)
    at_focus = hit_plane(b.origins, b.directions, 250.0)
    np.testing.assert_allclose(at_focus, np.broadcast_to(xy_n[:, None] * 250.0, at_focus.shape),
                               atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(b.directions, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(b.weights, 0.8 * (k + 1) / 15.0 + 0 * uv[:, :1], atol=1e-15)
    # uv from K when omitted
    b2 = lens.bundle(xy_n)
    np.testing.assert_allclose(b2.origins, b.origins, atol=1e-9)


def test_bilinear_and_nearest_between_nodes():
    uv = np.array([[6.0, 10.0], [17.5, 15.0], [-3.0, 40.0]])  # mid-cell, last span, outside
    x, y, w = make_lens().samples_at(uv)
    # x is linear in u: bilinear reproduces it exactly inside the grid; outside it clamps
    np.testing.assert_allclose(x[:, 0], [0.6, 1.75, 0.0], atol=1e-12)
    np.testing.assert_allclose(y[:, 1], [1.0 - 1, 1.5 - 1, 1.5 - 1], atol=1e-12)
    np.testing.assert_allclose(w.sum(axis=1), 0.8, atol=1e-12)
    xn, yn, _ = make_lens(interpolation="nearest").samples_at(uv)
    np.testing.assert_allclose(xn[:, 0], [0.4, 1.6, 0.0], atol=1e-12)  # u nodes 4 (tie), 16, 0
    np.testing.assert_allclose(yn[:, 0], [0.8, 1.5, 1.5], atol=1e-12)  # v nodes 8 (tie), 15, 15


def write_npz(path, **fields):
    with open(path, "wb") as f:
        np.savez(f, **fields)
    return path


def lens_fields(**over):
    lens = make_lens()
    d = {"format": np.array(FORMAT), "format_version": np.array(1),
         "focus_distance_mm": np.array(250.0), "optical_centre_mm": lens.optical_centre_mm,
         "camera_size": np.array([20, 16]), "node_u": lens.node_u, "node_v": lens.node_v,
         "aperture_x_mm": lens.aperture_x_mm, "aperture_y_mm": lens.aperture_y_mm,
         "weights": lens.weights, "transmittance": lens.transmittance,
         "interpolation": np.array("bilinear")}
    d.update(over)
    return {k: v for k, v in d.items() if v is not None}


def test_corrupted_and_missing_files(tmp_path):
    with pytest.raises(LensFileError, match="no such measured-lens file"):
        load_lens(tmp_path / "nope.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"PK\x03\x04 this is not really a zip file")
    with pytest.raises(LensFileError, match=r"bad\.npz: not a readable measured-lens"):
        load_lens(bad)
    good = save_lens(tmp_path / "good.npz", make_lens())
    cut = tmp_path / "cut.npz"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(LensFileError, match=r"cut\.npz: not a readable"):
        load_lens(cut)
    assert zipfile.is_zipfile(good)


@pytest.mark.parametrize(
    ("over", "message"),
    [
        ({"format": np.array("something-else")}, "field 'format' is 'something-else'"),
        ({"format_version": np.array(2)}, "field 'format_version' is 2; this reader supports"),
        ({"format_version": np.array([1, 1])}, "field 'format_version' must be a scalar"),
        ({"focus_distance_mm": np.array("far")}, "field 'focus_distance_mm' is not a float"),
        ({"weights": None}, r"missing field\(s\) \['weights'\]"),
        ({"extra_thing": np.zeros(2)}, r"unknown field\(s\) \['extra_thing'\]"),
        ({"metadata_json": np.array("{not json")}, "field 'metadata_json' is not JSON"),
        ({"node_u": np.array(["a", "b"])}, "field 'node_u' must be real numbers"),
    ],
)
def test_file_level_errors_name_file_and_field(tmp_path, over, message):
    path = write_npz(tmp_path / "lens.npz", **lens_fields(**over))
    with pytest.raises(LensFileError, match=rf"lens\.npz: {message}"):
        load_lens(path)


def _bad(name, fn):
    lens = make_lens()
    a = np.array(getattr(lens, name), dtype=np.float64, copy=True)
    return {name: fn(a)}


def _nan(a):
    a.flat[min(3, a.size - 1)] = np.nan
    return a


def _zero_node(a):
    a[1, 2] = 0.0
    return a


def _neg(a):
    a.flat[0] = -a.flat[0] - 1
    return a


@pytest.mark.parametrize(
    ("over", "message"),
    [
        (_bad("aperture_x_mm", _nan), r"field 'aperture_x_mm' has 1 NaN"),
        (_bad("weights", _nan), r"field 'weights' has 1 NaN"),
        (_bad("weights", _zero_node),
         r"field 'weights' must sum to 1 per node; node \(row 1, col 2\) sums to 0.0"),
        (_bad("weights", _neg), "field 'weights' has negative values"),
        (_bad("transmittance", _neg), "field 'transmittance' has negative values"),
        (_bad("transmittance", _nan), "field 'transmittance' has 1 NaN"),
        (_bad("optical_centre_mm", _nan), "field 'optical_centre_mm' has 1 NaN"),
        (_bad("node_u", _nan), "field 'node_u' has 1 NaN"),
        ({"node_u": np.array([0.0, 8, 4, 12, 16, 19])}, "field 'node_u' must increase strictly"),
        ({"node_v": np.array([0.0, 4, 8, 12, 16])},
         r"field 'node_v' must increase strictly within \[0, 15\]"),
        ({"node_v": np.zeros((0,))}, "field 'node_v' must be a non-empty 1-D array"),
        ({"weights": np.full((5, 6, 4), 0.25)}, "field 'aperture_x_mm' must have the shape of"),
        ({"weights": np.full((6, 5, 5), 0.2)}, r"field 'weights' must have shape \(len\(node_v\)"),
        ({"transmittance": np.ones((6, 5))}, r"field 'transmittance' must have shape \(5, 6\)"),
        ({"focus_distance_mm": np.array(-1.0)}, "field 'focus_distance_mm' must be > 0"),
        ({"camera_size": np.array([20, 16, 3])}, "field 'camera_size' must be"),
        ({"camera_size": np.array([0, 16])}, "field 'camera_size' must be"),
        ({"optical_centre_mm": np.zeros(2)}, r"field 'optical_centre_mm' must have shape \(3,\)"),
        ({"interpolation": np.array("cubic")}, "field 'interpolation' must be one of"),
        ({"camera_matrix": np.eye(2)}, "field 'camera_matrix' must be 3x3"),
        ({"camera_matrix": np.full((3, 3), np.nan)}, "field 'camera_matrix' has 9 NaN"),
        ({"dist_coeffs": np.zeros(4)}, "field 'dist_coeffs' must have 5 values"),
        ({"dist_coeffs": np.full(5, np.inf)}, "field 'dist_coeffs' has 5 NaN or infinite"),
        ({"focus_zones_mm": np.zeros(3)}, r"field 'focus_zones_mm' must have shape \(Z >= 2, 2\)"),
        ({"focus_zones_mm": np.array([[0.0, 250.0], [0.0, 251.0]])},
         "field 'focus_zones_mm' must have pupil radii"),
        ({"focus_zones_mm": np.array([[0.0, 250.0], [2.0, -1.0]])},
         "field 'focus_zones_mm' must have focus distances"),
        ({"focus_zones_mm": np.array([[0.0, np.nan], [2.0, 1.0]])},
         "field 'focus_zones_mm' has 1 NaN"),
    ],
)
def test_value_errors_name_file_and_field(tmp_path, over, message):
    path = write_npz(tmp_path / "lens.npz", **lens_fields(**over))
    with pytest.raises(LensFileError, match=rf"lens\.npz: {message}"):
        load_lens(path)


def test_bundle_errors():
    lens = make_lens(camera_matrix=None)
    with pytest.raises(LensFileError, match="needs uv .pixel coordinates.: the lens has no "
                       "camera_matrix"):
        lens.bundle(np.zeros((2, 2)))
    with pytest.raises(LensFileError, match="xy_n has 2 rows but uv has 1"):
        lens.bundle(np.zeros((2, 2)), np.zeros((1, 2)))


def test_metadata_is_json(tmp_path):
    path = save_lens(tmp_path / "lens.npz", make_lens(metadata={"a": [1, 2], "b": None}))
    with np.load(path, allow_pickle=False) as z:
        assert json.loads(str(z["metadata_json"])) == {"a": [1, 2], "b": None}


def test_gaussian_baseline_takes_the_second_moment_at_the_optical_centre():
    """docs/optics.md section 4: four samples at +-a on each axis have per-axis variance a^2 / 2;
    the Gaussian equivalent has that sigma and the lens's focus distance."""
    from sim.optics.measured_lens import centre_moments, gaussian_equivalent

    a, k = 3.0, 4
    lens = MeasuredLens(focus_distance_mm=500.0, optical_centre_mm=np.zeros(3), camera_size=(9, 7),
                        node_u=np.array([0.0]), node_v=np.array([0.0]),
                        aperture_x_mm=np.reshape([a, -a, 0, 0], (1, 1, k)),
                        aperture_y_mm=np.reshape([0, 0, a, -a], (1, 1, k)),
                        weights=np.full((1, 1, k), 1 / k), transmittance=np.ones((1, 1)),
                        camera_matrix=np.array([[50.0, 0, 4.0], [0, 50.0, 3.0], [0, 0, 1]]))
    mean, cov = centre_moments(lens)
    np.testing.assert_allclose(mean, 0, atol=1e-12)
    np.testing.assert_allclose(cov, np.diag([a * a / 2, a * a / 2]), atol=1e-12)
    g = gaussian_equivalent(lens)
    assert g.sigma_mm == pytest.approx(a / np.sqrt(2))
    assert (g.focus_distance_mm, g.samples) == (500.0, 4)
    b = g.bundle(np.zeros((1, 2)))
    w, xy = b.weights[0], b.origins[0, :, :2]
    assert np.mean(w @ xy**2) == pytest.approx(a * a / 2, rel=1e-9)  # per-axis variance


def test_focus_zones_aim_each_sample_at_its_zone_and_round_trip(tmp_path):
    """With ``focus_zones_mm`` ray k crosses the pixel's line of sight at the focus of its
    pupil radius (linear between rows, clamped beyond them); the table round-trips, and a
    file without it aims every ray at ``focus_distance_mm``."""
    zones = np.array([[0.0, 240.0], [2.0, 250.0], [4.0, 270.0]])
    lens = make_lens(focus_zones_mm=zones)
    back = load_lens(save_lens(tmp_path / "lens.npz", lens))
    np.testing.assert_array_equal(back.focus_zones_mm, zones)
    assert load_lens(save_lens(tmp_path / "plain.npz", make_lens())).focus_zones_mm is None
    uv = np.array([[4.0, 8.0], [12.0, 0.0]])
    xy_n = pixel_to_normalized(uv, K)
    b = back.bundle(xy_n, uv)
    rho = np.hypot(b.origins[..., 0], b.origins[..., 1])
    z_k = np.interp(rho, zones[:, 0], zones[:, 1])
    assert rho.max() > 4.0 and rho.min() < 2.0  # samples in both rows' spans and beyond
    for i in range(2):
        for k in range(5):
            p = hit_plane(b.origins[i, k], b.directions[i, k], z_k[i, k])
            np.testing.assert_allclose(p, xy_n[i] * z_k[i, k], atol=1e-9)


def test_aim_offset_moves_each_pixels_in_focus_point_and_round_trips(tmp_path):
    """With ``aim_offset`` e every sample of a pixel aims at ``(xy_n + e) z_f``, e read from
    the nodes like the samples (bilinear between them); the field round-trips, through
    ``save_lens`` and through the streaming ``LensFileWriter``, and a wrong shape is refused
    naming the field."""
    from sim.optics.measured_lens import LensFileWriter

    nu, nv = np.array([0.0, 4, 8, 12, 16, 19]), np.array([0.0, 4, 8, 12, 15])
    e = np.stack([1e-4 * nu[None, :] + 0 * nv[:, None], -2e-4 * nv[:, None] + 0 * nu[None, :]],
                 axis=-1)  # linear in u and v: bilinear reads it exactly
    lens = make_lens(aim_offset=e)
    back = load_lens(save_lens(tmp_path / "lens.npz", lens))
    np.testing.assert_array_equal(back.aim_offset, e)
    uv = np.array([[4.0, 8.0], [10.0, 6.0], [17.5, 13.0]])
    xy_n = pixel_to_normalized(uv, K)
    b = back.bundle(xy_n, uv)
    want = xy_n + np.stack([1e-4 * uv[:, 0], -2e-4 * uv[:, 1]], axis=1)
    at_focus = hit_plane(b.origins, b.directions, 250.0)
    np.testing.assert_allclose(at_focus, np.broadcast_to(want[:, None] * 250.0, at_focus.shape),
                               atol=1e-9)
    # the streaming writer stores it too
    w = LensFileWriter(tmp_path / "streamed.npz", nu, nv, 5)
    w.write_nodes(0, 0, lens.aperture_x_mm, lens.aperture_y_mm, lens.weights)
    w.close(focus_distance_mm=250.0, optical_centre_mm=lens.optical_centre_mm,
            camera_size=(20, 16), transmittance=lens.transmittance, camera_matrix=K,
            aim_offset=e)
    np.testing.assert_array_equal(load_lens(tmp_path / "streamed.npz").aim_offset, e)
    with pytest.raises(LensFileError, match="aim_offset"):
        make_lens(aim_offset=e[:, :3])


def test_gaussian_baseline_reads_moments_between_nodes_not_blended_samples():
    """Two nodes with the same aperture distribution, its samples in another order: halfway
    between them the second moment is that distribution's (blending sample k of one node
    with sample k of the other would shrink it to nothing here)."""
    from sim.optics.measured_lens import centre_moments

    a = 3.0
    xs = np.array([[a, -a, 0.0, 0.0], [-a, a, 0.0, 0.0]])
    ys = np.array([[0.0, 0.0, a, -a], [0.0, 0.0, -a, a]])
    lens = MeasuredLens(focus_distance_mm=500.0, optical_centre_mm=np.zeros(3), camera_size=(9, 7),
                        node_u=np.array([0.0, 8.0]), node_v=np.array([0.0]),
                        aperture_x_mm=xs[None], aperture_y_mm=ys[None],
                        weights=np.full((1, 2, 4), 0.25), transmittance=np.ones((1, 2)),
                        camera_matrix=np.array([[50.0, 0, 4.0], [0, 50.0, 3.0], [0, 0, 1]]))
    mean, cov = centre_moments(lens)
    np.testing.assert_allclose(mean, 0, atol=1e-12)
    np.testing.assert_allclose(cov, np.diag([a * a / 2, a * a / 2]), atol=1e-12)
