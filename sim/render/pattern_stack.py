"""Projector pattern images, each kept in its cheapest exact form.

Fringe and Gray-code patterns vary along one projector axis only. A pattern whose rows are all
equal is kept as one row (``rows``: it varies along u), one whose columns are all equal as one
column (``cols``: it varies along v), any other as the full image (``full``). The forms are exact:
``PatternStack.images()`` gives back the images bit for bit. Sampling a row or a column costs
the renderer two taps from a few kilobytes instead of four from a megapixel image.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numba as nb
import numpy as np

from sim.errors import SimInputError

FULL, ALONG_U, ALONG_V = 0, 1, 2  # values of PatternStack.form


@nb.njit(nogil=True, cache=True)
def _all_equal(img: np.ndarray, along_rows: bool) -> bool:
    """Whether every row of ``img`` (H, W) equals row 0 (``along_rows``), or every column
    equals column 0; stops at the first row that differs."""
    h, w = img.shape
    first = img[0]
    for r in range(h):
        row = img[r]
        differs = False
        if along_rows:
            for c in range(w):
                differs |= row[c] != first[c]
        else:
            for c in range(w):
                differs |= row[c] != row[0]
        if differs:
            return False
    return True


@nb.njit(nogil=True, cache=True)
def _forms(images: np.ndarray) -> np.ndarray:
    """(n,) int8 form of each pattern image of (n, H, W): ALONG_U, ALONG_V or FULL."""
    out = np.empty(len(images), np.int8)
    for p in range(len(images)):
        out[p] = (ALONG_U if _all_equal(images[p], True) else
                  ALONG_V if _all_equal(images[p], False) else FULL)
    return out


@dataclass(frozen=True)
class PatternStack:
    """``n`` projector patterns of ``size = (Wp, Hp)`` pixels: pattern ``p`` is
    ``rows[slot[p]]`` repeated down every row (``form[p] == ALONG_U``), ``cols[slot[p]]``
    repeated across every column (``ALONG_V``) or ``full[slot[p]]`` (``FULL``); float32."""

    size: tuple[int, int]
    form: np.ndarray  # (n,) int8
    slot: np.ndarray  # (n,) int64
    full: np.ndarray  # (n_full, Hp, Wp) float32
    rows: np.ndarray  # (n_u, Wp) float32
    cols: np.ndarray  # (n_v, Hp) float32

    def __len__(self) -> int:
        return len(self.form)

    @classmethod
    def from_images(cls, images: np.ndarray) -> PatternStack:
        """The stack of pattern images (n, Hp, Wp), each in its cheapest exact form."""
        p = np.ascontiguousarray(images, dtype=np.float32)
        if p.ndim != 3:
            raise SimInputError(f"pattern images must be (n, H, W), got shape {p.shape}")
        n, h, w = p.shape
        form = _forms(p) if p.size else np.full(n, FULL, np.int8)
        slot = np.zeros(n, np.int64)
        for f in (FULL, ALONG_U, ALONG_V):
            slot[form == f] = np.arange(np.count_nonzero(form == f))
        full = p if np.all(form == FULL) else p[form == FULL]
        return cls((w, h), form, slot, full, p[form == ALONG_U, 0, :],
                   np.ascontiguousarray(p[form == ALONG_V, :, 0]))

    def images(self) -> np.ndarray:
        """The patterns as full images (n, Hp, Wp) float32."""
        w, h = self.size
        out = np.empty((len(self), h, w), np.float32)
        for p, (f, s) in enumerate(zip(self.form, self.slot)):
            out[p] = (self.full[s] if f == FULL else self.rows[s][None, :] if f == ALONG_U
                      else self.cols[s][:, None])
        return out

    def map(self, fn: Callable[[np.ndarray], np.ndarray]) -> PatternStack:
        """The stack with ``fn`` applied to every pattern as a 2-D image: to each full image
        (Hp, Wp), each row as (1, Wp) and each column as (Hp, 1). ``fn`` must keep the shape
        and treat an image the same whatever its extent along an axis it does not vary on
        (pointwise maths; filters with replicated borders)."""
        def each(stack: np.ndarray, as_2d, back) -> np.ndarray:
            out = np.empty_like(stack)
            for i, s in enumerate(stack):
                out[i] = back(np.asarray(fn(as_2d(s)), dtype=np.float32))
            return out

        w, h = self.size
        return PatternStack(
            self.size, self.form, self.slot,
            each(self.full, lambda s: s, lambda r: r.reshape(h, w)),
            each(self.rows, lambda s: s[None, :], lambda r: r.reshape(w)),
            each(self.cols, lambda s: s[:, None], lambda r: r.reshape(h)))

    def value_range(self) -> tuple[float, float]:
        """Smallest and largest pattern value (NaN if any value is NaN)."""
        parts = [a.ravel() for a in (self.full, self.rows, self.cols) if a.size]
        if not parts:
            return 0.0, 0.0
        v = np.concatenate([[np.min(a), np.max(a)] for a in parts])
        return (float("nan"),) * 2 if np.isnan(v).any() else (float(v.min()), float(v.max()))
