"""Trapezoidal single-axis motion for the fake controller; microsteps and seconds."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Profile:
    """A move from ``start`` to ``end`` (microsteps) beginning at time ``t0`` (s) with speed
    ``v0`` toward ``end``: accelerate at ``accel`` (µsteps/s²) to at most ``vmax`` (µsteps/s),
    cruise, decelerate to rest exactly at ``end``. ``v0`` must not exceed what allows stopping
    within the distance (true for moves from rest and for a stop's deceleration).

    ``accel`` 0 is Zaber's "no ramp": the axis runs at ``vmax`` from the start and stops dead
    at ``end`` (duration |end - start| / vmax); a stop ends the motion where it is."""

    start: float
    end: float
    t0: float
    vmax: float
    accel: float
    v0: float = 0.0

    def _phases(self) -> tuple[float, float, float, float, float]:
        """(peak speed, accel time, accel distance, cruise distance, cruise time)."""
        d = abs(self.end - self.start)
        if self.no_ramp:
            return self.vmax, 0.0, 0.0, d, d / self.vmax
        v0 = min(self.v0, self.vmax)
        vp = min(self.vmax, math.sqrt(self.accel * d + v0 * v0 / 2))
        vp = max(vp, v0)
        t1 = (vp - v0) / self.accel
        d1 = (vp * vp - v0 * v0) / (2 * self.accel)
        d2 = max(0.0, d - d1 - vp * vp / (2 * self.accel))
        t2 = d2 / vp if vp > 0 else 0.0
        return vp, t1, d1, d2, t2

    @property
    def no_ramp(self) -> bool:
        """True for ``accel`` 0: full speed at once, no acceleration or deceleration phase."""
        return self.accel == 0

    @property
    def duration(self) -> float:
        """Total time of the move (s)."""
        if self.end == self.start:
            return 0.0
        vp, t1, _, _, t2 = self._phases()
        return t1 + t2 + (0.0 if self.no_ramp else vp / self.accel)

    def state(self, t: float) -> tuple[float, float]:
        """(position in microsteps, speed toward ``end`` in µsteps/s) at time ``t``."""
        tau = t - self.t0
        if tau >= self.duration:
            return self.end, 0.0
        tau = max(tau, 0.0)
        vp, t1, d1, d2, t2 = self._phases()
        v0 = min(self.v0, self.vmax)
        if tau < t1:
            s, v = v0 * tau + self.accel * tau * tau / 2, v0 + self.accel * tau
        elif tau < t1 + t2:
            s, v = d1 + vp * (tau - t1), vp
        else:
            u = tau - t1 - t2
            s, v = d1 + d2 + vp * u - self.accel * u * u / 2, vp - self.accel * u
        direction = 1.0 if self.end >= self.start else -1.0
        return self.start + direction * s, max(v, 0.0)

    def stopping(self, t: float) -> Profile:
        """The deceleration to rest that a stop at time ``t`` starts."""
        pos, v = self.state(t)
        if self.no_ramp:
            return Profile(pos, pos, t, self.vmax, 0.0)
        direction = 1.0 if self.end >= self.start else -1.0
        end = pos + direction * v * v / (2 * self.accel)
        return Profile(pos, end, t, max(v, 1e-9), self.accel, v)
