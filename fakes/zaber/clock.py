"""A manual clock for deterministic tests of the fake controller (seconds)."""

from __future__ import annotations


class ManualClock:
    """Callable clock that only moves when told to; use in place of ``time.monotonic``."""

    def __init__(self, start: float = 0.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        """Move time forward by ``seconds`` (>= 0)."""
        if seconds < 0:
            raise ValueError(f"a clock cannot go back: advance({seconds})")
        self.now += seconds
