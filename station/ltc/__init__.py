"""LTC reconstruction (Fourier single-pixel imaging), localisation and the LTC store.

Public names are re-exported lazily (PEP 562):
``from station.ltc import reconstruct`` imports only the submodule
that defines it, so importing the package stays cheap.
"""

from __future__ import annotations

import importlib
from typing import Any

_WHERE = {
    "LtcBlock": "spi",
    "reconstruct": "spi",
    "reconstruct_frames": "spi",
    "LcdMap": "localise",
    "lcd_coordinates": "localise",
    "LtcStoreError": "store",
    "LtcVolume": "store",
    "LtcVolumeError": "store",
    "create_ltc_store": "store",
    "open_ltc_store": "store",
    "open_ltc_volume": "store",
    "write_ltc_tile": "store",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    """Import ``name`` from its submodule on first use (then cached in this module)."""
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
