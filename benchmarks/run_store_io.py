"""Run-store layout and compressor, measured at full size.

Writes a few full-size camera frames (4096 x 2168, 12-bit in uint16 and 8-bit in uint8, a
blurred fringe with shot and read noise) in each candidate layout, with a raw sequential file
write of the same bytes (the frame's buffer appended, fsync per frame) as the reference in
the same run, paired frame by frame with the run store's writes (alternating which goes
first, per-frame medians), then reads one row of 64 x 64 tiles of every frame (what
reconstruction reads) against a raw read of the same bytes. Candidates:

- ``store``: the run store as built (format 2): per-frame shard of 64 x 64 uncompressed chunks
  with crc32c, written and read by the store itself (includes metadata, done flag, syncfs).
- ``zarr-zstd``: format 1's layout written through zarr (per-frame shard, 64 x 64 inner chunks,
  zarr's default zstd).
- ``zarr-lz4`` / ``zarr-none``: the same with blosc lz4 + shuffle / no compressor.
- ``zarr-k8``: shards of 8 frames x whole frame, inner chunks 8 x 64 x 64 (zstd), written 8
  frames at a time (per frame: total / 8).

Capture loop (``--capture``): the acquisition's loop shape with zero-latency fakes at full
size: per frame an optional camera wait (``--frame-ms``, sleeping, GIL free), an optional
stretch of pure-Python work holding the GIL (``--gil-ms``, standing for the loop's own Python),
a copy of a ready frame (the camera driver's buffer copy), and ``FrameWriter.submit_frame``
(the pipelined writer, queue of 4), against the same loop whose writer does nothing. Prints
frames/s with and without storage, and the loop's GIL work per frame with and without (if the
writer held the GIL, that work would stretch).

Writer throughput (``--throughput``): ``--frames`` full-size frames submitted back to back
through ``FrameWriter`` (then closed), and through ``RunStore.write_frame`` in series, against
raw appends of the same bytes with an fsync per frame, in the same run; prints each one's
ratio to raw (the target: at least 0.7).

Run: ``python benchmarks/run_store_io.py [--frames 6] [--dir /tmp] [--zarr] [--capture]
[--throughput]``. ``--zarr``
adds the zarr candidates (slow: seconds per frame); without it only ``raw`` and ``store`` run.
Prints a table; ``--write-results`` also rewrites ``benchmarks/results/run_store_io.md``
(``run_store_io-capture.md``, ``run_store_io-throughput.md`` for those modes). The decision
it informed: ``docs/decisions/``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zarr
from zarr.codecs import BloscCodec, BytesCodec, ZstdCodec

from station.acquisition.patterns import StationPatternPlan
from station.acquisition.run_store import FrameMeta, RunStore

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import captured, command_line, text_block, write_results  # noqa: E402

W, H, T = 4096, 2168, 64


def frames(n: int, bits: int) -> list[np.ndarray]:
    """Realistic camera frames: fringes through a blur, shot noise, read noise."""
    rng = np.random.default_rng(0)
    u = np.arange(W)[None, :]
    v = np.arange(H)[:, None]
    full = 2**bits - 1
    out = []
    for k in range(n):
        lum = 0.5 + 0.45 * np.cos(2 * np.pi * (u * 0.9 + v * 0.2) / 24.0 + k * np.pi / 2)
        e = rng.poisson(4000.0 * lum) + rng.normal(0.0, 5.0, (H, W))
        out.append(np.clip(np.rint(e * full / 5000.0), 0, full).astype(
            np.uint8 if bits <= 8 else np.uint16))
    return out


def du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def raw_read_rows(path: Path, n: int, dtype: np.dtype) -> float:
    """Read rows 0..T of every frame from the raw file (the same bytes a tile row holds)."""
    row_bytes = W * dtype.itemsize
    t0 = time.perf_counter()
    with open(path, "rb") as f:
        for k in range(n):
            f.seek(k * H * row_bytes)
            np.frombuffer(f.read(T * row_bytes), dtype)
    return time.perf_counter() - t0


def store_case(root: Path, imgs: list[np.ndarray], bits: int
               ) -> tuple[tuple[float, float, int], tuple[float, float, int]]:
    """The run store and the raw reference, paired: each frame is written to the raw file
    (append, fsync) and to the store (``write_frame``), in alternating order, so load on a
    shared machine hits both alike; per-frame medians. Returns (raw row, store row)."""
    n = len(imgs)
    plan = StationPatternPlan.for_lcd((64, 48), 4, 4)
    assert len(plan) > n
    s = RunStore.create(root / "store.zarr", config={}, plan=plan, depths_mm=[0.0],
                        camera_size=(W, H), bit_depth=bits, lcd_size=(64, 48),
                        lcd_pitch_mm=0.2715, tile_px=T)
    meta = FrameMeta(stage_target_mm=0.0, stage_measured_mm=0.0, swap_index=0, swap_time_s=0,
                     camera_timestamp_s=0, frame_id=0, exposure_ms=1.0)
    s.write_frame(0, n, imgs[0], meta)  # warm-up, untimed
    raw_t, store_t = [], []
    with open(root / "raw.bin", "wb") as raw:
        for p, img in enumerate(imgs):
            for what in ("raw", "store")[:: 1 if p % 2 else -1]:
                t0 = time.perf_counter()
                if what == "raw":
                    raw.write(img.data)
                    raw.flush()
                    os.fsync(raw.fileno())
                    raw_t.append(time.perf_counter() - t0)
                else:
                    s.write_frame(0, p, img, meta)
                    store_t.append(time.perf_counter() - t0)
    s.flush()
    raw_read = raw_read_rows(root / "raw.bin", n, imgs[0].dtype)
    class FirstFrames(RunStore):  # the store seen through its first n patterns
        n_patterns = property(lambda self: n)

    part = FirstFrames.open(s.path)
    t0 = time.perf_counter()  # one tile row of every frame, as iter_tiles reads it
    tile = part._read_tile(0, 0, 0, T, W, check_index=True)  # noqa: SLF001
    read = time.perf_counter() - t0
    assert np.array_equal(tile.frames[-1], imgs[-1][:T])
    size = du(root / "store.zarr" / "frames") * n // (n + 1)  # n frames + the warm-up
    return ((statistics.median(raw_t), raw_read, n * imgs[0].nbytes),
            (statistics.median(store_t), read, size))


def throughput_case(root: Path, imgs: list[np.ndarray], bits: int, n: int, how: str) -> float:
    """Seconds to write ``n`` frames back to back: ``raw`` appends each frame's buffer to one
    file with an fsync per frame; ``store`` submits them to a ``FrameWriter`` (the pipelined
    writer the acquisition uses) and closes it; ``serial`` calls ``RunStore.write_frame`` in
    this thread (the three stages in series, the writer of the previous version)."""
    from station.acquisition.acquire import FrameWriter

    plan = StationPatternPlan.for_lcd((64, 48), 4, 4)
    depths = -(-(n + 1) // len(plan))
    meta = FrameMeta(stage_target_mm=0.0, stage_measured_mm=0.0, swap_index=0, swap_time_s=0,
                     camera_timestamp_s=0, frame_id=0, exposure_ms=1.0)
    if how == "raw":
        with open(root / f"tp-raw-{bits}.bin", "wb") as raw:
            raw.write(imgs[0].data)  # warm-up, untimed
            raw.flush()
            os.fsync(raw.fileno())
            t0 = time.perf_counter()
            for k in range(n):
                raw.write(imgs[k % len(imgs)].data)
                raw.flush()
                os.fsync(raw.fileno())
            return time.perf_counter() - t0
    s = RunStore.create(root / f"tp-{how}-{bits}.zarr", config={}, plan=plan,
                        depths_mm=[0.0] * depths, camera_size=(W, H), bit_depth=bits,
                        lcd_size=(64, 48), lcd_pitch_mm=0.2715, tile_px=T)
    s.write_frame(depths - 1, len(plan) - 1, imgs[0], meta)  # warm-up, untimed
    t0 = time.perf_counter()
    if how == "serial":
        for k in range(n):
            s.write_frame(*divmod(k, len(plan)), imgs[k % len(imgs)], meta)
        s.flush()
    else:
        writer = FrameWriter(s)
        for k in range(n):
            writer.submit_frame(f"frame {k}", *divmod(k, len(plan)), imgs[k % len(imgs)], meta)
        writer.close()
    return time.perf_counter() - t0


def throughput_main(args: argparse.Namespace) -> None:
    for bits in (12, 8):
        imgs = frames(3, bits)
        times: dict[str, list[float]] = {"raw": [], "store": [], "serial": []}
        for r in range(args.repeats):
            root = Path(tempfile.mkdtemp(prefix="run_store_io-", dir=args.dir))
            try:
                order = list(times)[:: 1 if r % 2 == 0 else -1]  # alternate who goes first
                for how in order:
                    times[how].append(throughput_case(root, imgs, bits, args.frames, how))
            finally:
                shutil.rmtree(root, ignore_errors=True)
        t = {k: statistics.median(v) for k, v in times.items()}
        mb = imgs[0].nbytes * args.frames / 1e6
        print(f"\nwriter throughput, {bits}-bit frames ({imgs[0].dtype}, "
              f"{imgs[0].nbytes / 1e6:.1f} MB each), {args.frames} frames back to back, "
              f"median of {args.repeats}")
        for how, label in (("raw", "raw + fsync/frame"), ("store", "FrameWriter"),
                           ("serial", "write_frame serial")):
            print(f"{label:<20} {t[how]:7.2f} s {args.frames / t[how]:6.1f} frames/s "
                  f"{mb / t[how]:6.0f} MB/s  vs raw {t['raw'] / t[how]:5.2f}")


def zarr_case(root: Path, imgs: list[np.ndarray], name: str) -> tuple[float, float, int]:
    n = len(imgs)
    k = 8 if name == "zarr-k8" else 1
    kw = {"zarr-zstd": {"compressors": [ZstdCodec(level=0)]},
          "zarr-lz4": {"compressors": [BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")]},
          "zarr-none": {"compressors": None},
          "zarr-k8": {"compressors": [ZstdCodec(level=0)]}}[name]
    g = zarr.open_group(str(root / f"{name}.zarr"), mode="w-", zarr_format=3)
    a = g.create_array("frames", shape=(1, n, H, W), dtype=imgs[0].dtype, fill_value=0,
                       shards=(1, k, -(-H // T) * T, W), chunks=(1, k, T, T),
                       serializer=BytesCodec(endian="little"), **kw)
    t0 = time.perf_counter()
    if k == 1:
        for p, img in enumerate(imgs):
            a[0, p] = img
    else:
        for p0 in range(0, n, k):
            a[0, p0 : p0 + k] = np.stack(imgs[p0 : p0 + k])
    write = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    np.asarray(a[0, :, 0:T, :])
    read = time.perf_counter() - t0
    return write, read, du(root / f"{name}.zarr" / "frames")


def python_work(ms: float) -> None:
    """Pure-Python work holding the GIL for about ``ms`` milliseconds (calibrated once)."""
    n = int(ms * _LOOPS_PER_MS)
    x = 0
    for i in range(n):
        x += i * i


def _calibrate() -> float:
    t0 = time.perf_counter()
    x = 0
    for i in range(2_000_000):
        x += i * i
    return 2_000_000 / ((time.perf_counter() - t0) * 1e3)


_LOOPS_PER_MS = 0.0


def capture_case(root: Path, imgs: list[np.ndarray], bits: int, n: int, store: str,
                 frame_ms: float, gil_ms: float) -> tuple[float, float]:
    """(frames/s of the loop, mean seconds of its GIL work per frame); the writer writes
    through the run store (``store``), appends the bytes to one file with an fsync per frame
    (``raw``) or does nothing (``none``)."""
    from station.acquisition.acquire import FrameWriter

    plan = StationPatternPlan.for_lcd((64, 48), 4, 4)
    depths = -(-(n + 1) // len(plan))
    s = RunStore.create(root / f"cap-{store}.zarr", config={}, plan=plan,
                        depths_mm=[0.0] * depths, camera_size=(W, H), bit_depth=bits,
                        lcd_size=(64, 48), lcd_pitch_mm=0.2715, tile_px=T)
    meta = FrameMeta(stage_target_mm=0.0, stage_measured_mm=0.0, swap_index=0, swap_time_s=0,
                     camera_timestamp_s=0, frame_id=0, exposure_ms=1.0)
    s.write_frame(depths - 1, len(plan) - 1, imgs[0], meta)  # warm-up, untimed
    raw = open(root / "capture-raw.bin", "wb")  # noqa: SIM115 - closed below

    def raw_write(_d: int, _p: int, frame: np.ndarray, _m: FrameMeta) -> None:
        raw.write(frame.data)
        raw.flush()
        os.fsync(raw.fileno())

    write = {"raw": raw_write, "none": lambda *_: None}.get(store)
    writer = FrameWriter(s)
    gil = 0.0
    t0 = time.perf_counter()
    for k in range(n):
        if frame_ms:
            time.sleep(frame_ms / 1e3)
        g0 = time.perf_counter()
        python_work(gil_ms)
        gil += time.perf_counter() - g0
        frame = imgs[k % len(imgs)].copy()
        if write is None:  # the store: the pipelined writer's frame path
            writer.submit_frame(f"frame {k}", *divmod(k, len(plan)), frame, meta)
        else:
            writer.submit(f"frame {k}", write, *divmod(k, len(plan)), frame, meta)
    writer.close()
    fps = n / (time.perf_counter() - t0)
    raw.close()
    return fps, gil / n


def capture_main(args: argparse.Namespace) -> None:
    global _LOOPS_PER_MS
    _LOOPS_PER_MS = _calibrate()
    for bits in (12, 8):
        imgs = frames(3, bits)
        print(f"\ncapture loop, {bits}-bit frames ({imgs[0].dtype}), {args.frames} frames, "
              f"camera wait {args.frame_ms} ms, GIL work {args.gil_ms} ms; median of "
              f"{args.repeats}")
        rows: dict[str, list[tuple[float, float]]] = {"none": [], "raw": [], "store": []}
        for _ in range(args.repeats):
            root = Path(tempfile.mkdtemp(prefix="run_store_io-", dir=args.dir))
            try:
                for store in rows:
                    rows[store].append(capture_case(root, imgs, bits, args.frames, store,
                                                    args.frame_ms, args.gil_ms))
            finally:
                shutil.rmtree(root, ignore_errors=True)
        fps = {k: statistics.median(x[0] for x in v) for k, v in rows.items()}
        gil = {k: statistics.median(x[1] for x in v) for k, v in rows.items()}
        for name, label in (("none", "without storage"), ("raw", "raw file + fsync"),
                            ("store", "run store")):
            print(f"{label:<16} {fps[name]:7.1f} frames/s ({1 - fps[name] / fps['none']:6.1%} "
                  f"below without), GIL work {gil[name] * 1e3:6.1f} ms/frame")
        print(f"run store / raw  {fps['store'] / fps['raw']:7.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--dir", type=Path, default=None)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--zarr", action="store_true", help="also the zarr candidates (slow)")
    ap.add_argument("--capture", action="store_true", help="the capture loop instead")
    ap.add_argument("--throughput", action="store_true",
                    help="writer throughput instead: frames back to back through FrameWriter, "
                         "write_frame in series, and raw appends with fsync per frame")
    ap.add_argument("--frame-ms", type=float, default=0.0, help="camera wait per frame, ms")
    ap.add_argument("--gil-ms", type=float, default=0.0, help="GIL-holding work per frame, ms")
    ap.add_argument("--write-results", action="store_true",
                    help="rewrite benchmarks/results/run_store_io[-MODE].md with this run")
    args = ap.parse_args()
    if args.write_results:
        variant = "capture" if args.capture else "throughput" if args.throughput else None
        with captured() as out:
            run(args)
        write_results(__file__, "Run-store layout, writer throughput and capture loop",
                      text_block(out.getvalue()), command=command_line(), variant=variant)
        return
    run(args)


def run(args: argparse.Namespace) -> None:
    """The mode that ``args`` asks for, printed."""
    if args.capture:
        capture_main(args)
        return
    if args.throughput:
        throughput_main(args)
        return
    for bits in (12, 8):
        imgs = frames(args.frames, bits)
        nbytes = imgs[0].nbytes
        rows: dict[str, list[tuple[float, float, int]]] = {}
        for _ in range(args.repeats):
            root = Path(tempfile.mkdtemp(prefix="run_store_io-", dir=args.dir))
            try:
                raw_row, store_row = store_case(root, imgs, bits)
                rows.setdefault("raw", []).append(raw_row)
                rows.setdefault("store", []).append(store_row)
                for name in ("zarr-zstd", "zarr-lz4", "zarr-none", "zarr-k8") * args.zarr:
                    rows.setdefault(name, []).append(zarr_case(root, imgs, name))
            finally:
                shutil.rmtree(root, ignore_errors=True)
        raw_w = statistics.median(x[0] for x in rows["raw"])
        raw_r = statistics.median(x[1] for x in rows["raw"])
        print(f"\n{bits}-bit frames ({imgs[0].dtype}, {nbytes / 1e6:.1f} MB each), "
              f"{args.frames} frames (raw and store paired, median per frame), median of "
              f"{args.repeats} repeats")
        print(f"{'layout':<10} {'write s/frame':>14} {'MB/s':>8} {'vs raw':>7} "
              f"{'tile-row read s':>16} {'vs raw':>7} {'size ratio':>10}")
        for name, xs in rows.items():
            w = statistics.median(x[0] for x in xs)
            r = statistics.median(x[1] for x in xs)
            size = xs[0][2] / (len(imgs) * nbytes)
            print(f"{name:<10} {w:>14.3f} {nbytes / w / 1e6:>8.0f} {raw_w / w:>7.2f} "
                  f"{r:>16.4f} {raw_r / r:>7.2f} {size:>10.2f}")


if __name__ == "__main__":
    main()
