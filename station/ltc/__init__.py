"""LTC reconstruction (Fourier single-pixel imaging), localisation and the LTC store.

Public names are re-exported lazily (PEP 562):
``from station.ltc import reconstruct`` imports only the submodule
that defines it, so importing the package stays cheap.
"""

from __future__ import annotations

from sim._lazy import lazy_exports


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
    "mark_depth_complete": "store",
    "mark_tile_done": "store",
    "Engine": "parallel",
    "open_ltc_store": "store",
    "open_ltc_volume": "store",
    "write_ltc_tile": "store",
}

__all__ = sorted(_WHERE)


__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals())
