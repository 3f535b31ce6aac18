"""Pattern sets of the LTC station (docs/optics.md section 5): Fourier single-pixel patterns and
localisation patterns, combined in one ordered plan that round-trips through JSON.

Values are relative luminances in [0, 1] computed in float, mapped through the display's
inverse response LUT (see :func:`apply_lut`) and rounded (not truncated) to 8 bits.
When :meth:`StationPatternPlan.image` applies the LUT, the display's own LUT must be the
identity (``PatternDisplay.set_lut(None)``), or the correction is applied twice.

Plan order: the localisation set first (white, black, Gray code bits along x then y, phase
steps along x then y), then the Fourier set, frequency by frequency in the order of
:func:`half_plane_frequencies`, all steps of a frequency together.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Final, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from sim.render.fringe_patterns import Modulation, PatternDescriptor
from station.errors import StationInputError

PLAN_FORMAT: Final = "station-pattern-plan"
PLAN_VERSION: Final = 1


def half_plane_frequencies(period: int) -> tuple[np.ndarray, np.ndarray]:
    """The conjugate-symmetric half of the P x P frequency grid.

    Returns ``(regular, self_conjugate)``: (m, 2) and (s, 2) int arrays of (k, l) in
    [0, P), k multiplying the LCD column x and l the row y. Of each pair
    ``(k, l), (-k mod P, -l mod P)`` the one first in row-major (l, k) order is kept;
    self-conjugate terms (DC and, for even P, the Nyquist terms) are listed apart.
    ``m = (P^2 - s) / 2``; s is 4 for even P and 1 for odd P.
    """
    ll, kk = np.meshgrid(np.arange(period), np.arange(period), indexing="ij")
    k, l = kk.ravel(), ll.ravel()
    flat = l * period + k
    partner = ((-l) % period) * period + (-k) % period
    kl = np.stack([k, l], axis=1)
    return kl[flat < partner], kl[flat == partner]


class FourierPatternSet(Modulation):
    """Periodic Fourier patterns ``L = A + B cos(2 pi (k x + l y) / P + phi_m)`` (relative
    luminance; ``offset`` A and ``amplitude`` B as the projector's fringes, ``Modulation``)."""

    kind: Literal["fourier"] = "fourier"
    period: int = Field(24, ge=4, le=256, description="period P of the patterns, LCD pixels")
    steps: int = Field(4, ge=3, le=16, description="phase steps n, phi_m = 2 pi m / n")

    @property
    def frequencies(self) -> tuple[np.ndarray, np.ndarray]:
        """``half_plane_frequencies(period)``: (regular (m, 2), self-conjugate (s, 2)), read-only."""
        return _frequencies(self.period)

    @property
    def grid(self) -> int:
        """L = lcm(P, n): every regular pattern value is ``level_table()[u]`` for an integer
        phase index u, ``u = ((k x + l y) L / P + m L / n) mod L``."""
        return int(np.lcm(self.period, self.steps))

    def level_table(self) -> np.ndarray:
        """(L,) float64 relative luminances ``a + b cos(2 pi u / L)``."""
        u = np.arange(self.grid)
        return np.clip(self.offset + self.amplitude * np.cos(2 * np.pi * u / self.grid), 0, 1)

    def tile(self, k: int, l: int, step: int) -> np.ndarray:
        """One period (P, P) float64 of the pattern for frequency (k, l) and phase step
        ``step``, ``[y mod P, x mod P]``. Regular frequencies read :meth:`level_table` (so a
        model of the shown levels sees exactly the same floats); self-conjugate ones, whose
        phases are 0 and pi, take the values ``a + b`` and ``a - b`` only."""
        p, big = self.period, self.grid
        xy = k * np.arange(p)[None, :] + l * np.arange(p)[:, None]
        if (2 * k) % p == 0 and (2 * l) % p == 0:
            sign = 1 - 2 * (((2 * xy) // p + step) % 2)
            return np.clip(self.offset + self.amplitude * sign, 0.0, 1.0)
        u = (xy * (big // p) + step * (big // self.steps)) % big
        return self.level_table()[u]

    @property
    def count(self) -> int:
        """Number of patterns: n per regular frequency, 2 (phases 0, pi) per self-conjugate one."""
        reg, sc = self.frequencies
        return self.steps * len(reg) + 2 * len(sc)


class LocalisationPatternSet(BaseModel):
    """Gray code plus phase shifting along both LCD axes, with a white and a black frame.

    Gray code bit patterns (0 or 1) split each axis into half-period stripes of ``period / 2``
    pixels; stripe ``m = floor(x / (period / 2))`` is coded as ``gray(m)``, most significant
    bit first. Phase patterns: ``0.5 + 0.5 cos(2 pi x / period - 2 pi i / steps)``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: Literal["localisation"] = "localisation"
    period: int = Field(48, ge=4, le=4096, description="phase-shift period Q, LCD pixels (even)")
    steps: int = Field(4, ge=3, le=16, description="phase steps per axis")
    bits_x: int = Field(8, ge=1, le=16, description="Gray code bits along LCD columns")
    bits_y: int = Field(7, ge=1, le=16, description="Gray code bits along LCD rows")

    @model_validator(mode="after")
    def _even(self) -> LocalisationPatternSet:
        if self.period % 2:
            raise ValueError(f"localisation period must be even, got {self.period}")
        return self

    @property
    def count(self) -> int:
        return 2 + self.bits_x + self.bits_y + 2 * self.steps

    def covers(self, lcd_size: tuple[int, int]) -> bool:
        """True when the Gray code numbers every stripe of an LCD of (width, height)."""
        half = self.period // 2
        return all(n <= (2**b) * half for n, b in zip(lcd_size, (self.bits_x, self.bits_y), strict=True))


class StationPatternPlan(BaseModel):
    """The ordered patterns of one depth of an acquisition run."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    format: Literal["station-pattern-plan"] = PLAN_FORMAT
    version: Literal[1] = PLAN_VERSION
    fourier: FourierPatternSet = Field(default_factory=FourierPatternSet)
    localisation: LocalisationPatternSet = Field(default_factory=LocalisationPatternSet)

    @classmethod
    def for_lcd(
        cls,
        lcd_size: tuple[int, int],
        period: int = 24,
        steps: int = 4,
        *,
        offset: float = 0.5,
        amplitude: float = 0.5,
        localisation_period: int | None = None,
        localisation_steps: int = 4,
    ) -> StationPatternPlan:
        """A plan for an LCD of (width, height); the localisation period defaults to 2 P
        and the Gray code gets just enough bits to number every half-period stripe."""
        q = 2 * period if localisation_period is None else localisation_period
        half = max(q // 2, 1)
        bits = [max(1, int(np.ceil(np.log2(max(-(-n // half), 1))))) for n in lcd_size]
        return cls(
            fourier=FourierPatternSet(period=period, steps=steps, offset=offset,
                                      amplitude=amplitude),
            localisation=LocalisationPatternSet(period=q, steps=localisation_steps,
                                                bits_x=bits[0], bits_y=bits[1]),
        )

    def __len__(self) -> int:
        return self.localisation.count + self.fourier.count

    @property
    def descriptors(self) -> tuple[PatternDescriptor, ...]:
        """Pattern ``i`` of the plan is ``descriptors[i]``."""
        return _descriptors(self)

    @property
    def indices(self) -> dict[str, np.ndarray]:
        """Plan indices by role, for decoders (fresh arrays on every call):

        ``white``, ``black``: (1,); ``gray_x`` (bits_x,), ``gray_y`` (bits_y,);
        ``phase_x``, ``phase_y``: (steps,); ``regular``: (m, n) patterns of each regular
        frequency in step order; ``self_conjugate``: (s, 2) phases 0 and pi.
        """
        loc, f = self.localisation, self.fourier
        start = 2
        out = {"white": np.array([0]), "black": np.array([1])}
        for name, n in (("gray_x", loc.bits_x), ("gray_y", loc.bits_y),
                        ("phase_x", loc.steps), ("phase_y", loc.steps)):
            out[name] = np.arange(start, start + n)
            start += n
        reg, sc = f.frequencies
        out["regular"] = start + np.arange(len(reg) * f.steps).reshape(len(reg), f.steps)
        start += len(reg) * f.steps
        out["self_conjugate"] = start + np.arange(2 * len(sc)).reshape(len(sc), 2)
        return out

    def values(self, index: int, lcd_size: tuple[int, int]) -> np.ndarray:
        """Pattern ``index`` as relative luminance, as a periodic tile.

        Returns a (th, tw) float64 tile in [0, 1] with ``image[r, c] = tile[r % th, c % tw]``:
        (P, P) for Fourier patterns, (1, width) or (height, 1) for localisation stripes,
        (1, 1) for white and black.
        """
        if not 0 <= index < len(self):
            raise IndexError(f"pattern index {index} out of range 0..{len(self) - 1}")
        w, h = _check_size(lcd_size)
        loc = self.localisation
        if not loc.covers((w, h)):
            raise StationInputError(
                f"lcd_size {(w, h)} is larger than the localisation Gray code covers "
                f"(bits_x={loc.bits_x}, bits_y={loc.bits_y}, period={loc.period}); "
                "build the plan with StationPatternPlan.for_lcd"
            )
        d = self.descriptors[index]
        if d.kind in ("white", "black"):
            return np.full((1, 1), 1.0 if d.kind == "white" else 0.0)
        if d.kind == "fourier":
            if d.k is None or d.l is None or d.shift is None:
                raise StationInputError(f"pattern {index}: a fourier pattern needs k, l and shift")
            return self.fourier.tile(d.k, d.l, d.shift)
        along_u = d.direction == "u"
        coord = np.arange(w if along_u else h)
        if d.kind == "gray":
            if d.bit is None:
                raise StationInputError(f"pattern {index}: a gray pattern needs its bit")
            bits = loc.bits_x if along_u else loc.bits_y
            m = coord // (loc.period // 2)
            line = (((m ^ (m >> 1)) >> (bits - 1 - d.bit)) & 1).astype(np.float64)
        else:
            if d.phase_rad is None:
                raise StationInputError(f"pattern {index}: a phase pattern needs phase_rad")
            line = 0.5 + 0.5 * np.cos(2 * np.pi * coord / loc.period - d.phase_rad)
        return line[None, :] if along_u else line[:, None]

    def image(
        self, index: int, lcd_size: tuple[int, int], lut: np.ndarray | None = None
    ) -> np.ndarray:
        """Pattern ``index`` for an LCD of (width, height): (height, width) uint8, the float
        values passed through ``lut`` (see :func:`apply_lut`) and rounded to 8 bits."""
        tile = apply_lut(self.values(index, lcd_size), lut)
        w, h = int(lcd_size[0]), int(lcd_size[1])
        th, tw = tile.shape
        reps = (-(-h // th), -(-w // tw))
        return np.ascontiguousarray(np.tile(tile, reps)[:h, :w])


@lru_cache(maxsize=16)
def _frequencies(period: int) -> tuple[np.ndarray, np.ndarray]:
    reg, sc = half_plane_frequencies(period)
    reg.flags.writeable = False
    sc.flags.writeable = False
    return reg, sc


@lru_cache(maxsize=8)
def _descriptors(plan: StationPatternPlan) -> tuple[PatternDescriptor, ...]:
    out: list[dict] = [{"kind": "white"}, {"kind": "black"}]
    loc, f = plan.localisation, plan.fourier
    for axis, bits in (("u", loc.bits_x), ("v", loc.bits_y)):
        out += [{"kind": "gray", "direction": axis, "bit": b,
                 "stripe_width_px": loc.period / 2} for b in range(bits)]
    for axis in ("u", "v"):
        out += [{"kind": "phase", "direction": axis, "period_px": loc.period, "shift": i,
                 "steps": loc.steps, "phase_rad": 2 * np.pi * i / loc.steps}
                for i in range(loc.steps)]
    reg, sc = f.frequencies
    for (k, l), n in [(kl, f.steps) for kl in reg] + [(kl, 2) for kl in sc]:
        out += [{"kind": "fourier", "k": int(k), "l": int(l), "period_px": f.period, "shift": m,
                 "steps": n, "phase_rad": 2 * np.pi * m / n} for m in range(n)]
    return tuple(PatternDescriptor(index=i, **d) for i, d in enumerate(out))


def apply_lut(values: np.ndarray, lut: np.ndarray | None = None) -> np.ndarray:
    """Relative luminances (any shape, [0, 1]) -> 8-bit drive levels, rounded to nearest.

    lut : None (identity: ``255 v``) or (N,) with N >= 2, non-decreasing values in [0, 255]
        (float allowed): entry i is the drive level that makes the display emit relative
        luminance ``i / (N - 1)``. A 256-entry LUT is the display's usual inverse response
        table; a finer float LUT avoids rounding the table itself. Values between entries are
        linearly interpolated; the result is rounded once, at the end.
    """
    v = np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0)
    if lut is None:
        drive = 255.0 * v
    else:
        table = np.asarray(lut, dtype=np.float64)
        if table.ndim != 1 or len(table) < 2:
            raise StationInputError("lut must be a 1-D table of >= 2 entries, got shape "
                                    f"{table.shape}")
        if not np.all(np.isfinite(table)) or table.min() < 0 or table.max() > 255:
            raise StationInputError("lut entries must be finite drive levels in [0, 255]")
        if np.any(np.diff(table) < 0):
            raise StationInputError("lut must be non-decreasing (an inverse display response)")
        n = len(table)
        drive = np.interp(v * (n - 1), np.arange(n), table)
    return np.clip(np.rint(drive), 0, 255).astype(np.uint8)


def shown_luminance(drive: np.ndarray, lut: np.ndarray | None = None) -> np.ndarray:
    """Relative luminance a display emits for 8-bit drive levels, assuming its response is
    the exact inverse of ``lut`` (identity: ``drive / 255``); float64, same shape.
    Used to model the levels actually shown after the LUT and rounding."""
    g = np.asarray(drive, dtype=np.float64)
    if lut is None:
        return g / 255.0
    table = np.asarray(lut, dtype=np.float64)
    apply_lut(np.zeros(1), table)  # validates the table
    return np.interp(g, table, np.linspace(0.0, 1.0, len(table)))


def _check_size(lcd_size: tuple[int, int]) -> tuple[int, int]:
    if len(lcd_size) != 2 or min(int(lcd_size[0]), int(lcd_size[1])) < 1:
        raise StationInputError(f"lcd_size must be positive (width, height), got {lcd_size}")
    return int(lcd_size[0]), int(lcd_size[1])
