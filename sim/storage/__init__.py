"""Storage: the lowest layer, shared by the virtual scanner and the station. The one durable
write (temporary file, fsync, rename, fsync of the folder; ``O_DIRECT`` for large aligned
buffers), the one writer lock (``flock``), checksums, and the checks of a zarr store's
attributes. Names load on first use.
"""

from __future__ import annotations

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "errors": "StorageError",
    "durable": "DIRECT_ALIGN aligned_empty barrier durable_figure durable_file fsync_path "
               "new_file publish start_writeback sync_tree temporary_name write_all "
               "write_json write_new_file",
    "lock": "LOCK_NAME StoreLock StoreLockedError describe_holder",
    "checksum": "NO_CRC array_crc32c crc32c crc32c_extend readonly sha256_hex",
    "attrs": "RunStoreAttrs LtcStoreAttrs open_zarr_group check_attrs",
})
