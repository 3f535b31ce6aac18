"""The camera sensor: photo-electrons to digital numbers. One model for the renderer's cameras
(``sim.render.images.CameraResponse``) and the station's fake camera (``fakes.camera``).

Per pixel: expected electrons ``e``; Poisson shot noise; clipping at the full well; Gaussian
read noise (electrons rms); ``DN = black_level_dn + dn_per_e * e``, rounded half to even and
clipped to ``0 .. 2^bit_depth - 1``. The renderer applies the same last step in its compiled
kernel (``sim.render.image_kernels.response``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.errors import SimInputError


@dataclass(frozen=True)
class Sensor:
    """full_well_e : full-well capacity, electrons; dn_per_e : conversion gain, DN per
    electron; black_level_dn : offset of every pixel, DN; bit_depth : ADC bits;
    shot_noise : Poisson photon noise on/off; read_noise_e : read noise, electrons rms."""

    full_well_e: float
    dn_per_e: float
    black_level_dn: float = 0.0
    bit_depth: int = 12
    shot_noise: bool = True
    read_noise_e: float = 0.0

    @property
    def max_dn(self) -> int:
        """Largest digital number, ``2^bit_depth - 1``."""
        return (1 << self.bit_depth) - 1

    @property
    def noisy(self) -> bool:
        """Whether :meth:`expose` draws random numbers."""
        return self.shot_noise or self.read_noise_e > 0

    def expose(self, electrons: np.ndarray, rng: np.random.Generator | None,
               dtype: type = np.float64) -> np.ndarray:
        """Electrons read out (same shape, ``dtype``) for expected ``electrons``: shot noise,
        full-well clipping, read noise. ``rng`` may be None only when not :attr:`noisy`."""
        if self.noisy and rng is None:
            raise SimInputError("Sensor.expose: rng is required when shot noise or read noise is "
                                "on")
        e = np.asarray(electrons)
        if self.shot_noise:
            e = rng.poisson(np.maximum(e, 0)).astype(dtype)
        e = np.minimum(e, dtype(self.full_well_e)).astype(dtype, copy=False)
        if self.read_noise_e > 0:
            e = e + dtype(self.read_noise_e) * rng.standard_normal(e.shape, dtype=dtype)
        return e

    def expose_gaussian(self, electrons: np.ndarray, rng: np.random.Generator | None,
                        dtype: type = np.float32) -> np.ndarray:
        """:meth:`expose` with shot and read noise drawn as one normal deviate of the same
        variance, ``e + sqrt(max(e, 0) + read_noise_e^2) N(0, 1)`` (close to Poisson above a
        few tens of electrons; about 7x faster, for full-size synthetic frames), then clipped at
        the full well."""
        e = np.asarray(electrons, dtype=dtype)
        if self.noisy:
            if rng is None:
                raise SimInputError("Sensor.expose_gaussian: rng is required when noise is on")
            var = (np.maximum(e, 0) if self.shot_noise else 0) + dtype(self.read_noise_e**2)
            e = e + rng.standard_normal(e.shape, dtype=dtype) * np.sqrt(var).astype(dtype)
        return np.minimum(e, dtype(self.full_well_e))

    def digitise(self, electrons: np.ndarray) -> np.ndarray:
        """Digital numbers of electrons read out: uint8 (8 bits or fewer) or uint16."""
        dn = np.rint(self.black_level_dn + self.dn_per_e * np.asarray(electrons))
        return np.clip(dn, 0, self.max_dn).astype(np.uint8 if self.bit_depth <= 8 else np.uint16)

    def mean_dn(self, electrons: np.ndarray) -> np.ndarray:
        """Expected DN of expected electrons, below saturation."""
        return self.black_level_dn + self.dn_per_e * np.asarray(electrons)

    def variance_dn(self, electrons: np.ndarray) -> np.ndarray:
        """Expected DN variance below saturation: shot (if on) and read noise, and the
        uniform rounding (1/12)."""
        shot = np.asarray(electrons) if self.shot_noise else 0.0
        return self.dn_per_e**2 * (shot + self.read_noise_e**2) + 1.0 / 12.0
