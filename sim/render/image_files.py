"""Rendered images on disk: PNG files (8-bit, or 16-bit holding 12- and 16-bit DN unscaled) and
a zarr v3 stack of every camera's images and truth maps (``sim.render.images.RenderResult``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import zarr

from sim.errors import SimInputError

if TYPE_CHECKING:
    from sim.render.images import RenderResult


def write_png(path: str | Path, image: np.ndarray, bit_depth: int) -> None:
    """Write one image (H, W): 8 bits as 8-bit PNG; 12 and 16 bits as 16-bit PNG holding the
    DN values unscaled (a 12-bit image keeps 0..4095, it is not shifted to the top bits)."""
    image = np.asarray(image)
    want = {8: np.uint8, 12: np.uint16, 16: np.uint16}.get(bit_depth)
    if want is None:
        raise SimInputError(f"write_png: bit_depth must be 8, 12 or 16, got {bit_depth}")
    if image.ndim != 2 or image.dtype != want or (bit_depth == 12 and image.max(initial=0) > 4095):
        raise SimInputError(f"write_png {path}: expected a 2-D {np.dtype(want).name} image with values "
                         f"< 2^{bit_depth}, got {image.dtype} {image.shape}")
    ok, png = cv2.imencode(".png", image)  # encoded here, so a full disk is Python's OSError
    if not ok:
        raise SimInputError(f"write_png {path}: OpenCV could not encode the image")
    with open(path, "wb") as f:
        f.write(png.tobytes())


def write_pngs(directory: str | Path, images: np.ndarray, bit_depth: int) -> list[Path]:
    """Write images (n, H, W) as ``directory/pattern_000.png`` ...; returns the paths."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    paths = [d / f"pattern_{i:03d}.png" for i in range(len(images))]
    for p, im in zip(paths, images):
        write_png(p, im, bit_depth)
    return paths


def write_zarr(path: str | Path, result: RenderResult, attrs: dict | None = None,
               radiance: bool = False) -> None:
    """Write a zarr v3 stack: group ``camera_<i>`` per camera with ``images`` (n, H, W, one
    chunk per image), ``depth`` (H, W) mm, ``projector_map`` (H, W, 2) projector px,
    ``lit`` (H, W), ``object_id`` (H, W) and, if asked, ``radiance`` (n, H, W) float32;
    ``attrs`` (JSON-able) go on the root group, the camera name and timings on each group."""
    root = zarr.open_group(str(path), mode="w", attributes=attrs or {})
    for i, c in enumerate(result.cameras):
        g = root.create_group(f"camera_{i}", attributes={"name": c.name, "timings": c.timings,
                                                             "rays": c.n_rays})
        h, w = c.depth.shape
        g.create_array("images", data=c.images, chunks=(1, h, w))
        if radiance:
            g.create_array("radiance", data=c.radiance, chunks=(1, h, w))
        g.create_array("depth", data=c.depth, chunks=(h, w))
        g.create_array("projector_map", data=c.projector_map, chunks=(h, w, 2))
        g.create_array("lit", data=c.lit, chunks=(h, w))
        g.create_array("object_id", data=c.object_id, chunks=(h, w))
