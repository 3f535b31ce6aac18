"""The paper's configuration on the synthetic full-size bench: 4096 x 2168 camera,
3840 x 2160 LCD, P = 24, 4-step (1,177 frames per depth).

    python benchmarks/full_size.py --out /tmp/full            # full size (hours on 2 cores)
    python benchmarks/full_size.py --out /tmp/crop --rows 32  # full width, 32 rows: minutes
    python benchmarks/full_size.py --out /tmp/crops --rows 64 256 --cold --skip-lens

``--write-results`` also rewrites ``benchmarks/results/full_size.md`` (``full_size-lens.md``
with ``--lens-only``) with the printed figures.

Stages, each in its own process so its peak memory (ru_maxrss, workers included) is its own:
capture without storage (show + capture of every pattern of one depth), ``acquire`` of one
depth into a run store, the reference read of the depth's frame files (``raw_read``: every
byte in 16 MiB reads, the disk's pace), the store's checked read of them
(``RunStore.iter_tiles``), ``reconstruct`` (every core), centroid error against the bench's
true moments, and the lens derivation with default settings on an LTC store of two depths
written from the bench's true LTC plus noise. ``--cold`` drops the page cache before each
read (root). Projections scale the measured per-pixel times to the full sensor and six
depths; with two or more crops the full sensor is also projected from their difference, so
fixed costs (worker start-up, 1,177 files opened) are not scaled; N Dask workers divide the
compute, never below one read of the frames.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _results import captured, command_line, text_block, write_results  # noqa: E402

FULL_H = 2168
LENS_DEPTHS = (60.0, 260.0, 100.0, 140.0, 180.0, 220.0)  # the first --lens-depths are used
CONFIG = """
backend = "fake"
depths_mm = {depths}
[stage]
travel_mm = [0.0, 400.0]
[display]
latency_frames = 0
[camera]
exposure_ms = 20.0
[patterns]
period = 24
steps = 4
[frame_check]
enabled = false
[fake]
model = "synthetic"
seed = 1
rows = [{r0}, {r1}]
"""


def peak_mb() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, kids) / 1024.0


def stage(name: str, out: Path, rows: int, workers: int | None, depths: int = 2) -> dict:
    from station.acquisition.acquire import pattern_plan
    from station.api import acquire, load_config, open_bench
    from station.compute import default_workers

    cfg_path = out / "bench.toml"
    cfg = load_config(cfg_path)
    res: dict = {}
    if name == "capture":
        with open_bench(cfg) as b:
            plan = pattern_plan(cfg, b.display.size)
            b.stage.move_to(cfg.depths_mm[0])
            t = time.perf_counter()
            for i in range(len(plan)):
                b.display.show(plan.image(i, b.display.size))
                b.camera.capture()
            res["capture_fps_no_storage"] = len(plan) / (time.perf_counter() - t)
    elif name == "acquire":
        t = time.perf_counter()
        s = acquire(cfg, out / "run.zarr", progress=False)
        res["acquire_seconds"] = time.perf_counter() - t
        res["capture_fps_with_storage"] = s["frames_written"] / res["acquire_seconds"]
    elif name == "raw_read":  # the reference: every frame file's bytes, in 16 MiB reads
        files = sorted((out / "run.zarr" / "frames" / "c" / "0").rglob("*"))
        nbytes = 0
        t = time.perf_counter()
        for f in (q for q in files if q.is_file()):
            with open(f, "rb", buffering=0) as fh:
                while chunk := fh.read(16 << 20):
                    nbytes += len(chunk)
        res["raw_read_seconds"] = time.perf_counter() - t
        res["raw_read_mb_s"] = nbytes / 1e6 / res["raw_read_seconds"]
    elif name == "read":
        from station.acquisition.run_store import RunStore

        st = RunStore.open(out / "run.zarr")
        t = time.perf_counter()
        nbytes = sum(tile.frames.nbytes for tile in st.iter_tiles(0))
        res["read_seconds"] = time.perf_counter() - t
        res["read_mb_s"] = nbytes / 1e6 / res["read_seconds"]
    elif name == "reconstruct":
        from station.ltc.tiles import reconstruct

        s = reconstruct(out / "run.zarr", out / "ltc.zarr", progress=False, workers=workers)
        res.update(reconstruct_seconds=s["seconds"], pixels_per_second=s["pixels_per_second"],
                   engine=s["engine"])
    elif name == "truth":
        res.update(centroid_error(cfg, out / "ltc.zarr", rows))
    elif name == "lens_store":
        write_true_store(cfg, out / "lens_ltc.zarr", depths=sorted(LENS_DEPTHS[:depths]))
    elif name == "lens":
        from station.api import derive_lens
        from station.lens.geometry import LensFitConfig

        tree = TreePeak()
        t = time.perf_counter()
        # two depths cannot fit the focus: give the bench's (from its pupil, the centre)
        # the plain derivation at every pixel, as this benchmark has always timed it
        lens_cfg = LensFitConfig.basic(focus_distance_mm=_bench(cfg).config.focus_distance_mm)
        r = derive_lens(out / "lens_ltc.zarr", lens_cfg, progress=False,
                        out=out / "lens.npz", workers=workers)
        res["lens_seconds"] = time.perf_counter() - t
        res["lens_pixels_per_second"] = 4096 * rows / res["lens_seconds"]
        res["lens_pixels_usable"] = r.summary().pixels_usable
        res["lens_file_mb"] = (out / "lens.npz").stat().st_size / 1e6
        res["lens_workers"] = workers or default_workers()
        res.update(tree.stop())
        return res
    res[f"{name}_peak_mb"] = peak_mb()
    return res


class TreePeak:
    """Peak resident memory of this process and every descendant (worker processes of any
    engine, forkserver children included): each process's own peak (VmHWM) polled from
    /proc, summed. The sum is an upper bound on the peak of the whole job."""

    def __init__(self, every_s: float = 0.5) -> None:
        import threading

        self.peaks: dict[int, float] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(every_s,), daemon=True)
        self._thread.start()

    def _descendants(self) -> list[int]:
        parent: dict[int, int] = {}
        for d in os.listdir("/proc"):
            if d.isdigit():
                try:
                    with open(f"/proc/{d}/stat") as f:
                        parent[int(d)] = int(f.read().rsplit(")", 1)[1].split()[1])
                except (OSError, IndexError, ValueError):
                    pass
        out, todo = [], [os.getpid()]
        while todo:
            p = todo.pop()
            out.append(p)
            todo += [c for c, q in parent.items() if q == p]
        return out

    def _run(self, every_s: float) -> None:
        while not self._stop.wait(every_s):
            for pid in self._descendants():
                try:
                    with open(f"/proc/{pid}/status") as f:
                        kb = next(int(x.split()[1]) for x in f if x.startswith("VmHWM"))
                except (OSError, StopIteration):
                    continue
                self.peaks[pid] = max(self.peaks.get(pid, 0.0), kb / 1024.0)

    def stop(self) -> dict:
        self._stop.set()
        self._thread.join()
        me = os.getpid()
        others = sorted((v for p, v in self.peaks.items() if p != me), reverse=True)
        return {"lens_parent_peak_mb": peak_mb(), "lens_other_process_peaks_mb": others[:4],
                "lens_peak_mb": peak_mb() + sum(others)}


def _bench(cfg):
    from fakes.synthetic import SyntheticBench, parse_synthetic_settings

    s = parse_synthetic_settings(cfg.fake)
    return SyntheticBench(s.synthetic, s.rows)


def centroid_error(cfg, ltc_path: Path, rows: int) -> dict:
    from station.lens.centroids import window_stats
    from station.ltc.store import open_ltc_store

    g = open_ltc_store(ltc_path)
    truth, _ = _bench(cfg).true_moments(cfg.depths_mm[0])
    p = g["ltc"].shape[-1]
    errs = []
    for r0 in range(0, rows, 64):
        ltc = np.asarray(g["ltc"][0, r0 : r0 + 64], dtype=np.float64).reshape(-1, p, p)
        noise = np.asarray(g["noise"][0, r0 : r0 + 64], dtype=np.float64).ravel()
        st = window_stats(ltc, noise)
        got = st.centroid + np.asarray(g["origin"][0, r0 : r0 + 64]).reshape(-1, 2)
        errs.append(np.hypot(*(got - truth[r0 : r0 + 64].reshape(-1, 2)).T))
    e = np.concatenate(errs)
    ok = np.isfinite(e)
    return {"centroid_error_p50_px": float(np.percentile(e[ok], 50)),
            "centroid_error_p95_px": float(np.percentile(e[ok], 95)),
            "centroid_valid_fraction": float(ok.mean())}


def write_true_store(cfg, path: Path, depths=(60.0, 260.0), p: int = 24,
                     noise: float = 1e-3) -> None:
    """An LTC store of two depths: the bench's true LTC (Gaussian integrated over LCD pixels)
    in P x P windows, plus Gaussian noise of std ``noise`` per weight."""
    from scipy.special import ndtr

    from station.ltc.store import centred_origins, create_ltc_store, mark_depth_complete

    b = _bench(cfg)
    c = b.config
    w = c.camera_size[0]
    h = b.rows[1] - b.rows[0]
    k = b.K.copy()
    k[1, 2] -= b.rows[0]
    g = create_ltc_store(path, depths_mm=list(depths), camera_size=(w, h), period=p,
                         pitch_mm=c.lcd_pitch_mm, lcd_size=c.lcd_size,
                         attrs={"camera_matrix": k.tolist()})
    rng = np.random.default_rng(0)
    for i, z in enumerate(depths):
        mu, mom = b.true_moments(z)
        for r0 in range(0, h, 16):
            m = mu[r0 : r0 + 16].reshape(-1, 2)
            o = centred_origins(m, p)
            f = b.field(z)
            sx = np.sqrt(f["sxx"][r0 : r0 + 16].ravel())
            sy = np.sqrt(f["syy"][r0 : r0 + 16].ravel())
            x = o[:, 0, None] + np.arange(p + 1) - 0.5
            y = o[:, 1, None] + np.arange(p + 1) - 0.5
            wx = np.diff(ndtr((x - m[:, :1]) / sx[:, None]), axis=1)
            wy = np.diff(ndtr((y - m[:, 1:]) / sy[:, None]), axis=1)
            win = wy[:, :, None] * wx[:, None, :]  # axis-aligned: the test store's LTC
            win = win / win.sum(axis=(1, 2), keepdims=True)
            win += rng.normal(0.0, noise, win.shape)
            n = len(m) // w
            g["ltc"][i, r0 : r0 + n] = win.reshape(n, w, p, p)
            g["origin"][i, r0 : r0 + n] = o.reshape(n, w, 2)
            g["gain"][i, r0 : r0 + n] = 3000.0
            g["noise"][i, r0 : r0 + n] = noise
        mark_depth_complete(g, i, all_tiles=True)


COLD_STAGES = ("raw_read", "read", "reconstruct")  # --cold: the page cache dropped first


def drop_page_cache() -> None:
    """Empty the kernel's page cache (root only), so the next read comes from the disk."""
    os.sync()
    try:
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
    except OSError as exc:
        sys.exit(f"--cold: cannot drop the page cache ({exc.strerror}); run as root or "
                 "without --cold")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="work folder (replaced)")
    ap.add_argument("--rows", type=int, nargs="+", default=[FULL_H],
                    help="camera rows (crop, full width); two or more crops also project "
                         "the full sensor from their difference (fixed costs apart)")
    ap.add_argument("--cold", action="store_true",
                    help="drop the page cache before every read (root only)")
    ap.add_argument("--workers", type=int, default=None, help="reconstruction workers")
    ap.add_argument("--dask-workers", type=int, default=8, help="N for the projection")
    ap.add_argument("--stage", help=argparse.SUPPRESS)
    ap.add_argument("--skip-lens", action="store_true")
    ap.add_argument("--lens-only", action="store_true",
                    help="only the lens stage (at every --lens-rows)")
    ap.add_argument("--lens-rows", type=int, nargs="+", default=[64, 256],
                    help="crop heights of the lens stage (memory flat in sensor size: compare)")
    ap.add_argument("--lens-depths", type=int, default=2, choices=range(2, 7),
                    help="depths of the lens stage's LTC store")
    ap.add_argument("--write-results", action="store_true",
                    help="rewrite benchmarks/results/full_size.md with the printed figures")
    a = ap.parse_args()
    if a.write_results and not a.stage:
        with captured() as out:
            run(a)
        write_results(__file__, "Full size on the synthetic bench",
                      text_block(out.getvalue(), "Figures in seconds, bytes and hours as named; "
                                 "per-pixel times in seconds."),
                      command=command_line(), variant="lens" if a.lens_only else None)
        return
    run(a)


def run(a: argparse.Namespace) -> None:
    """The stages that ``a`` asks for; prints the figures as JSON."""
    if a.stage:
        print(json.dumps(stage(a.stage, a.out, a.rows[0], a.workers, a.lens_depths)))
        return
    if a.lens_only:
        print(json.dumps(lens_stages(a), indent=2))
        return
    if a.out.exists():
        shutil.rmtree(a.out)
    a.out.mkdir(parents=True)
    crops = [crop_stages(a, rows, a.out if len(a.rows) == 1 else a.out / f"rows_{rows}")
             for rows in a.rows]
    res = crops[0] if len(crops) == 1 else {"crops": crops, **marginal(crops)}
    if not a.skip_lens:
        res.update(lens_stages(a))
    print(json.dumps(res, indent=2))


def crop_stages(a, rows: int, out: Path) -> dict:
    """Every stage on one crop of ``rows`` full-width rows in ``out``, each in its own
    process; the crop's figures and its linear projection to the full sensor."""
    out.mkdir(parents=True, exist_ok=True)
    r0 = (FULL_H - rows) // 2
    (out / "bench.toml").write_text(CONFIG.format(depths=[140.0], r0=r0, r1=r0 + rows))
    res: dict = {"rows": rows, "width": 4096, "cores": os.cpu_count(),
                 "date": time.strftime("%Y-%m-%d"), "cold": a.cold}
    for name in ["capture", "acquire", "raw_read", "read", "reconstruct", "truth"]:
        if a.cold and name in COLD_STAGES:
            drop_page_cache()
        res.update(_run_stage(a, name, out, rows))
    scale = FULL_H / rows
    res["storage_cost_fraction"] = 1 - res["capture_fps_with_storage"] / res[
        "capture_fps_no_storage"]
    res["reconstruct_over_read"] = res["reconstruct_seconds"] / res["read_seconds"]
    res["reconstruct_over_raw_read"] = res["reconstruct_seconds"] / res["raw_read_seconds"]
    recon_full = res["reconstruct_seconds"] * scale
    read_full = res["read_seconds"] * scale
    acq_full = res["acquire_seconds"] * scale  # frame cost scales with the pixels rendered
    res["projected_six_depths_this_machine_h"] = 6 * (acq_full + recon_full) / 3600
    n = a.dask_workers
    res["projected_six_depths_reconstruct_dask_h"] = {
        "workers": n, "hours": 6 * max(read_full, recon_full * (os.cpu_count() or 1) / n)
        / 3600, "measured_engine": res["engine"]}
    return res


def marginal(crops: list[dict]) -> dict:
    """The full sensor projected from the smallest and the largest crop: per pixel the
    difference of their times over the difference of their pixels, plus the fixed cost
    (worker start-up, opening 1,177 files) the smaller crop leaves over."""
    lo, hi = min(crops, key=lambda c: c["rows"]), max(crops, key=lambda c: c["rows"])
    full = 4096 * FULL_H
    res: dict = {"marginal_between_rows": [lo["rows"], hi["rows"]]}
    for key in ("raw_read", "read", "reconstruct"):
        per_px = (hi[f"{key}_seconds"] - lo[f"{key}_seconds"]) / (4096 * (hi["rows"] -
                                                                           lo["rows"]))
        fixed = lo[f"{key}_seconds"] - per_px * 4096 * lo["rows"]
        res[f"{key}_us_per_px"] = per_px * 1e6
        res[f"{key}_projected_full_s"] = fixed + per_px * full
    res["reconstruct_over_read_projected"] = (res["reconstruct_projected_full_s"]
                                              / res["read_projected_full_s"])
    res["reconstruct_over_raw_read_projected"] = (res["reconstruct_projected_full_s"]
                                                  / res["raw_read_projected_full_s"])
    return res


def _run_stage(a, name: str, out: Path, rows: int) -> dict:
    cmd = [sys.executable, __file__, "--out", str(out), "--rows", str(rows), "--stage", name,
           "--lens-depths", str(a.lens_depths)] + (["--workers", str(a.workers)] if a.workers
                                                   else [])
    t = time.perf_counter()
    got = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if got.returncode:
        sys.exit(f"stage {name} failed:\n{got.stderr[-3000:]}")
    part = json.loads(got.stdout.strip().splitlines()[-1])
    print(f"{name} ({rows} rows): {time.perf_counter() - t:.1f} s {json.dumps(part)}",
          file=sys.stderr, flush=True)
    return part


def lens_stages(a) -> dict:
    """The lens with default settings (grid step 1, K = 32, streamed to its file) on LTC
    stores of ``--lens-depths`` depths at each ``--lens-rows`` crop height, each in its own
    process; projects the full sensor (six depths: time x 6 / depths) and its peak memory
    (a line through the measured peaks against rows, at 2168 rows)."""
    runs = []
    for rows in a.lens_rows:
        out = a.out / f"lens_{rows}"
        if out.exists():
            shutil.rmtree(out)
        out.mkdir(parents=True)
        r0 = (FULL_H - rows) // 2
        (out / "bench.toml").write_text(CONFIG.format(depths=[140.0], r0=r0, r1=r0 + rows))
        _run_stage(a, "lens_store", out, rows)
        part = _run_stage(a, "lens", out, rows)
        part["rows"] = rows
        runs.append(part)
        shutil.rmtree(out / "lens_ltc.zarr")
    res: dict = {"lens_depths": a.lens_depths, "lens_runs": runs}
    fast = max(runs, key=lambda q: q["rows"])
    res["lens_projected_full_s"] = (4096 * FULL_H / fast["lens_pixels_per_second"]
                                    * 6 / a.lens_depths)
    if len(runs) > 1:
        rows = np.array([q["rows"] for q in runs], dtype=float)
        mb = np.array([q["lens_peak_mb"] for q in runs])
        slope, icpt = np.polyfit(rows, mb, 1)
        res["lens_peak_mb_per_row"] = float(slope)
        res["lens_projected_full_peak_mb"] = float(icpt + slope * FULL_H)
    return res


if __name__ == "__main__":
    main()
