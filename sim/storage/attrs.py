"""Checks of a zarr store's root metadata and attributes on opening, shared by the run store
(``station.acquisition.run_store``) and the LTC store (``station.ltc.store``): a malformed
``zarr.json`` or an attribute of the wrong type or value is refused with one line naming the
store and the attribute, before any code uses it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any

import zarr
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError


def _finite(v: float) -> float:
    if not math.isfinite(v):
        raise ValueError(f"must be finite, got {v}")
    return v


Finite = Annotated[float, AfterValidator(_finite)]
Size = Annotated[list[Annotated[int, Field(ge=1)]], Field(min_length=2, max_length=2)]


class RunStoreAttrs(BaseModel):
    """The attributes a run store must have, with their types (docs/formats.md)."""

    model_config = ConfigDict(extra="allow", strict=True)
    format: str
    format_version: int
    config: dict[str, Any]
    pattern_set: dict[str, Any]
    software: dict[str, Any]
    start_time: str
    depths_mm: list[Finite] = Field(min_length=1)
    camera_size: Size
    bit_depth: int = Field(ge=1, le=16)
    lcd_size: Size
    lcd_pitch_mm: Finite = Field(gt=0)
    tile_px: int = Field(ge=1)
    display_lut: list[Finite] | None


class LtcStoreAttrs(BaseModel):
    """The attributes an LTC store must have, with their types (docs/formats.md)."""

    model_config = ConfigDict(extra="allow", strict=True)
    format: str
    depths_mm: list[Finite] = Field(min_length=1)
    pitch_mm: Finite = Field(gt=0)
    camera_size: Size
    camera_matrix: Annotated[list[Annotated[list[Finite], Field(min_length=3, max_length=3)]],
                             Field(min_length=3, max_length=3)] | None = None
    dist_coeffs: Annotated[list[Finite], Field(min_length=5, max_length=5)] | None = None


def open_zarr_group(path: Path, mode: str, error: type[ValueError], what: str) -> zarr.Group:
    """``zarr.open_group``, with a malformed ``zarr.json`` refused as ``error`` naming the path
    (an ``OSError`` stays an ``OSError``)."""
    try:
        return zarr.open_group(str(path), mode=mode)
    except FileNotFoundError as exc:  # zarr's GroupNotFoundError: no zarr.json
        raise error(f"{path}: not a zarr group, so not a {what} ({exc})") from exc
    except OSError:
        raise
    except Exception as exc:  # noqa: BLE001 - zarr's metadata parser raises anything on bad JSON
        detail = " ".join(str(exc).split())[:200]
        raise error(f"{path}: not a zarr group with readable metadata, so not a {what} "
                    f"({type(exc).__name__}: {detail})") from exc


def check_attrs(path: Path, attrs: dict, model: type[BaseModel], error: type[ValueError]) -> None:
    """Raise ``error`` naming ``path`` and the attribute unless ``attrs`` fit ``model``."""
    try:
        model.model_validate(dict(attrs))
    except ValidationError as exc:
        first = exc.errors()[0]
        name = ".".join(str(p) for p in first["loc"])
        if first["type"] == "missing":
            raise error(f"{path}: attribute '{name}' is missing") from exc
        raise error(f"{path}: attribute '{name}': {first['msg']} (got {first['input']!r:.80})"
                    ) from exc
