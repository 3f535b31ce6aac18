"""Projector pattern sets shared by the renderer and the reconstruction.

Conventions (docs/optics.md section 7, ``sim.fpp.phase``): shift ``i`` of ``N`` is
``I_i = A + B cos(phi - 2 pi i / N)`` with ``phi = 2 pi u_p / period``, ``u_p`` the projector
column (``v_p`` the row for direction ``v``), pixel centres at integer coordinates.
Gray-code stripe ``k`` covers projector coordinates ``[-0.5 + k w, -0.5 + (k + 1) w)`` (``w`` the
stripe width); bit planes are most significant first and a bit plane is white where the bit of
the stripe's Gray code ``k ^ (k >> 1)`` is 1. The image order is the order of ``descriptors()``.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, model_validator

from sim.errors import SimInputError
from sim.tolerances import PATTERN_RANGE_TOL

Direction = Literal["u", "v", "both"]


class PatternDescriptor(BaseModel):
    """What one pattern image shows: the one vocabulary of the renderer's pattern sets and the
    station's pattern plan (``station.acquisition.patterns``). Axes follow OpenCV: ``u`` along
    columns (projector or LCD x), ``v`` along rows.

    Phase patterns are ``A + B cos(2 pi c / period_px - phase_rad)`` with ``c`` the coordinate
    along ``direction`` and ``phase_rad = 2 pi shift / steps``; Fourier patterns (station) are
    ``a + b cos(2 pi (k x + l y) / period_px + phase_rad)``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    index: int = Field(ge=0, description="position in the set")
    kind: Literal["phase", "gray", "gray_inverse", "white", "black", "fourier"]
    direction: Literal["u", "v"] | None = Field(None, description="axis the pattern varies along")
    period_px: float | None = Field(None, description="period, projector/LCD pixels (phase, fourier)")
    shift: int | None = Field(None, description="shift index i of N (phase, fourier)")
    steps: int | None = Field(None, description="N, shifts per period (phase, fourier)")
    bit: int | None = Field(None, description="Gray-code bit plane, 0 = most significant")
    stripe_width_px: float | None = Field(None, description="Gray-code stripe width, pixels")
    k: int | None = Field(None, description="fourier: cycles per period along u")
    l: int | None = Field(None, description="fourier: cycles per period along v")
    phase_rad: float | None = Field(None, description="phase of this shift, rad (phase, fourier)")


def _axes(direction: Direction) -> list[str]:
    return ["u", "v"] if direction == "both" else [direction]


def _coordinate(axis: str, size: tuple[int, int]) -> np.ndarray:
    """Projector coordinate along ``axis`` as an (H, W) float64 grid (pixel centres at integers)."""
    w, h = size
    if axis == "u":
        return np.broadcast_to(np.arange(w, dtype=np.float64)[None, :], (h, w))
    return np.broadcast_to(np.arange(h, dtype=np.float64)[:, None], (h, w))


def _check_size(size: tuple[int, int]) -> tuple[int, int]:
    w, h = (int(x) for x in size)
    if w < 1 or h < 1:
        raise SimInputError(f"projector_size must be (width, height) >= 1 pixel, got {size}")
    return w, h


class Modulation(BaseModel):
    """Offset and amplitude of a sinusoidal pattern family, ``A + B cos(...)``, values in
    [0, 1]: the projector's fringe sets here and the station's Fourier patterns."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    offset: float = Field(0.5, description="A, mean pattern value in [0, 1]")
    amplitude: float = Field(0.5, gt=0, description="B, fringe amplitude; A - B >= 0, A + B <= 1")

    @model_validator(mode="after")
    def _in_range(self):
        tol = PATTERN_RANGE_TOL
        if self.offset - self.amplitude < -tol or self.offset + self.amplitude > 1 + tol:
            raise SimInputError(
                f"offset A={self.offset} and amplitude B={self.amplitude} must keep A +- B in [0, 1]"
            )
        return self


class _Fringes(Modulation):
    """A fringe set. Where it is read from a file (a scene's ``[patterns]``, a ``--patterns``
    JSON), ``fringes`` may replace the periods: counts across the projector, turned into
    periods in projector pixels with the projector's (width, height) given as the validation
    context ``{"projector_size": ...}`` (:func:`pattern_set_from`)."""

    steps: int = Field(4, ge=3, description="N, phase shifts per period")
    direction: Direction = Field("u", description="fringes vary along u (columns), v (rows) or both")

    @model_validator(mode="before")
    @classmethod
    def _fringe_counts(cls, data, info: ValidationInfo):
        if not isinstance(data, dict) or "fringes" not in data:
            return data
        return _periods_from_fringes(data, (info.context or {}).get("projector_size"))

    def _phase_images(self, axis: str, period: float, size) -> np.ndarray:
        phi = (2 * np.pi / period) * _coordinate(axis, size)
        d = 2 * np.pi * np.arange(self.steps) / self.steps
        return self.offset + self.amplitude * np.cos(phi[None] - d[:, None, None])


class PhaseShiftSet(_Fringes):
    """N-step phase shifting at one or more periods (for multi-frequency unwrapping).

    Order: for each direction, for each period in the given order, shifts 0..N-1."""

    kind: Literal["phase_shift"] = "phase_shift"
    periods_px: list[float] = Field(min_length=1, description="fringe periods, projector pixels")

    @model_validator(mode="after")
    def _periods(self):
        if any(p <= 0 for p in self.periods_px):
            raise SimInputError(f"periods_px must all be > 0, got {self.periods_px}")
        return self

    def descriptors(self, projector_size: tuple[int, int]) -> list[PatternDescriptor]:
        """What each image of ``images(projector_size)`` shows, in order."""
        _check_size(projector_size)
        out: list[PatternDescriptor] = []
        for axis in _axes(self.direction):
            for p in self.periods_px:
                for i in range(self.steps):
                    out.append(PatternDescriptor(index=len(out), kind="phase", direction=axis,
                                                 period_px=p, shift=i, steps=self.steps,
                                                 phase_rad=2 * math.pi * i / self.steps))
        return out

    def images(self, projector_size: tuple[int, int]) -> np.ndarray:
        """All patterns, (n, H, W) float32 in [0, 1]; ``projector_size = (width, height)``."""
        size = _check_size(projector_size)
        stacks = [self._phase_images(a, p, size) for a in _axes(self.direction) for p in self.periods_px]
        return np.clip(np.concatenate(stacks), 0.0, 1.0).astype(np.float32)


class GrayCodeSet(_Fringes):
    """Gray-code stripes plus N-step phase shifting at one period.

    Order per direction: white and black references (if ``references``), the Gray bit planes
    (each followed by its inverse if ``inverse``), then the N phase shifts."""

    kind: Literal["gray_code"] = "gray_code"
    period_px: float = Field(gt=0, description="phase-shift fringe period, projector pixels")
    stripe_width_px: float | None = Field(
        None, gt=0, description="Gray-code stripe width w, projector pixels (default period / 2)"
    )
    inverse: bool = Field(True, description="follow each bit plane by its inverse")
    references: bool = Field(True, description="start each direction with a white and a black image")

    @property
    def stripe_width(self) -> float:
        return self.period_px / 2 if self.stripe_width_px is None else self.stripe_width_px

    def n_bits(self, extent_px: int) -> int:
        """Bit planes needed to number the stripes across ``extent_px`` projector pixels."""
        n_stripes = math.ceil(extent_px / self.stripe_width)
        return max(1, math.ceil(math.log2(n_stripes)))

    def stripe_index(self, coordinate_px: np.ndarray) -> np.ndarray:
        """Stripe number ``floor((c + 0.5) / w)`` of projector coordinates (any shape)."""
        return np.floor((np.asarray(coordinate_px) + 0.5) / self.stripe_width).astype(np.int64)

    def _axis_items(self, axis: str, size) -> list[tuple[dict, np.ndarray]]:
        extent = size[0] if axis == "u" else size[1]
        items: list[tuple[dict, np.ndarray]] = []
        if self.references:
            items.append(({"kind": "white"}, np.ones(size[::-1])))
            items.append(({"kind": "black"}, np.zeros(size[::-1])))
        k = self.stripe_index(_coordinate(axis, size))
        gray = k ^ (k >> 1)
        nb = self.n_bits(extent)
        for b in range(nb):
            plane = ((gray >> (nb - 1 - b)) & 1).astype(np.float64)
            items.append(({"kind": "gray", "bit": b, "stripe_width_px": self.stripe_width}, plane))
            if self.inverse:
                items.append(({"kind": "gray_inverse", "bit": b, "stripe_width_px": self.stripe_width},
                              1.0 - plane))
        phase = self._phase_images(axis, self.period_px, size)
        for i in range(self.steps):
            info = {"kind": "phase", "period_px": self.period_px, "shift": i, "steps": self.steps,
                    "phase_rad": 2 * math.pi * i / self.steps}
            items.append((info, phase[i]))
        return [({**d, "direction": axis}, img) for d, img in items]

    def descriptors(self, projector_size: tuple[int, int]) -> list[PatternDescriptor]:
        """What each image of ``images(projector_size)`` shows, in order."""
        size = _check_size(projector_size)
        items = [d for a in _axes(self.direction) for d, _ in self._axis_items(a, size)]
        return [PatternDescriptor(index=i, **d) for i, d in enumerate(items)]

    def images(self, projector_size: tuple[int, int]) -> np.ndarray:
        """All patterns, (n, H, W) float32 in [0, 1]; ``projector_size = (width, height)``."""
        size = _check_size(projector_size)
        imgs = [img for a in _axes(self.direction) for _, img in self._axis_items(a, size)]
        return np.clip(np.stack(imgs), 0.0, 1.0).astype(np.float32)


PatternSet = Annotated[PhaseShiftSet | GrayCodeSet, Field(discriminator="kind")]


def _periods_from_fringes(raw: dict, projector_size: tuple[int, int] | None) -> dict:
    """``raw`` with ``fringes`` (counts across the projector) turned into ``periods_px`` (a
    phase-shift set) or ``period_px`` (a Gray-code set), projector pixels."""
    raw = dict(raw)
    fringes = raw.pop("fringes")
    keys = {"phase_shift": "periods_px", "gray_code": "period_px"}
    kind = raw.get("kind")
    if kind not in keys:
        raise ValueError(f"'fringes' needs kind 'phase_shift' or 'gray_code', got {kind!r}")
    key = keys[kind]
    if key in raw:
        raise ValueError(f"give 'fringes' or '{key}', not both")
    if projector_size is None:
        raise ValueError("'fringes' needs the projector's size (the rig)")
    direction = raw.get("direction", "u")
    if direction not in ("u", "v"):
        raise ValueError(f"'fringes' with direction {direction!r}: the projector's width and "
                         f"height differ, give '{key}' (projector pixels) instead")
    extent = projector_size[0] if direction == "u" else projector_size[1]
    if kind == "gray_code" and isinstance(fringes, list):
        raise ValueError(f"a gray_code set's 'fringes' is one count, got {fringes!r}")
    counts = fringes if isinstance(fringes, list) else [fringes]
    try:
        values = [float(c) for c in counts]
    except (TypeError, ValueError):
        raise ValueError(f"'fringes' must be numbers (fringes across the projector), got "
                         f"{fringes!r}") from None
    if not values or any(not c > 0 for c in values):
        raise ValueError(f"'fringes' must be counts > 0, got {fringes!r}")
    periods = [extent / c for c in values]
    raw[key] = periods if kind == "phase_shift" else periods[0]
    return raw


def pattern_set_from(raw: object, projector_size: tuple[int, int] | None = None
                     ) -> PhaseShiftSet | GrayCodeSet:
    """Validate a pattern-set mapping (as a scene's ``[patterns]`` or a ``--patterns`` file
    holds it): the one model of both, ``fringes`` included. Raises pydantic's
    ``ValidationError``."""
    from pydantic import TypeAdapter

    return TypeAdapter(PatternSet).validate_python(raw, context={"projector_size": projector_size})

