"""Fourier single-pixel LTC reconstruction (docs/optics.md section 5).

Per camera pixel: n-step demodulation of the Fourier frames into the P x P spectrum
``G(k, l) = S F(k, l) = S sum_xy h(x, y) exp(-2 pi j (k x + l y) / P)`` (ADU; conjugate
symmetry fills the other half), inverse 2-D DFT to the LTC folded onto P x P
(``folded[y mod P, x mod P]``), unfolding into a P x P window around the pixel's centre,
normalisation to sum 1. ``gain = G(0, 0)`` is the response to full white above black.

Centre used for unfolding: the coarse centre ``c`` from the localisation patterns, refined
by the first harmonic of the measured spectrum (the LTC's circular mean at period P,
``x' = -P arg G(1, 0) / 2 pi``) snapped to the period nearest ``c``:
``x = x' + P round((c_x - x') / P)``. The window origin centres the window on that point,
so the coarse centre only has to pick the right period (error < P/2) and the window sits
on the LTC itself; pixels whose first harmonic is too weak keep the coarse centre.

Noise: the mean of each regular frequency's n frames is ``a S sum h + A`` for every
frequency, so their scatter gives the frame noise ``sigma_D`` (``n var(means)``); it
propagates to one normalised LTC weight as
``sigma_h = sigma_D / (P^2 b gain) sqrt(s / 2 + 4 (P^2 - s) / n)``, s self-conjugate terms.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache

import numpy as np
import scipy.fft

from sim.storage.durable import aligned_empty
from station.acquisition.patterns import (
    FourierPatternSet,
    StationPatternPlan,
    apply_lut,
    shown_luminance,
)
from station.ltc.localise import lcd_coordinates
from station.ltc.spi_kernels import (
    _apply_level_inverse,
    _block_scalars,
    _demodulate_kernel,
    _half_spectrum,
    _window,
)
from station.ltc.store import (
    TILE_STATS,
)

PIXELS_PER_BLOCK = 128  # pixels reconstructed at once: bounds memory whatever the tile size;
# 128 keeps a block's spectrum planes (1.2 MB) in a core's L2 cache (2 MB here): 8 % less CPU
# per pixel than 256, which is 1.0-1.7x faster than 1024


@dataclass(frozen=True)
class LtcBlock:
    """Reconstruction of n pixels.

    ltc : (n, P, P) float64 (float32 as stored, through a float32 inverse DFT, from
        :func:`reconstruct_tile`), normalised
        windows (NaN where invalid); [r, s] is LCD pixel ``(origin_x + s, origin_y + r)``.
    origin : (n, 2) int32 LCD (x, y) of window element [0, 0] (0 where invalid).
    gain : (n,) response to full white, ADU.  noise : (n,) std of one LTC weight.
    lcd_xy : (n, 2) coarse LCD (x, y) from the localisation patterns.
    valid : (n,) bool.  edge_mass : (n,) LTC mass in the window's outer ring (fit check).
    """

    ltc: np.ndarray
    origin: np.ndarray
    gain: np.ndarray
    noise: np.ndarray
    lcd_xy: np.ndarray
    valid: np.ndarray
    edge_mass: np.ndarray


def demodulate(frames: np.ndarray, plan: StationPatternPlan) -> np.ndarray:
    """Spectrum ``G[l, k]`` (n, P, P) complex128 in ADU from frames (patterns, n)."""
    re, im, _ = _demodulate(frames, plan)
    return _to_spectrum(re, im, plan.fourier.period)


def _to_spectrum(re: np.ndarray, im: np.ndarray, p: int) -> np.ndarray:
    """(n, P, P) complex128 from frequency-major planes re, im (P^2, n)."""
    return (re + 1j * im).T.reshape(-1, p, p)


def _to_planes(spectrum: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frequency-major planes re, im (P^2, n) float64 of a spectrum (n, P, P)."""
    flat = np.asarray(spectrum, dtype=np.complex128).reshape(len(spectrum), -1)
    return np.ascontiguousarray(flat.real.T), np.ascontiguousarray(flat.imag.T)


def _demodulate(frames: np.ndarray, plan: StationPatternPlan, j0: int = 0,
                j1: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Spectrum as frequency-major planes (re, im: (P^2, n) float64, row ``l P + k``) and
    the frame noise ``sigma_D`` (n,) from the scatter of the regular frequencies' frame
    means (:func:`_noise_from_means`), from frames (patterns, N) of any real
    dtype (pixels ``j0:j1``, n of them; default all), in one compiled pass over the frames:
    ``G = 2 / (n b) sum_m D_m exp(2 pi j m / n)`` for regular frequencies (and their
    conjugates at the mirrored ones), ``(D_+ - D_-) / 2 b`` for self-conjugate ones.
    re and im are the two halves of one (2 P^2, n) array (``re.base``)."""
    p = plan.fourier.period
    d = np.asarray(frames)
    if d.dtype.kind not in "uif":
        d = d.astype(np.float64)
    d = np.ascontiguousarray(d)  # a C array: the compiled loops run 2-4x faster on rows
    j1 = d.shape[1] if j1 is None else j1
    t = _plan_tables(plan.fourier)
    reg_idx, sc_idx, e_re, e_im, f_reg, f_sc = _demod_tables(plan)
    planes = np.empty((2 * p * p, j1 - j0))
    sigma = np.empty(j1 - j0)
    _demodulate_kernel(d, j0, reg_idx, sc_idx, e_re, e_im, t.here, t.mirror, t.sc, t.rest,
                       p * p, f_reg, f_sc, planes, sigma)
    return planes[: p * p], planes[p * p :], sigma


@lru_cache(maxsize=16)
def _demod_tables(plan: StationPatternPlan) -> tuple:
    """What :func:`_demodulate_kernel` needs of a plan, once per plan in a process (building
    it costs ~0.15 ms, as much as demodulating 100 pixels): the regular (m, n) and
    self-conjugate (s, 2) pattern indices, the steps' phasors (re, im) and the scales of
    regular and self-conjugate coefficients."""
    f = plan.fourier
    e = np.exp(2j * np.pi * np.arange(f.steps) / f.steps)
    out = (np.ascontiguousarray(plan.indices["regular"], dtype=np.int64),
           np.ascontiguousarray(plan.indices["self_conjugate"], dtype=np.int64),
           e.real.copy(), e.imag.copy())
    for a in out:
        a.flags.writeable = False
    return out + (2.0 / (f.steps * f.amplitude), 1.0 / (2.0 * f.amplitude))


def _noise_from_means(means: np.ndarray, steps: int) -> np.ndarray:
    """``sigma_D`` (n,) from the regular frequencies' frame means (m, n)."""
    return np.sqrt(steps * means.var(axis=0, ddof=1))


@dataclass(frozen=True)
class LevelHarmonics:
    """How the levels actually shown distort the demodulated spectrum.

    With shown levels ``rho_u`` (u on the grid of ``FourierPatternSet.grid``, L points) and
    their DFT ``c_h``, a regular coefficient measures
    ``G'(k, l) = sum_{h = -1 mod n} gamma_h F(-h k, -h l)``, ``gamma_h = 2 c_h / b``
    (``gamma_{L-1}`` is the main term, 1 for ideal levels); a self-conjugate one measures
    ``gamma_sc F(k, l)``, ``gamma_sc = (rho(a + b) - rho(a - b)) / 2 b``.
    h : (H,) int harmonic numbers in [0, L); gamma : (H,) complex; gamma_sc : float.
    """

    h: np.ndarray
    gamma: np.ndarray
    gamma_sc: float


def level_harmonics(fourier: FourierPatternSet, lut: np.ndarray | None = None) -> LevelHarmonics:
    """The harmonics of the levels shown after the LUT and 8-bit rounding, assuming the
    display's response is the exact inverse of ``lut`` (identity: a linear display)."""
    big, n, a, b = fourier.grid, fourier.steps, fourier.offset, fourier.amplitude
    rho = shown_luminance(apply_lut(fourier.level_table(), lut), lut)
    c = np.fft.fft(rho) / big
    h = np.arange(big)[(np.arange(big) + 1) % n == 0]
    ends = shown_luminance(apply_lut(np.array([a + b, a - b]), lut), lut)
    gamma, gamma_sc = 2.0 * c[h] / b, float(ends[0] - ends[1]) / (2 * b)
    main = abs(gamma[h == big - 1][0])
    if gamma_sc < 0.5 or main < 0.5 or np.abs(gamma).sum() - main >= 0.5 * main:
        raise ValueError(
            f"the shown levels do not carry the patterns (main harmonic {main:.3f}, "
            f"self-conjugate gain {gamma_sc:.3f}, both ~1 expected): check the LUT and the "
            "pattern offset/amplitude")
    return LevelHarmonics(h=h, gamma=gamma, gamma_sc=gamma_sc)


@lru_cache(maxsize=16)
def _level_harmonics_cached(fourier: FourierPatternSet, lut: bytes | None) -> LevelHarmonics:
    """:func:`level_harmonics` once per pattern set and LUT (float64 bytes) in a process."""
    return level_harmonics(fourier, None if lut is None else np.frombuffer(lut, np.float64))


def correct_levels(spectrum: np.ndarray, fourier: FourierPatternSet,
                   harmonics: LevelHarmonics) -> np.ndarray:
    """Undo the shown levels' harmonics (see :class:`LevelHarmonics`): solve, per pixel, the
    linear equations ``G'(k, l) = gamma_main G(k, l) + sum_side gamma_h G(-h k, -h l)`` of the
    regular coefficients (self-conjugate ones divided by ``gamma_sc``; ``G(-v) = conj G(v)``)
    exactly. The solution is one fixed real-linear map of the measured coefficients, the same
    for every pixel; it is computed once per pattern set and LUT (:func:`_level_inverse`) and
    is sparse (a coefficient depends only on the frequencies ``c (k, l)`` for the products c of
    the side harmonics' multipliers), so applying it costs a few multiply-adds per
    coefficient. spectrum (n, P, P) complex as from :func:`demodulate`; returns a corrected
    copy."""
    re, im = _to_planes(spectrum)
    _correct_planes(re, im, fourier, harmonics)
    return _to_spectrum(re, im, fourier.period)


def _correct_planes(re: np.ndarray, im: np.ndarray, fourier: FourierPatternSet,
                    harmonics: LevelHarmonics) -> None:
    """:func:`correct_levels` in place on frequency-major planes re, im (P^2, n)."""
    planes = np.concatenate([re, im])
    _correct_stacked(planes, fourier, harmonics)
    p2 = fourier.period ** 2
    re[...], im[...] = planes[:p2], planes[p2:]


def _correct_stacked(planes: np.ndarray, fourier: FourierPatternSet,
                     harmonics: LevelHarmonics) -> None:
    """:func:`_correct_planes` in place on planes (2 P^2, n): re rows, then im rows."""
    t = _plan_tables(fourier)
    op = _level_inverse(fourier, harmonics.h.tobytes(), harmonics.gamma.tobytes(),
                        harmonics.gamma_sc)
    pp = fourier.period ** 2
    planes[t.sc] /= harmonics.gamma_sc
    planes[pp + t.sc] /= harmonics.gamma_sc
    _apply_level_inverse(planes, op.start, op.source, op.weight, t.here, t.mirror)


@dataclass(frozen=True)
class _LevelInverse:
    """The exact level correction as a sparse real matrix (CSR): output row ``r`` (< m: the
    real part of regular frequency r's estimate, else the imaginary part of ``r - m``) is
    ``sum weight[q] x[source[q]]`` over ``q in start[r] : start[r + 1]``, where ``x[s]`` is
    row s of the re plane (s < P^2) or row ``s - P^2`` of the im plane (after the
    self-conjugate rows were divided by ``gamma_sc``)."""

    start: np.ndarray
    source: np.ndarray
    weight: np.ndarray


@lru_cache(maxsize=16)
def _level_inverse(fourier: FourierPatternSet, h_bytes: bytes, gamma_bytes: bytes,
                   gamma_sc: float) -> _LevelInverse:
    """:class:`_LevelInverse` for a pattern set and its level harmonics (as bytes, hashable).
    The map is real-linear, so its column for each plane row (a unit input there, zero
    elsewhere) is the correction of that input: computed for all 2 P^2 unit inputs at once by
    the Jacobi (fixed-point) iteration ``u <- (G' - sum_side gamma_h G(-h k, -h l)) /
    gamma_main`` until it no longer changes in float64 (each step gains a factor
    ``sum |gamma_side| / |gamma_main|`` < 0.5, checked by :func:`level_harmonics`), with
    element-wise numpy only, so every process and machine with this numpy gets the same
    weights bit for bit (a LAPACK inverse may vary with its thread count). Weights below
    1e-17 of a row's largest are dropped (they change no result above float64 rounding)."""
    t = _plan_tables(fourier)
    h = np.frombuffer(h_bytes, dtype=np.int64)
    gamma = np.frombuffer(gamma_bytes, dtype=np.complex128)
    big, pp = fourier.grid, fourier.period ** 2
    side = [(t.side_target[int(hh)], complex(g)) for hh, g in zip(h, gamma, strict=True)
            if hh != big - 1 and abs(g) > 1e-15]
    main = complex(gamma[h == big - 1][0])
    x = np.zeros((pp, 2 * pp), np.complex128)  # plane rows x unit inputs (re plane, im plane)
    x[np.arange(pp), np.arange(pp)] = 1.0
    x[np.arange(pp), pp + np.arange(pp)] = 1j
    measured = x[t.here]
    est = measured / main
    for _ in range(200 if side else 0):
        x[t.here], x[t.mirror] = est, np.conj(est)
        acc = measured.copy()
        for target, g in side:
            acc -= x[target] * g
        new = acc / main
        change = np.abs(new - est).max()
        est = new
        if change <= 1e-18:  # inputs are 1: below float64 rounding of every weight that stays
            break
    full = np.concatenate([est.real, est.imag])  # (2m, 2 P^2)
    full[np.abs(full) < 1e-17 * np.abs(full).max(axis=1, keepdims=True)] = 0.0
    nz = full != 0
    op = _LevelInverse(
        start=np.concatenate([[0], np.cumsum(nz.sum(axis=1))]).astype(np.int64),
        source=np.nonzero(nz)[1].astype(np.int64), weight=full[nz].astype(np.float64))
    for arr in (op.start, op.source, op.weight):
        arr.flags.writeable = False
    return op


@dataclass(frozen=True)
class _PlanTables:
    """Flat frequency rows (``l P + k``) of a Fourier pattern set: regular ones (m,), their
    mirrors (m,), self-conjugate ones (s,), the rows none of these covers (zero in every
    spectrum), and for every harmonic number h in [0, L) the row
    ``(-h l mod P) P + (-h k mod P)`` each regular frequency's harmonic h reads (L, m)."""

    here: np.ndarray
    mirror: np.ndarray
    sc: np.ndarray
    rest: np.ndarray
    side_target: np.ndarray


@lru_cache(maxsize=16)
def _plan_tables(fourier: FourierPatternSet) -> _PlanTables:
    p, big = fourier.period, fourier.grid
    reg, sc = fourier.frequencies
    k, l = reg[:, 0].astype(np.int64), reg[:, 1].astype(np.int64)
    h = np.arange(big, dtype=np.int64)[:, None]
    here, mirror = l * p + k, ((-l) % p) * p + (-k) % p
    sc_rows = (sc[:, 1] * p + sc[:, 0]).astype(np.int64)
    tables = _PlanTables(
        here=here, mirror=mirror, sc=sc_rows,
        rest=np.setdiff1d(np.arange(p * p), np.concatenate([here, mirror, sc_rows])),
        side_target=((-h * l) % p) * p + (-h * k) % p)
    for a in (tables.here, tables.mirror, tables.sc, tables.rest, tables.side_target):
        a.flags.writeable = False
    return tables


def fold(spectrum: np.ndarray) -> np.ndarray:
    """Folded LTC (n, P, P) float64 ``[y mod P, x mod P]`` from the Hermitian spectrum
    (n, P, P) (real inverse DFT of its non-negative-k half)."""
    p = spectrum.shape[-1]
    return np.fft.irfft2(spectrum[..., : p // 2 + 1], s=(p, p), axes=(-2, -1))


def frame_noise(frames: np.ndarray, plan: StationPatternPlan) -> np.ndarray:
    """Per-pixel frame noise std ``sigma_D`` (n,) from the scatter of the regular
    frequencies' frame means (frames (patterns, n))."""
    means = np.asarray(frames, dtype=np.float64)[plan.indices["regular"]].mean(axis=1)
    return _noise_from_means(means, plan.fourier.steps)


def ltc_noise(sigma_frame: np.ndarray, gain: np.ndarray, fourier: FourierPatternSet) -> np.ndarray:
    """Std of one normalised LTC weight (n,) from frame noise and gain (n,), ADU."""
    p, n, b = fourier.period, fourier.steps, fourier.amplitude
    s = len(fourier.frequencies[1])
    factor = np.sqrt(s / 2.0 + 4.0 * (p * p - s) / n) / (p * p * b)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(gain > 0, factor * sigma_frame / gain, np.nan)


def refine_centre(
    spectrum: np.ndarray, coarse_xy: np.ndarray, min_harmonic: float = 0.05
) -> np.ndarray:
    """Centre (n, 2) LCD (x, y): the first-harmonic circular mean of each LTC at period P,
    in the period nearest the coarse centre (n, 2); the coarse centre where
    ``|G(1, 0)| / G(0, 0)`` (or the y twin) is below ``min_harmonic``."""
    return _refine(spectrum[:, 0, 0].real, spectrum[:, 0, 1], spectrum[:, 1, 0],
                   spectrum.shape[-1], coarse_xy, min_harmonic)


def _refine(g0: np.ndarray, g_x: np.ndarray, g_y: np.ndarray, p: int, coarse_xy: np.ndarray,
            min_harmonic: float) -> np.ndarray:
    """:func:`refine_centre` from the DC term g0 (n,) and the first harmonics G(1, 0) along
    x and y (n,) complex."""
    out = np.array(coarse_xy, dtype=np.float64, copy=True)
    for axis, g1 in enumerate((g_x, g_y)):
        xp = np.mod(-np.angle(g1) * p / (2 * np.pi), p)
        c = out[:, axis]
        fine = xp + p * np.round((c - xp) / p)
        with np.errstate(divide="ignore", invalid="ignore"):
            strong = np.abs(g1) >= min_harmonic * g0
        out[:, axis] = np.where(strong & np.isfinite(c), fine, c)
    return out


def unfold(folded: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Windows (n, P, P): element [r, s] = ``folded[(o_y + r) mod P, (o_x + s) mod P]``,
    i.e. LCD pixel ``(o_x + s, o_y + r)``; origin (n, 2) int (x, y)."""
    n, p = folded.shape[0], folded.shape[-1]
    o = np.asarray(origin, dtype=np.int64)
    rows = (o[:, 1, None] + np.arange(p)) % p
    cols = (o[:, 0, None] + np.arange(p)) % p
    return folded[np.arange(n)[:, None, None], rows[:, :, None], cols[:, None, :]]


def reconstruct_frames(
    frames: np.ndarray, plan: StationPatternPlan, *, lut: np.ndarray | None = None,
    level_correction: bool = True, min_snr: float = 10.0, min_harmonic: float = 0.05,
) -> LtcBlock:
    """Reconstruct n pixels from their responses (patterns, n) to every pattern of ``plan``.

    lut : the inverse response LUT the patterns were shown through (None: none).
    level_correction : undo the harmonics of the levels actually shown (8-bit rounding after
        the LUT; :func:`correct_levels`), assuming the LUT inverts the display exactly.
    A pixel is valid when its gain exceeds ``min_snr`` times the gain's noise and its
    localisation decoded. Pure function: the tiled :func:`reconstruct` calls it per block.
    """
    d = np.asarray(frames)
    if d.ndim != 2 or d.shape[0] != len(plan):
        raise ValueError(f"frames must be (patterns={len(plan)}, pixels), got {d.shape}")
    harmonics = level_harmonics(plan.fourier, lut) if level_correction else None
    return _reconstruct_block(d, plan, harmonics, lcd_coordinates(d, plan).xy, min_snr,
                              min_harmonic)


def _reconstruct_block(d: np.ndarray, plan: StationPatternPlan,
                       harmonics: LevelHarmonics | None, lcd_xy: np.ndarray, min_snr: float,
                       min_harmonic: float, ltc: np.ndarray | None = None, j0: int = 0,
                       j1: int | None = None) -> LtcBlock:
    """:func:`reconstruct_frames` of pixels ``j0:j1`` of frames d (patterns, N) given the
    level harmonics (None: no level correction) and the decoded localisation ``lcd_xy``
    (n, 2) of those pixels, both per pixel independent of the block, so a tile computes
    them once; ``ltc`` (n, P, P): where to put the windows, default new float64. The
    inverse DFT runs in the precision of ``ltc``: float32 for the store (half the time of
    float64; within 3e-7 of the window's peak of the float64 windows, some 10^4 times below
    the LTC's measurement noise). Each pixel's result depends on its own frames only (never
    on the block it is computed in)."""
    f = plan.fourier
    p = f.period
    re, im, sigma_d = _demodulate(d, plan, j0, j1)
    planes = re.base
    assert planes is not None  # re is a view of _demodulate's stacked (2 P^2, n) planes
    if harmonics is not None:
        _correct_stacked(planes, f, harmonics)
    n = planes.shape[1]
    gain, noise, centre = np.empty(n), np.empty(n), np.empty((n, 2))
    valid, origin = np.empty(n, bool), np.empty((n, 2), np.int32)
    s = len(f.frequencies[1])
    noise_factor = np.sqrt(s / 2.0 + 4.0 * (p * p - s) / f.steps) / (p * p * f.amplitude)
    _block_scalars(planes, sigma_d, np.ascontiguousarray(lcd_xy, dtype=np.float64), p,
                   f.amplitude, noise_factor, min_snr, min_harmonic, gain, noise,
                   centre, valid, origin)
    if ltc is None:
        ltc = np.empty((n, p, p))
    half = np.empty((p, p // 2 + 1, n),  # frequency-major, no transpose
                    dtype=np.complex64 if ltc.dtype == np.float32 else np.complex128)
    _half_spectrum(planes, p, half)
    folded = scipy.fft.irfft2(half, s=(p, p), axes=(0, 1), overwrite_x=True)  # (P, P, n)
    ring = _window(folded, origin, gain, valid, ltc)
    return LtcBlock(ltc=ltc, origin=origin, gain=gain, noise=noise, lcd_xy=lcd_xy,
                    valid=valid, edge_mass=ring)


def reconstruct_tile(
    frames: np.ndarray, plan: StationPatternPlan, lut: np.ndarray | None, min_snr: float,
    code_mask: np.ndarray,
) -> tuple[LtcBlock, np.ndarray]:
    """One camera tile: frames (patterns, th, tw) -> its :class:`LtcBlock` (th * tw pixels,
    row-major, ``ltc`` float32 as stored; pixels in ``code_mask`` (th, tw) excluded) and its
    statistics
    (``station.ltc.store.TILE_STATS``). Pure: every engine computes tiles with it."""
    _, th, tw = frames.shape
    flat = np.ascontiguousarray(frames).reshape(len(plan), th * tw)
    harmonics = _level_harmonics_cached(plan.fourier, None if lut is None else
                                        np.asarray(lut, np.float64).tobytes())
    lcd_xy = lcd_coordinates(flat, plan).xy
    p = plan.fourier.period
    # page-aligned, so the store's writer can send it straight to the disk (O_DIRECT)
    out: dict[str, np.ndarray] = {"ltc": aligned_empty((th * tw, p, p), np.float32)}
    for i in range(0, th * tw, PIXELS_PER_BLOCK):
        i1 = min(i + PIXELS_PER_BLOCK, th * tw)
        part = _reconstruct_block(flat, plan, harmonics, lcd_xy[i:i1], min_snr, 0.05,
                                  out["ltc"][i:i1], i, i1)
        for fld in fields(LtcBlock):
            if fld.name == "ltc":  # written in place
                continue
            v = getattr(part, fld.name)
            if fld.name not in out:
                out[fld.name] = np.empty((th * tw,) + v.shape[1:], dtype=v.dtype)
            out[fld.name][i : i + len(v)] = v
    blk = LtcBlock(**out)
    blk = _exclude(blk, np.asarray(code_mask, dtype=bool).ravel())
    v = blk.valid
    stats = np.full(len(TILE_STATS), np.nan)
    stats[0] = int(v.sum())
    if v.any():
        stats[1] = float(np.median(blk.gain[v]))
        stats[2] = float(np.median(blk.noise[v]))
        stats[3] = float(np.percentile(np.abs(blk.edge_mass[v]), 95))
    return blk, stats


def _exclude(blk: LtcBlock, mask: np.ndarray) -> LtcBlock:
    """The block with the pixels in ``mask`` (n,) bool made invalid (LTC NaN, origin 0), in
    place: the block's arrays are its caller's own (:func:`reconstruct_tile`)."""
    if mask.any():
        blk.ltc[mask] = np.nan
        blk.origin[mask] = 0
        blk.valid[mask] = False
    return blk
