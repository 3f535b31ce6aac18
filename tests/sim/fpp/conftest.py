"""Shared by the rendered-scan tests: rig cameras cropped to a window around the world origin."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest


def crop_about_origin(cam, size: tuple[int, int]):
    """Camera ``cam`` cut to a ``size`` (width, height) window of its sensor around the world
    origin's image (a whole-pixel shift of the principal point: pixels keep their rays)."""
    uv = cam.project(np.zeros((1, 3)))[0]
    k = cam.K_array.copy()
    k[0, 2] -= np.round(uv[0] - (size[0] - 1) / 2)
    k[1, 2] -= np.round(uv[1] - (size[1] - 1) / 2)
    return cam.model_copy(update={"K": k.tolist(), "size": size})


@pytest.fixture(scope="session")
def crop() -> Callable:
    """:func:`crop_about_origin`."""
    return crop_about_origin
