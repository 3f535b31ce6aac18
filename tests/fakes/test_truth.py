"""fakes.truth: the true lens of a fake-bench run, from its stored config."""

import numpy as np

from fakes.bench import BenchConfig, FakeBench
from fakes.truth import lens_truth, optical_centre_error


def test_truth_of_a_fake_run_and_none_for_a_real_one():
    bench = FakeBench(BenchConfig.small())
    truth = lens_truth({"backend": "fake", "fake": {}})
    np.testing.assert_array_equal(truth["optical_centre_mm"], bench.optical_centre_station_mm())
    assert truth["focus_distance_mm"] == bench.config.focus_distance_mm
    assert lens_truth({"backend": "real"}) is None
    c = np.asarray(truth["optical_centre_mm"])
    err = optical_centre_error({"optical_centre_mm": (c + [0.3, 0.0, -0.4]).tolist()}, truth)
    np.testing.assert_allclose(err["optical_centre_error_mm"], [0.3, 0.0, -0.4], atol=1e-12)
    assert abs(err["optical_centre_error_norm_mm"] - 0.5) < 1e-12
