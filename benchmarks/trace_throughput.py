"""Tracing throughput: our whole ``trace_camera`` against raw embreex on the same rays.

"Raw embreex on the same rays" is the Embree work the job inherently needs, and nothing else:
the same primary rays cast with ``scene.run(o, d, output=1)`` (first hit with distance,
barycentrics and normal) plus the same shadow rays cast as occlusion queries
(``query="OCCLUDED"`` with their far distances), in the same chunks, on the same number of
threads. The rays are exactly the ones our tracer casts: one untimed ``trace_camera`` runs with
the scene's Embree object wrapped in a recorder that keeps a copy of every query; the timed raw
run replays those queries. The primary rays are also checked against ``sim.render.trace.camera_rays``.

"Ours" is the wall time of the whole ``trace_camera`` call (ray generation, Embree, float64 hit
refinement, shading, shadow rays, projector coordinates, bookkeeping into the ``Transport``).
The throughput fraction is ``raw seconds / our seconds`` (equal rays), target >= 0.8.

Scene: ``_bench_scene.py`` (the 50.8 mm sphere at 760 mm and a plane 100 mm behind it,
2048 x 1088 camera, 1920 x 1080 projector 200 mm to the side). Cases: pinhole over the whole
frame; the 64-sample ideal thin lens (f/2.8, focused at 760 mm) over a band of rows through the
sphere (``--band-fraction``, 1/8 by default: 18 M camera rays). Ours and raw take turns repeat by
repeat; medians of ``--repeats`` are reported.

    .venv/bin/python benchmarks/trace_throughput.py                # about 3 minutes on 2 cores
    .venv/bin/python benchmarks/trace_throughput.py --scale 0.25 --repeats 1   # smoke run
    .venv/bin/python benchmarks/trace_throughput.py --write-results
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _bench_scene import (  # noqa: E402
    BenchConfig, band_pixels, bench_lens, bench_rig, bench_scene, machine,
)
from _results import command_line, write_results  # noqa: E402

from sim.render.trace import TraceGeometry, camera_rays, trace_camera  # noqa: E402

TITLE = "Tracing throughput: our trace_camera against raw embreex on the same rays"
TARGET = 0.8


class RecordingScene:
    """Stands in for an embreex scene: forwards ``run`` and keeps a copy of every query."""

    def __init__(self, scene) -> None:
        self.scene = scene
        self.queries: list[tuple[np.ndarray, np.ndarray, dict]] = []
        self._lock = threading.Lock()

    def run(self, origins, directions, **kw):
        q = (np.array(origins), np.array(directions),
             {k: (np.array(v) if isinstance(v, np.ndarray) else v) for k, v in kw.items()})
        with self._lock:
            self.queries.append(q)
        return self.scene.run(origins, directions, **kw)


def record_queries(geom: TraceGeometry, trace) -> list[tuple[np.ndarray, np.ndarray, dict]]:
    """Every Embree query ``trace()`` makes on ``geom``, in order of arrival."""
    scene = geom.embree
    rec = RecordingScene(scene)
    geom.__dict__["embree"] = rec  # the cached_property's slot
    try:
        trace()
    finally:
        geom.__dict__["embree"] = scene
    return rec.queries


def timed(fn) -> tuple[float, float, object]:
    """Wall and CPU seconds (all threads of this process) of ``fn()``, and its result."""
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return time.perf_counter() - w0, time.process_time() - c0, out


def replay(geom: TraceGeometry, queries: list, threads: int) -> None:
    """Replay ``queries`` on the scene with ``threads`` Python threads."""
    scene = geom.embree
    with ThreadPoolExecutor(threads) as ex:
        list(ex.map(lambda q: scene.run(q[0], q[1], **q[2]), queries))


def _is_primary(q: tuple) -> bool:
    return q[2].get("query", "INTERSECT") != "OCCLUDED"


def summarise_queries(queries: list) -> dict:
    """Counts of the recorded primary and shadow rays, and of calls; every primary query must
    have asked for ``output=1`` (what the comparison assumes)."""
    primary = [q for q in queries if _is_primary(q)]
    if any(not q[2].get("output") for q in primary):
        raise RuntimeError("trace_throughput: a primary query without output=1 was recorded")
    return {"primary": sum(len(q[0]) for q in primary),
            "shadow": sum(len(q[0]) for q in queries if not _is_primary(q)),
            "calls": len(queries)}


def check_primaries(queries: list, cam, lens, pix) -> None:
    """The recorded primary rays are ``camera_rays``: same count, same sums of every
    coordinate (chunks arrive in any order)."""
    o, d = camera_rays(cam, lens, pix)
    prim = [q for q in queries if _is_primary(q)]
    n = sum(len(q[0]) for q in prim)
    if n != len(o):
        raise RuntimeError(f"trace_throughput: {n} primary rays recorded, camera_rays gives "
                           f"{len(o)}")
    for col, ref, what in ((0, o, "origins"), (1, d, "directions")):
        got = sum(q[col].sum(axis=0, dtype=np.float64) for q in prim)
        want = ref.astype(np.float32).sum(axis=0, dtype=np.float64)
        if not np.allclose(got, want, rtol=1e-9, atol=1e-6 * len(ref)):
            raise RuntimeError(f"trace_throughput: recorded primary {what} differ from "
                               f"camera_rays (sums {got} vs {want})")


def run_case(name: str, geom, cam, projector, lens, pix, threads: int, repeats: int) -> dict:
    """Record our queries, then time ours and the raw replay, taking turns; medians."""
    def ours():
        return trace_camera(geom, cam, projector, lens, pixels=pix, threads=threads)

    queries = record_queries(geom, ours)  # also the warm-up of ours
    counts = summarise_queries(queries)
    check_primaries(queries, cam, lens, pix)
    replay(geom, queries[: max(1, len(queries) // 8)], threads)  # warm-up
    t = {"ours": ([], []), "raw": ([], [])}
    for r in range(repeats):
        for who in (("ours", "raw") if r % 2 == 0 else ("raw", "ours")):
            job = ours if who == "ours" else (lambda: replay(geom, queries, threads))
            wall, cpu, _ = timed(job)
            t[who][0].append(wall)
            t[who][1].append(cpu)
        print(f"  {name} repeat {r + 1}: ours {t['ours'][0][-1]:.3f} s "
              f"({t['ours'][1][-1]:.3f} s CPU), raw {t['raw'][0][-1]:.3f} s "
              f"({t['raw'][1][-1]:.3f} s CPU)", flush=True)
    med = {f"{who}_{kind}_s": statistics.median(t[who][i]) for who in t
           for i, kind in enumerate(("wall", "cpu"))}
    return {"case": name, "pixels": len(pix), **counts, "times": t, **med,
            "fraction": med["raw_wall_s"] / med["ours_wall_s"],
            "fraction_cpu": med["raw_cpu_s"] / med["ours_cpu_s"],
            "ours_mrays_per_s": counts["primary"] / med["ours_wall_s"] / 1e6,
            "raw_mrays_per_s": counts["primary"] / med["raw_wall_s"] / 1e6}


def report_markdown(s: dict) -> str:
    """The results table of section "Tracing throughput"."""
    head = (f"Measured {s['date']} on {s['machine']}; {s['threads']} threads, scale "
            f"{s['scale']}, medians of {s['repeats']} repeats.")
    columns = ("| case | camera rays | shadow rays | ours, s | raw embreex, s | ours, M camera "
               f"rays/s | fraction, wall (target >= {TARGET}) | fraction, CPU time |")
    lines = [head, "", columns, "|---|---|---|---|---|---|---|---|"]
    for c in s["cases"]:
        lines.append(f"| {c['case']} | {c['primary'] / 1e6:.2f} M | {c['shadow'] / 1e6:.2f} M | "
                     f"{c['ours_wall_s']:.2f} | {c['raw_wall_s']:.2f} | "
                     f"{c['ours_mrays_per_s']:.2f} | **{c['fraction']:.2f}** | "
                     f"{c['fraction_cpu']:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark; returns the results (also printed, and written where asked)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scale", type=float, default=1.0,
                    help="image sizes times this (smoke runs: 0.25)")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats per case (medians)")
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="threads, both sides")
    ap.add_argument("--samples", type=int, default=64, help="thin-lens rays per pixel")
    ap.add_argument("--band-fraction", type=float, default=0.125,
                    help="thin lens: fraction of the camera rows traced (a band through the "
                    "sphere)")
    ap.add_argument("--cases", default="pinhole,thin", help="comma-separated: pinhole, thin")
    ap.add_argument("--json", type=Path, help="write the results as JSON")
    ap.add_argument("--write-results", action="store_true",
                    help="rewrite benchmarks/results/trace_throughput.md with this run")
    args = ap.parse_args(argv)
    names = args.cases.split(",")
    if unknown := sorted(set(names) - {"pinhole", "thin"}):
        raise ValueError(f"--cases: unknown case(s) {unknown}; expected pinhole, thin")
    cfg = BenchConfig(scale=args.scale, repeats=args.repeats, thin_samples=args.samples,
                      band_fraction=args.band_fraction, mitsuba=False)
    rig = bench_rig(cfg)
    cam = rig.cameras[0]
    geom = bench_scene().trace_geometry()
    _ = geom.embree
    w, h = cam.size
    subsets = {"pinhole": (bench_lens("pinhole", cfg), np.arange(w * h, dtype=np.int64)),
               "thin": (bench_lens("thin", cfg), band_pixels(cam, cfg.band_fraction))}
    cases = []
    for name in names:
        lens, pix = subsets[name]
        print(f"{name}: {len(pix)} pixels", flush=True)
        cases.append(run_case(name, geom, cam, rig.projector, lens, pix, args.threads,
                              args.repeats))
    s = {"date": datetime.date.today().isoformat(), "machine": machine(), "threads": args.threads,
         "scale": args.scale, "repeats": args.repeats, "cases": cases}
    text = report_markdown(s)
    print("\n" + text)
    if args.json:
        args.json.write_text(json.dumps(s, indent=2))
    if args.write_results:
        write_results(__file__, TITLE, text, command=command_line(["trace_throughput.py", *(
            argv if argv is not None else sys.argv[1:])]))
    return s


if __name__ == "__main__":
    main()
