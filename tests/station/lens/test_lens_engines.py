"""The lens derivation on every engine, and streamed to a file, gives the same lens bit for
bit as the in-memory, single-process derivation."""

from __future__ import annotations

import numpy as np
import pytest

from fakes.bench import BenchConfig, FakeBench
from sim.optics.measured_lens import load_lens, read_lens_nodes
from station.api import derive_lens
from station.lens.geometry import LensFitConfig
from tests.support.ltc_stores import write_true_ltc_store

P = 24
DEPTHS = [0.0, 30.0, 60.0, 250.0, 290.0]
ARRAYS = ("aperture_x_mm", "aperture_y_mm", "weights", "transmittance", "node_u", "node_v",
          "optical_centre_mm", "camera_matrix")


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """A 40 x 30 LTC store in 16 x 16 tiles (6 tiles), the bench's LTC plus noise, with one
    pixel without signal at three depths (its node is filled from a neighbour)."""
    bench = FakeBench(BenchConfig.small(lcd_size=(120, 96), lcd_distance_at_zero_mm=100.0,
                                        pupil_samples=150, subpixels=1))
    return write_true_ltc_store(tmp_path_factory.mktemp("engines") / "ltc.zarr", bench, DEPTHS,
                                period=P, tile_px=16, hole_px=(17, 20), hole_depths=3,
                                gain_jitter=100.0)


@pytest.mark.slow
def test_streamed_and_dask_lenses_equal_the_in_memory_one(store, tmp_path):
    cfg = LensFitConfig.basic()  # every pixel a node
    ref = derive_lens(store, cfg, progress=False, workers=1)
    assert ref.filled_nodes == 1
    a = derive_lens(store, cfg, progress=False, workers=1, out=tmp_path / "serial.npz")
    b = derive_lens(store, cfg, progress=False, workers=2, dask=True,
                    out=tmp_path / "dask.npz")
    assert a.lens is None and a.lens_path == tmp_path / "serial.npz"
    assert not (tmp_path / "serial.npz.partial").exists()
    la, lb = load_lens(a.lens_path), load_lens(b.lens_path)
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(la, name), getattr(ref.lens, name), err_msg=name)
        np.testing.assert_array_equal(getattr(lb, name), getattr(ref.lens, name), err_msg=name)
    assert la.focus_distance_mm == lb.focus_distance_mm == ref.lens.focus_distance_mm
    assert la.metadata == lb.metadata == ref.lens.metadata
    assert a.summary() == b.summary() == ref.summary()
    nodes = np.array([0, 17 * 40 + 20, 40 * 30 - 1])
    x, y, w = read_lens_nodes(a.lens_path, nodes)
    np.testing.assert_array_equal(x, ref.lens.aperture_x_mm.reshape(-1, 32)[nodes])
    np.testing.assert_array_equal(w, (ref.lens.weights * ref.lens.transmittance[..., None])
                                  .reshape(-1, 32)[nodes])


def test_lens_file_writer_checks_blocks_and_leaves_nothing_when_aborted(tmp_path):
    from sim.optics.measured_lens import LensFileError, LensFileWriter

    path = tmp_path / "l.npz"
    wr = LensFileWriter(path, np.arange(3.0), np.arange(2.0), 4)
    x = np.zeros((2, 3, 4))
    with pytest.raises(LensFileError, match="'weights' of nodes from row 0, col 0"):
        wr.write_nodes(0, 0, x, x, np.full((2, 3, 4), 0.3))
    wr.write_nodes(0, 0, x + 1.0, x, np.full((2, 3, 4), 0.25))
    with pytest.raises(LensFileError, match="'transmittance' must have shape"):
        wr.close(focus_distance_mm=100.0, optical_centre_mm=np.zeros(3), camera_size=(3, 2),
                 transmittance=np.ones((3, 2)))
    wr.abort()
    assert not path.exists() and not (tmp_path / "l.npz.partial").exists()
    wr = LensFileWriter(path, np.arange(3.0), np.arange(2.0), 4)
    wr.write_nodes(0, 0, x + np.arange(6.0).reshape(2, 3, 1), x, np.full((2, 3, 4), 0.25))
    wr.copy_nodes(np.array([5]), np.array([0]))
    wr.close(focus_distance_mm=100.0, optical_centre_mm=np.zeros(3), camera_size=(3, 2),
             transmittance=np.ones((2, 3)))
    lens = load_lens(path)
    np.testing.assert_array_equal(lens.aperture_x_mm[..., 0], [[0, 1, 2], [3, 4, 0]])
    assert lens.weights.sum() == pytest.approx(6.0)
