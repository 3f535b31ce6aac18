"""The error root of the storage layer: a store or output that cannot be written, locked or
trusted; the message names the path and what to do."""

from __future__ import annotations

from sim.errors import SimInputError


class StorageError(SimInputError):
    """A store or output is locked, damaged or misused; the message names the path."""
