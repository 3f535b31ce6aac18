"""Tiled reconstruction of a whole run store into an LTC store (:func:`reconstruct`): bands of
tiles read by the workers straight from the run store, reconstructed
(:func:`station.ltc.spi.reconstruct_tile`) and written in a writer thread, each tile
recorded done with its statistics and chunk checksums; resumable, under the LTC store's
writer lock.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import datetime as _dt
import threading
import time
import uuid
from pathlib import Path

import numpy as np
from tqdm import tqdm

from sim.storage.lock import StoreLock
from station.acquisition.patterns import StationPatternPlan
from station.acquisition.run_store import RunStore, RunStoreError, software_versions
from station.compute import Engine, run_ordered
from station.ltc.spi import reconstruct_tile
from station.ltc.store import (
    TILE_STATS,
    LtcStoreError,
    LtcTileWriter,
    TileRecords,
    create_ltc_store,
    incomplete_depths,
    mark_depth_complete,
    open_ltc_store,
)

BAND_BYTES = 128 * 2**20  # frames a worker reads at once (one band of tiles side by side):
# 13 tiles at P = 24, 4-step, uint16; one open and one read per frame serve twice the pixels
# of 64 MiB (6 tiles): read CPU 1.0-1.2 instead of 1.1-1.5 us per pixel (page cache)

_OPEN_STORES: dict[str, tuple[str, LtcTileWriter]] = {}  # per worker: path -> (token, writer)
_RUN_STORES: dict[str, tuple[str, RunStore]] = {}  # per worker process: run path -> (token, store)
_BUFFERS = threading.local()  # per worker thread: the band buffer, reused from band to band


def _band_job(run_path: str, token: str, depth: int, row0: int, col0: int, n_tiles: int,
              tile_px: int, todo: list[int], plan: StationPatternPlan, lut: np.ndarray | None,
              min_snr: float, code_mask: np.ndarray, out_path: str
              ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Read one band of tiles (``n_tiles`` of ``tile_px`` side by side from camera pixel
    (row0, col0)) from the run store and reconstruct and write the tiles at band indices
    ``todo``; returns their statistics and chunk checksums in that order. Run by a worker
    (or in process): the frames go from the store to the worker without passing through
    the caller. ``token``
    names one reconstruction, so a store reopened at the same path is never a stale one.
    code_mask : (rows, cols) bool over the band."""
    import zarr

    held = _RUN_STORES.get(run_path)
    if held is None or held[0] != token:
        held = _RUN_STORES[run_path] = (token, RunStore.open(run_path))
    store = held[1]
    opened = _OPEN_STORES.get(out_path)
    if opened is None or opened[0] != token:
        opened = _OPEN_STORES[out_path] = (token, LtcTileWriter(zarr.open_group(out_path,
                                                                                mode="r+")))
    out = opened[1]
    if tile_px == store.tile_px:
        shape = (n_tiles, store.n_patterns, tile_px, tile_px)
        buf = getattr(_BUFFERS, "frames", None)
        if buf is None or buf.dtype != store.dtype or buf.size < np.prod(shape):
            buf = _BUFFERS.frames = np.empty(shape, store.dtype)
        tiles = store.read_tile_row(depth, row0, col0, n_tiles,
                                    check_index=row0 == 0 and col0 == 0, out=buf)
    else:
        w, _ = store.camera_size
        tiles = [store.read_tile(depth, row0, c0, tile_px, tile_px,
                                 check_index=row0 == 0 and c0 == 0)
                 for c0 in range(col0, min(col0 + n_tiles * tile_px, w), tile_px)]
    p = plan.fourier.period
    stats, crcs = [], []
    writing = None  # the previous tile's write, in the writer thread while this one computes
    try:
        for i in todo:
            tile = tiles[i]
            _, th, tw = tile.frames.shape
            c0 = tile.col0 - col0
            blk, st = reconstruct_tile(tile.frames, plan, lut, min_snr,
                                       code_mask[:th, c0 : c0 + tw])
            if writing is not None:
                crcs.append(writing.result())  # one tile waits to be written at most
            writing = _writer().submit(
                out.write, depth, tile.row0, tile.col0, ltc=blk.ltc.reshape(th, tw, p, p),
                origin=blk.origin.reshape(th, tw, 2), gain=blk.gain.reshape(th, tw),
                noise=blk.noise.reshape(th, tw), lcd_xy=blk.lcd_xy.reshape(th, tw, 2))
            stats.append(st)
    finally:
        if writing is not None:  # every tile reported is written (an error is raised here)
            crcs.append(writing.result())
    return list(zip(stats, crcs, strict=True))


def _writer() -> cf.ThreadPoolExecutor:
    """This thread's tile writer: one thread, so a tile's LTC (9.4 MB at P = 24, written
    into the page cache, or waiting while the kernel throttles dirty pages) is written
    while the next tile is computed; :func:`_band_job` waits for every write before it
    returns the tiles' statistics, so a tile is recorded done only once written."""
    pool = getattr(_BUFFERS, "writer", None)
    if pool is None:
        pool = _BUFFERS.writer = cf.ThreadPoolExecutor(1, thread_name_prefix="ltc-writer")
    return pool


def reconstruct(
    run_path: str | Path, out_path: str | Path, tile_px: int | None = None,
    progress: bool = True, *, min_snr: float = 10.0, resume: bool = False,
    workers: int | None = None, dask: bool = False, scheduler: str | None = None,
) -> dict:
    """Reconstruct every depth of a complete run store into an LTC store, tile by tile.

    tile_px : camera tile edge (default: the run store's inner chunk); memory depends on it,
        on the pattern count and on the workers, not on the sensor size.
    resume : finish the LTC store ``out_path`` a killed reconstruction of this run left
        (tiles recorded done are kept; the result equals an uninterrupted run bit for bit);
        refused unless the store records this run's identity (``RunStore.identity``).
    The LTC store's writer lock is held throughout: a second writer is refused naming it.
    workers, dask, scheduler : where tiles are computed (``station.compute.Engine``):
        default every core in local processes; 1 in this process; ``dask`` a Dask
        LocalCluster of ``workers`` processes; ``scheduler`` an existing Dask cluster.
        Every engine gives bit-identical stores.
    Each worker reads its bands of tiles (``BAND_BYTES`` of frames, one open and read per
    frame) straight from the run store, then computes them, writing each tile in a writer
    thread while it computes the next: only tile positions and statistics pass through this
    process, and the reads run on every worker at once. This process asks the kernel to
    read each band and the next ahead (``RunStore.prefetch_tile_row``), so the disk works
    while the workers compute.
    Returns a JSON-able summary; per-depth statistics come from the store's per-tile
    records (``tile_stats``), so a resumed run reports what an uninterrupted one does.
    """
    t_start = time.perf_counter()
    store = RunStore.open(run_path)
    todo = store.first_incomplete()
    if todo is not None:
        raise RunStoreError(f"{store.path}: run is incomplete (first frame not done: depth "
                            f"{todo[0]}, pattern {todo[1]}); finish it with --resume first")
    plan, p, lut = store.plan, store.plan.fourier.period, store.display_lut
    t = store.tile_px if tile_px is None else int(tile_px)
    if t < 1:
        raise RunStoreError(f"{store.path}: tile_px must be >= 1, got {tile_px}")
    w, h = store.camera_size
    out_path = Path(out_path)
    with contextlib.ExitStack() as held:
        if resume and out_path.exists():
            held.enter_context(StoreLock(out_path))
            out = _open_for_resume(out_path, store, t)
        else:
            out = create_ltc_store(
                out_path, depths_mm=store.depths_mm, camera_size=store.camera_size, period=p,
                pitch_mm=store.lcd_pitch_mm, lcd_size=store.lcd_size, tile_px=t,
                attrs={"run_store": str(store.path),
                       "pattern_set": plan.model_dump(mode="json"),
                       "camera_matrix": store.config.get("camera", {}).get("matrix"),
                       "config": store.config,
                       "software": software_versions(),
                       "created": _dt.datetime.now(_dt.UTC).isoformat(),
                       "run_id": store.identity()},
            )
            held.enter_context(StoreLock(out_path))
        records = TileRecords(out)
        done = records.done.copy()
        n_left = int((~done).sum())
        per_tile = len(plan) * t * t * store.dtype.itemsize
        band = max(1, BAND_BYTES // per_tile)  # tiles a worker reads and computes per task
        token = uuid.uuid4().hex
        px_done = [0]
        with Engine(workers, dask=dask, scheduler=scheduler) as engine, \
                tqdm(total=done.size, initial=done.size - n_left, desc="reconstruct",
                     unit="tile", disable=None if progress else True) as bar:
            bar.set_postfix_str(engine.describe(), refresh=False)
            for di in range(store.n_depths):
                if done[di].all():
                    if di in incomplete_depths(out):
                        mark_depth_complete(out, di)
                    continue
                code_mask = store.code_mask(di)

                def tasks(di=di, code_mask=code_mask):
                    bands = [(r0, b0, min(band, -(-(w - b0) // t)))
                             for r0 in range(0, h, t) for b0 in range(0, w, band * t)
                             if not done[di, r0 // t, b0 // t : b0 // t + band].all()]
                    for i, (r0, b0, n) in enumerate(bands):
                        # the disk reads this band and the next while the workers compute
                        # the ones before (for the stored tile size; a hint, nothing else)
                        for r1, b1, n1 in bands[(i > 0) + i : i + 2] if t == store.tile_px else ():
                            store.prefetch_tile_row(di, r1, b1, n1)
                        tr = r0 // t
                        todo = [k for k in range(n) if not done[di, tr, b0 // t + k]]
                        for k in todo:
                            px_done[0] += min(t, h - r0) * min(t, w - b0 - k * t)
                        cm = np.ascontiguousarray(code_mask[r0 : r0 + t, b0 : b0 + n * t])
                        yield ((di, tr, [b0 // t + k for k in todo]), _band_job,
                               (str(store.path), token, di, r0, b0, n, t, todo, plan, lut,
                                float(min_snr), cm, str(out_path)))

                def finished(key, results) -> None:
                    di_, tr, cols = key
                    records.mark(di_, tr, cols, [st for st, _ in results],
                                 [crc for _, crc in results])
                    bar.update(len(cols))

                run_ordered(engine, tasks(), finished)
                mark_depth_complete(out, di)
            used = engine.describe()
        stats_all = np.asarray(out["tile_stats"][...])
        per_depth = []
        for di in range(store.n_depths):
            st = stats_all[di].reshape(-1, len(TILE_STATS))
            per_depth.append({
                "depth_mm": store.depths_mm[di],
                "valid_fraction": float(np.nansum(st[:, 0])) / (w * h),
                "gain_median_adu": _median(st[:, 1]),
                "noise_median": _median(st[:, 2]),
                "edge_mass_p95": _max(st[:, 3]),
            })
        out.attrs["noise_median"] = [q["noise_median"] for q in per_depth]
    seconds = time.perf_counter() - t_start
    return {
        "run": str(store.path), "out": str(out_path), "camera_size": list(store.camera_size),
        "lcd_size": list(store.lcd_size), "period": p, "steps": plan.fourier.steps,
        "patterns_per_depth": len(plan), "tile_px": t, "depths": per_depth,
        "engine": used, "tiles_computed": n_left, "resumed": bool(resume and n_left < done.size),
        "seconds": seconds, "pixels_per_second": px_done[0] / max(seconds, 1e-9),
    }


def _open_for_resume(out_path: Path, store: RunStore, tile_px: int):
    """The LTC store a killed reconstruction of ``store`` left, checked to be that one."""
    out = open_ltc_store(out_path, mode="r+")
    a = out.attrs
    if a.get("run_id") != store.identity():
        started = store.group.attrs.get("start_time", "?")
        raise LtcStoreError(f"{out_path}: was reconstructed from run {a.get('run_id')!r} (run "
                            f"store {a.get('run_store')!r}, created {a.get('created', '?')}), "
                            f"but {store.path} is run {store.identity()!r} (acquired from "
                            f"{started}); cannot resume it from another run: reconstruct "
                            "afresh with --force")
    if int(a.get("tile_px", -1)) != tile_px:
        raise LtcStoreError(f"{out_path}: was written with tile_px {a.get('tile_px')}, not "
                            f"{tile_px}; resume with --tile {a.get('tile_px')}")
    if a.get("pattern_set") != store.plan.model_dump(mode="json"):
        raise LtcStoreError(f"{out_path}: pattern set differs from the run store's")
    return out


def _median(values: np.ndarray) -> float | None:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else None


def _max(values: np.ndarray) -> float | None:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.max()) if v.size else None
