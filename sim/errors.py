"""The simulator's errors: :class:`SimError` is the root of every error ``sim`` raises on
purpose; :class:`SimInputError` is an input it refuses (a file, a field, an argument value),
and is a ``ValueError`` too.

Any other exception out of ``sim`` (a plain ``ValueError`` from numpy, an ``IndexError``) is a
bug, and the ``ltc`` command line reports it as one. Kept free of imports: ``ltc --help``
may load it.
"""

from __future__ import annotations

__all__ = ["SimError", "SimInputError"]


class SimError(Exception):
    """Root of the simulator's errors; the message names the file, field or value and what to
    do."""


class SimInputError(SimError, ValueError):
    """An input the simulator refuses: a file that cannot be read, a field or an argument out
    of range; the message names it."""
