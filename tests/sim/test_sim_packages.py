"""The sim packages re-export their public names lazily, and importing them stays cheap."""

import importlib
import pkgutil
import subprocess
import sys

import pytest

PACKAGES = ("sim.optics", "sim.render", "sim.fpp", "sim.metrology", "sim.dataset", "sim.calibration")


@pytest.mark.parametrize("name", PACKAGES)
def test_every_public_name_resolves_to_its_definition(name):
    pkg = importlib.import_module(name)
    subs = {m.name for m in pkgutil.iter_modules(pkg.__path__)}
    assert pkg.__all__ and sorted(pkg.__all__) == pkg.__all__
    for attr in pkg.__all__:
        assert attr not in subs, f"{name}.{attr} is also a submodule: the two would shadow"
        value = getattr(pkg, attr)
        assert getattr(importlib.import_module(f"{name}.{pkg._EXPORTS[attr]}"), attr) is value
        assert attr in dir(pkg)
    with pytest.raises(AttributeError, match="has no attribute 'no_such_name'"):
        _ = pkg.no_such_name


def test_importing_the_packages_loads_neither_numba_nor_embreex():
    code = ("import sys, sim.optics, sim.render, sim.fpp, sim.metrology, sim.dataset, sim.calibration; "
            "print(sorted(m for m in ('numba', 'embreex') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
