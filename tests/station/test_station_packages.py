"""station.acquisition, station.ltc, station.lens: lazy re-exports of their public names."""

import importlib
import subprocess
import sys

import pytest

PACKAGES = ("station.acquisition", "station.ltc", "station.lens", "station.experiment")


def test_importing_the_packages_loads_no_heavy_module():
    code = ("import sys, station.acquisition, station.ltc, station.lens, station.experiment; "
            "print(','.join(m for m in ('zarr', 'matplotlib', 'numba', 'scipy') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == ""


@pytest.mark.parametrize("name", PACKAGES)
def test_every_public_name_resolves_to_its_submodule(name):
    pkg = importlib.import_module(name)
    for attr in pkg.__all__:
        value = getattr(pkg, attr)
        assert getattr(importlib.import_module(f"{name}.{pkg._EXPORTS[attr]}"), attr) is value
    assert set(pkg.__all__) <= set(dir(pkg))
    with pytest.raises(AttributeError, match=f"module '{name}' has no attribute 'nope'"):
        pkg.nope  # noqa: B018
