"""Fringe analysis: N-step wrapped phase, quality mask, temporal unwrapping, projector coordinates.

Convention (docs/optics.md section 7): shift i of N is ``I_i = A + B cos(phi - 2 pi i / N)`` and the
phase of a fringe of period ``p`` projector pixels is ``phi = 2 pi u_p / p``, projector pixel
centres at integer ``u_p``. Wrapped phases are returned in ``[0, 2 pi)``; absolute phases are
``2 pi u_p / p`` without wrapping, so ``u_p = Phi p / (2 pi)``.

Unwrapping is done in projector pixels: every method builds a coarse estimate ``u_c`` of the
projector coordinate and snaps the finer wrapped phase to the fringe order nearest to it,
``Phi = phi + 2 pi round((2 pi u_c / p - phi) / (2 pi))``, which is right wherever
``|u_c - u_p| < p / 2``. Invalid pixels carry NaN through every function.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sim.errors import SimInputError

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class WrappedPhase:
    """Result of N-step phase shifting, all (H, W) float64.

    phase : wrapped phase, rad, in [0, 2 pi).
    modulation : fringe amplitude ``B`` in image units.
    offset : mean intensity ``A`` in image units.
    """

    phase: np.ndarray
    modulation: np.ndarray
    offset: np.ndarray


def wrapped_phase(images: np.ndarray) -> WrappedPhase:
    """Wrapped phase, modulation and offset of N phase-shifted images (N >= 3).

    images : (N, H, W) array, shift i is ``A + B cos(phi - 2 pi i / N)``.
    ``phi = atan2(sum I_i sin d_i, sum I_i cos d_i)``, ``B = 2/N |sum I_i exp(j d_i)|``,
    ``d_i = 2 pi i / N``.
    """
    images = np.asarray(images)
    if images.ndim != 3:
        raise SimInputError(f"images must be (N, H, W), got shape {images.shape}")
    n = images.shape[0]
    if n < 3:
        raise SimInputError(f"N-step phase shifting needs at least 3 images, got {n}")
    d = TWO_PI * np.arange(n) / n
    stack = images.astype(np.float64, copy=False)
    s = np.tensordot(np.sin(d), stack, axes=1)
    c = np.tensordot(np.cos(d), stack, axes=1)
    phase = np.mod(np.arctan2(s, c), TWO_PI)
    phase[phase >= TWO_PI] = 0.0  # mod of a tiny negative number rounds up to 2 pi
    return WrappedPhase(phase, (2.0 / n) * np.hypot(s, c), stack.mean(axis=0))


def quality_mask(
    wp: WrappedPhase,
    min_modulation: float,
    min_contrast: float = 0.0,
    saturation: float | None = None,
    max_intensity: np.ndarray | None = None,
) -> np.ndarray:
    """Pixels whose phase is trustworthy, (H, W) bool.

    min_modulation : smallest fringe amplitude ``B`` kept, image units.
    min_contrast : smallest ``B / A`` kept (0 keeps all).
    saturation, max_intensity : pixels whose brightest image (``max_intensity``, (H, W))
        reaches ``saturation`` are dropped.
    """
    if min_modulation < 0 or min_contrast < 0:
        raise SimInputError(
            f"min_modulation and min_contrast must be >= 0, got {min_modulation}, {min_contrast}"
        )
    ok = wp.modulation >= min_modulation
    if min_contrast > 0:
        ok &= wp.modulation >= min_contrast * np.maximum(wp.offset, 0.0)
    if saturation is not None:
        if max_intensity is None:
            raise SimInputError("quality_mask: saturation given without max_intensity")
        ok &= max_intensity < saturation
    return ok & np.isfinite(wp.phase)


def unwrap_with_reference(
    phase: np.ndarray, period_px: float, reference_px: np.ndarray
) -> np.ndarray:
    """Absolute phase (rad) of a wrapped phase given a coarse projector coordinate.

    phase : (...) wrapped phase of period ``period_px``; reference_px : (...) coarse
    projector coordinate, correct to better than ``period_px / 2``.
    """
    target = TWO_PI * np.asarray(reference_px) / period_px
    return phase + TWO_PI * np.round((target - phase) / TWO_PI)


def fringe_order_error(abs_phase: np.ndarray, period_px: float, reference_px: np.ndarray) -> np.ndarray:
    """How far (in fringes, |.| <= 0.5) the coarse reference was from the chosen fringe order:
    near 0 when the levels agree, near 0.5 where the unwrapping is a coin toss."""
    return (TWO_PI * np.asarray(reference_px) / period_px - abs_phase) / TWO_PI


def absolute_phase_to_projector(abs_phase: np.ndarray, period_px: float) -> np.ndarray:
    """Projector coordinate (pixels, centres at integers) of an absolute phase (rad)."""
    return np.asarray(abs_phase) * (period_px / TWO_PI)


def _single_period_coordinate(phase: np.ndarray, period_px: float, extent_px: int) -> np.ndarray:
    """Projector coordinate from a phase whose period covers the projector's whole axis.

    Coordinates lie in ``[-0.5, extent_px - 0.5]``; the wrap point is put in the middle of the
    spare range, so ``period_px`` must be at least ``extent_px``.
    """
    if period_px < extent_px:
        raise SimInputError(
            f"the coarsest period ({period_px:g} px) must be at least the projector extent "
            f"({extent_px} px) for the unwrapping to be unique"
        )
    lo = 0.5 * (extent_px - 1) - 0.5 * period_px
    u = np.asarray(phase) * (period_px / TWO_PI)
    return lo + np.mod(u - lo, period_px)


def _check_levels(phases: Sequence[np.ndarray], periods_px: Sequence[float]) -> None:
    if len(phases) != len(periods_px) or len(phases) < 1:
        raise SimInputError(
            f"need one wrapped phase per period, got {len(phases)} phases for "
            f"{len(periods_px)} periods"
        )
    shapes = {np.shape(p) for p in phases}
    if len(shapes) != 1:
        raise SimInputError(f"wrapped phases differ in shape: {sorted(shapes)}")
    if any(p <= 0 for p in periods_px):
        raise SimInputError(f"periods must be > 0 px, got {list(periods_px)}")


def unwrap_hierarchical(
    phases: Sequence[np.ndarray],
    periods_px: Sequence[float],
    extent_px: int,
    return_order_error: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Multi-frequency hierarchical temporal unwrapping.

    phases : wrapped phases (H, W), one per period; periods_px : their periods in projector
    pixels, any order; the longest must be at least ``extent_px`` (the projector's size along the
    fringe axis) and each ratio of consecutive periods must be small enough for the phase
    noise (the error of a level times the ratio must stay below half a fringe).
    Returns the absolute phase (rad) of the finest period, and with ``return_order_error``
    also the largest ``|fringe_order_error|`` over the levels, (H, W).
    """
    _check_levels(phases, periods_px)
    order = np.argsort(periods_px)[::-1]
    u = _single_period_coordinate(phases[order[0]], periods_px[order[0]], extent_px)
    abs_phase = TWO_PI * u / periods_px[order[0]]
    worst = np.zeros(np.shape(abs_phase))
    for k in order[1:]:
        abs_phase = unwrap_with_reference(phases[k], periods_px[k], u)
        worst = np.maximum(worst, np.abs(fringe_order_error(abs_phase, periods_px[k], u)))
        u = absolute_phase_to_projector(abs_phase, periods_px[k])
    return (abs_phase, worst) if return_order_error else abs_phase


def beat(
    phase_a: np.ndarray, period_a: float, phase_b: np.ndarray, period_b: float
) -> tuple[np.ndarray, float]:
    """Heterodyne beat of two wrapped phases: ``(wrapped phase in [0, 2 pi), period px)``.

    The beat of periods ``p_a < p_b`` is ``phi_a - phi_b`` with period ``p_a p_b / (p_b - p_a)``.
    """
    if period_a == period_b:
        raise SimInputError(f"heterodyne needs two different periods, got {period_a:g} twice")
    if period_a > period_b:
        phase_a, period_a, phase_b, period_b = phase_b, period_b, phase_a, period_a
    return np.mod(phase_a - phase_b, TWO_PI), period_a * period_b / (period_b - period_a)


def unwrap_heterodyne(
    phases: Sequence[np.ndarray],
    periods_px: Sequence[float],
    extent_px: int,
    return_order_error: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Two- or three-frequency heterodyne (multi-wavelength) temporal unwrapping.

    Two periods ``p1 < p2``: their beat must be at least ``extent_px``; it unwraps ``phi_1``.
    Three periods ``p1 < p2 < p3``: beats ``b12`` and ``b23``, and their beat ``b123`` (which
    must be at least ``extent_px``) unwraps the shorter of ``b12, b23``, which unwraps ``phi_1``.
    Returns the absolute phase (rad) of the finest period ``p1`` (and the order error, as
    ``unwrap_hierarchical``).
    """
    _check_levels(phases, periods_px)
    if len(phases) not in (2, 3):
        raise SimInputError(f"heterodyne unwrapping takes 2 or 3 periods, got {len(phases)}")
    order = np.argsort(periods_px)
    ph = [phases[k] for k in order]
    pp = [float(periods_px[k]) for k in order]
    if len(ph) == 2:
        b, pb = beat(ph[0], pp[0], ph[1], pp[1])
        return unwrap_hierarchical([b, ph[0]], [pb, pp[0]], extent_px, return_order_error)
    b12, p12 = beat(ph[0], pp[0], ph[1], pp[1])
    b23, p23 = beat(ph[1], pp[1], ph[2], pp[2])
    b123, p123 = beat(b12, p12, b23, p23)
    mid, pmid = (b12, p12) if p12 < p23 else (b23, p23)
    return unwrap_hierarchical([b123, mid, ph[0]], [p123, pmid, pp[0]], extent_px, return_order_error)


def gray_to_index(bits: np.ndarray) -> np.ndarray:
    """Stripe index from Gray-code bits (n_bits, H, W) bool, most significant bit first."""
    bits = np.asarray(bits, dtype=bool)
    if bits.ndim < 1 or bits.shape[0] < 1:
        raise SimInputError(f"Gray code needs at least one bit plane, got shape {bits.shape}")
    binary = np.logical_xor.accumulate(bits, axis=0)
    weights = 1 << np.arange(bits.shape[0] - 1, -1, -1, dtype=np.int64)
    return np.tensordot(weights, binary.astype(np.int64), axes=1)


def gray_bits(
    images: np.ndarray,
    threshold: np.ndarray | None = None,
    inverse: np.ndarray | None = None,
) -> np.ndarray:
    """Binarise Gray-code images (n_bits, H, W): against their inverse images where given,
    else against a threshold image (H, W) such as the phase-shift offset ``A``."""
    images = np.asarray(images, dtype=np.float64)
    if inverse is not None:
        inverse = np.asarray(inverse, dtype=np.float64)
        if inverse.shape != images.shape:
            raise SimInputError(
                f"inverse Gray images have shape {inverse.shape}, expected {images.shape}"
            )
        return images > inverse
    if threshold is None:
        raise SimInputError("gray_bits needs either a threshold image or the inverse images")
    threshold = np.asarray(threshold, dtype=np.float64)
    if threshold.shape != images.shape[1:]:
        raise SimInputError(
            f"threshold image has shape {threshold.shape}, expected {images.shape[1:]}"
        )
    return images > threshold[None]


def unwrap_gray_code(
    phase: np.ndarray,
    period_px: float,
    stripe_index: np.ndarray,
    stripe_width_px: float,
    stripe_origin_px: float = -0.5,
    return_order_error: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Absolute phase (rad) from a wrapped phase and a Gray-code stripe index.

    Stripe k covers projector coordinates ``[origin + k w, origin + (k + 1) w)``; its centre is
    the coarse coordinate. Tolerant of stripe decoding errors at the stripe edges as long as
    they reach less than ``(period - w) / 2`` pixels into the neighbour, so ``w`` must be
    shorter than the period (``w = period / 2``: one extra Gray bit, is robust). With
    ``return_order_error`` also ``|fringe_order_error|`` (up to ``w / (2 period)`` when right).
    """
    if stripe_width_px >= period_px:
        raise SimInputError(
            f"Gray-code stripes ({stripe_width_px:g} px) must be narrower than the phase "
            f"period ({period_px:g} px) to unwrap robustly; add a Gray-code bit"
        )
    coarse = stripe_origin_px + (np.asarray(stripe_index) + 0.5) * stripe_width_px
    abs_phase = unwrap_with_reference(phase, period_px, coarse)
    if return_order_error:
        return abs_phase, np.abs(fringe_order_error(abs_phase, period_px, coarse))
    return abs_phase
