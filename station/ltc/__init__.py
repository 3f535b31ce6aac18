"""LTC reconstruction (Fourier single-pixel imaging), localisation and the LTC store; names
load on first use (``import station.ltc`` stays cheap)."""

from __future__ import annotations

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "spi": "LtcBlock reconstruct_frames reconstruct_tile",
    "tiles": "reconstruct",
    "localise": "LcdMap lcd_coordinates",
    "store": "LtcStoreError LtcVolume LtcVolumeError create_ltc_store open_ltc_store "
             "open_ltc_volume write_ltc_tile LtcTileWriter mark_depth_complete mark_tile_done "
             "TileRecords",
    "checked": "CheckedArray LtcChunkError",
    "verify": "StoreReport verify_store",
})
