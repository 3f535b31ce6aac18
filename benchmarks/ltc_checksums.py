"""What verifying the LTC store's chunk checksums costs ``ltc lens``.

The lens derivation (default settings: every pixel a node, K = 32, streamed to its file) runs
on the same LTC store read three ways in the same run, alternating, best of ``--repeats``:

- ``zarr``: the arrays read through zarr, as before chunks carried checksums;
- ``unchecked``: the store's own chunk reader without the crc32c checks;
- ``checked``: what ``ltc lens`` does now (``open_ltc_volume``): every chunk of a done tile
  verified against ``tile_crc32c``.

Stores: the fake bench of the lens tests (40 x 30 camera, 5 depths, P = 24) and the 64-row
full-width crop of the full-size synthetic bench (4096 x 64, 2 depths, P = 24; the crop
machinery of ``benchmarks/full_size.py``). Target: checked at most 10 % over zarr.

    python benchmarks/ltc_checksums.py [--repeats 3] [--crop-rows 64] [--workers N] \
        [--write-results]

Prints the table; ``--write-results`` rewrites ``benchmarks/results/ltc_checksums.md``.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

MODES = ("zarr", "unchecked", "checked")


def volume(path: Path, mode: str):
    """The store's ``LtcVolume`` read the way ``mode`` says."""
    import zarr

    from station.ltc.checked import checked_arrays
    from station.ltc.store import LtcVolume, open_ltc_volume

    if mode == "checked":
        return open_ltc_volume(path)
    v = open_ltc_volume(path)
    g = zarr.open_group(str(path), mode="r")
    arrays = ({n: g[n] for n in ("ltc", "origin", "gain", "noise")} if mode == "zarr"
              else checked_arrays(path, g, verify=False))
    return LtcVolume(ltc=arrays["ltc"], origin=arrays["origin"], gain=arrays["gain"],
                     noise=arrays["noise"], depths_mm=v.depths_mm, pitch_mm=v.pitch_mm,
                     camera_matrix=v.camera_matrix, dist_coeffs=v.dist_coeffs, name=v.name)


def lens_seconds(path: Path, mode: str, out: Path, workers: int | None,
                 focus_mm: float | None) -> tuple[float, float]:
    """(CPU seconds of this process, wall seconds) of one lens derivation; with one worker
    (the default) all the work is this process's, and its CPU time is what a loaded machine
    distorts least."""
    from station.compute import Engine
    from station.lens.derive import derive_lens
    from station.lens.geometry import LensFitConfig

    cfg = LensFitConfig(focus_distance_mm=focus_mm)
    t, c = time.perf_counter(), time.process_time()
    v = volume(path, mode)
    with Engine(workers) as engine:
        derive_lens(v, cfg, None, None, progress=False, engine=engine, out=out)
    cpu, wall = time.process_time() - c, time.perf_counter() - t
    out.unlink()
    return cpu, wall


def fake_store(root: Path) -> tuple[Path, float | None, str]:
    from ltc_stores import write_true_ltc_store

    from fakes.bench import BenchConfig, FakeBench

    bench = FakeBench(BenchConfig.small(lcd_size=(120, 96), lcd_distance_at_zero_mm=100.0,
                                        pupil_samples=150, subpixels=1))
    path = write_true_ltc_store(root / "fake.zarr", bench, [0.0, 30.0, 60.0, 250.0, 290.0],
                                period=24)
    return path, None, "fake bench, 40 x 30 camera, 5 depths, P = 24"


def crop_store(root: Path, rows: int) -> tuple[Path, float | None, str]:
    import full_size

    from station.api import load_config

    r0 = (full_size.FULL_H - rows) // 2
    cfg_path = root / "bench.toml"
    cfg_path.write_text(full_size.CONFIG.format(depths=[140.0], r0=r0, r1=r0 + rows))
    cfg = load_config(cfg_path)
    path = root / "crop.zarr"
    full_size.write_true_store(cfg, path)
    focus = full_size._bench(cfg).config.focus_distance_mm
    return path, focus, f"full-size crop, 4096 x {rows}, 2 depths, P = 24"


def measure(path: Path, focus: float | None, repeats: int, workers: int | None,
            root: Path) -> dict[str, float]:
    """Best CPU seconds per mode (and best wall seconds as ``<mode>_wall``)."""
    best = {m: float("inf") for m in MODES} | {m + "_wall": float("inf") for m in MODES}
    for i in range(repeats):
        order = MODES if i % 2 == 0 else MODES[::-1]
        for mode in order:
            cpu, wall = lens_seconds(path, mode, root / f"lens_{mode}.npz", workers, focus)
            best[mode] = min(best[mode], cpu)
            best[mode + "_wall"] = min(best[mode + "_wall"], wall)
            print(f"  {mode:10s} CPU {cpu:8.2f} s, wall {wall:8.2f} s", flush=True)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--crop-rows", type=int, default=64, help="0: skip the full-size crop")
    ap.add_argument("--crop-repeats", type=int, default=1)
    ap.add_argument("--workers", type=int, default=1,
                    help="lens worker processes (default 1: CPU time then counts all work)")
    ap.add_argument("--dir", type=Path, default=None, help="scratch folder (default: /tmp)")
    ap.add_argument("--write-results", action="store_true",
                    help="rewrite benchmarks/results/ltc_checksums.md whole")
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(dir=a.dir) as tmp:
        root = Path(tmp)
        cases = [(fake_store, (), a.repeats)]
        if a.crop_rows:
            cases.append((crop_store, (a.crop_rows,), a.crop_repeats))
        for make, args, repeats in cases:
            sub = root / make.__name__
            sub.mkdir()
            path, focus, what = make(sub, *args)
            print(what, flush=True)
            best = measure(path, focus, repeats, a.workers, sub)
            rows.append((what, repeats, best))
            shutil.rmtree(sub)
    lines = [
        "# LTC chunk checksums: cost in `ltc lens`",
        "",
        f"`python benchmarks/ltc_checksums.py` on {time.strftime('%Y-%m-%d')}, "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, workers "
        f"{a.workers}; lens with default settings, best CPU seconds of the repeats (wall "
        "seconds beside), modes alternating in one run. Target: checked at most 10 % over "
        "zarr.",
        "",
        "| store | repeats | zarr CPU s (wall) | unchecked CPU s (wall) | checked CPU s (wall) | "
        "checked / zarr | checked / unchecked |",
        "|---|---|---|---|---|---|---|",
    ]
    for what, repeats, b in rows:
        cells = " | ".join(f"{b[m]:.2f} ({b[m + '_wall']:.2f})" for m in MODES)
        lines.append(f"| {what} | {repeats} | {cells} | {b['checked'] / b['zarr']:.3f} | "
                     f"{b['checked'] / b['unchecked']:.3f} |")
    print("\n".join(lines))
    if a.write_results:
        from _results import command_line, write_results

        write_results(__file__, lines[0].lstrip("# "), "\n".join(lines[2:]),
                      command=command_line())


if __name__ == "__main__":
    main()
