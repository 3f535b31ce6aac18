"""Data-set generation throughput at 960 x 960: ours against raw embreex (and Mitsuba 3).

Per sample: two 960 x 960 cameras, 3-frequency 4-step phase shift (12 images per camera),
8-bit images with shot and read noise, every label and truth map, written compressed into
the zarr data set. Cases: pinhole lenses; a measured lens (a synthetic space-variant lens
file, 16 aperture samples per node, its pupil growing from the centre to the corners).

- Ours: ``sim.dataset`` generating the sample (trace once, gather 12 patterns, response,
  labels, truth maps) plus writing it (``write_sample``), wall time, one process (the
  renderer's threads on every core).
- Raw embreex: every Embree query the sample's rendering makes (primary rays with
  ``output=1``, shadow rays as occlusion queries; both cameras), recorded during one untimed
  generation and replayed on the same number of threads: the CPU limit of tracing those rays.
  The fraction is raw seconds / our seconds (target >= 0.7 for the pinhole).
- Mitsuba 3 (when installed): the same sample (a sphere before a backdrop plane; no
  distortion, the benchmark renderer's limits) rendered at one sample per pixel (ours: one
  ray per pixel) for the 12 patterns on both cameras: its time against our whole sample.
- Scaling: ``station.dataset.generate_dataset`` with 1 and 2 worker processes.
- Bytes per sample: one sample written with several lossless zarr codecs.
- Projection: 10,000 samples on 2 cores and on N Dask workers (per-core rate times N).

    nice .venv/bin/python benchmarks/dataset_throughput.py            # a few minutes
    nice .venv/bin/python benchmarks/dataset_throughput.py --size 240 --samples 1   # smoke
"""

from __future__ import annotations

import argparse
import datetime
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _bench_scene import machine  # noqa: E402
from trace_throughput import record_queries, replay, summarise_queries  # noqa: E402

from sim.dataset.config import Storage, parse_config  # noqa: E402
from sim.dataset.generate import render_sample, scene_geometry  # noqa: E402
from sim.dataset.randomise import config_rig, draw_scene  # noqa: E402
from sim.dataset.store import read_sample, write_group, write_sample  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "dataset_throughput.md"
TARGET = 0.7
IMAGES_PER_CAMERA = 12
CODECS = [("none", 0), ("zstd", 1), ("zstd", 3), ("zstd", 9), ("blosc_zstd", 3),
          ("blosc_lz4", 5), ("gzip", 6)]


def measured_lens_file(path: Path, size: tuple[int, int]) -> Path:
    """A synthetic measured lens for a camera of ``size``: 5 x 5 nodes, 16 samples each, the
    pupil radius 1.0 mm at the centre growing to 1.6 mm at the corners, focused at 760 mm."""
    from sim.optics.lens import sunflower_disk
    from sim.optics.measured_lens import MeasuredLens, save_lens

    w, h = size
    nu, nv = np.linspace(0, w - 1, 5), np.linspace(0, h - 1, 5)
    r = 1.0 + 0.6 * np.hypot(*np.meshgrid((nu - nu.mean()) / nu.max(),
                                          (nv - nv.mean()) / nv.max())) / np.sqrt(0.5)
    disk = sunflower_disk(16)
    lens = MeasuredLens(focus_distance_mm=760.0, optical_centre_mm=np.zeros(3), camera_size=size,
                        node_u=nu, node_v=nv, aperture_x_mm=r[..., None] * disk[:, 0],
                        aperture_y_mm=r[..., None] * disk[:, 1],
                        weights=np.full((5, 5, 16), 1 / 16), transmittance=np.ones((5, 5)))
    return save_lens(path, lens)


def config(size: int, lens: dict, *, sphere_only: bool = False, distortion: bool = True,
           storage: tuple[str, int] = ("zstd", 3)):
    objects = {"size_mm": [80.0, 140.0]}
    placement = {}
    if sphere_only:
        objects["families"] = {"sphere": 1.0}
        placement = {"backdrop_probability": 1.0}
    return parse_config({
        "seed": 1,
        "rig": {"builtin": {"camera_size_px": [size, size], "camera_scale": 0.5 * size / 960,
                            "distortion": distortion}},
        "objects": objects, "placement": placement, "lenses": [[lens], [lens]],
        "camera": {"shot_noise": True, "read_noise_e": [2.0, 8.0], "bit_depth": 8},
        "patterns": [{"kind": "phase_shift", "steps": [4], "periods_px": [[2048.0, 128.0, 16.0]]}],
        "storage": {"codec": storage[0], "level": storage[1]},
    })


def tree_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())


def time_case(name: str, cfg, indices: list[int], threads: int, tmp: Path) -> dict:
    """Ours (generate + write) against raw embreex on the same sample's queries, per sample."""
    rig = config_rig(cfg)
    root = tmp / f"{name}.zarr"
    (root / "samples").mkdir(parents=True)
    ours, gen, raw, rays, stages = [], [], [], [], []
    for i in indices:
        scene = draw_scene(cfg, rig, i)
        geom = scene_geometry(scene.objects)
        queries = record_queries(geom, lambda s=scene, g=geom: render_sample(s, g))  # warm-up
        counts = summarise_queries(queries)
        tm: dict[str, float] = {}
        t0 = time.perf_counter()
        sample = render_sample(draw_scene(cfg, rig, i), timings=tm)
        t1 = time.perf_counter()
        write_sample(root, sample, cfg.storage)
        t2 = time.perf_counter()
        replay(geom, queries, threads)
        t3 = time.perf_counter()
        ours.append(t2 - t0)
        gen.append(t1 - t0)
        raw.append(t3 - t2)
        rays.append(counts)
        tm["write_s"] = t2 - t1
        tm["draw_s"] = t1 - t0 - sum(tm[k] for k in ("geometry_s", "render_s", "labels_s",
                                                      "noise_s"))
        stages.append(tm)
        print(f"  {name} sample {i}: ours {t2 - t0:.2f} s (generate {t1 - t0:.2f}: render "
              f"{tm['render_s']:.2f} + noise {tm['noise_s']:.2f} + labels {tm['labels_s']:.2f}"
              f"; write {t2 - t1:.2f}), raw embreex {t3 - t2:.2f} s, "
              f"{counts['primary'] / 1e6:.1f} M camera + {counts['shadow'] / 1e6:.1f} M shadow "
              "rays", flush=True)
    images = 2 * IMAGES_PER_CAMERA
    o, g, r = statistics.median(ours), statistics.median(gen), statistics.median(raw)
    st = {k: statistics.median(t[k] for t in stages) for k in stages[0]}
    rs = statistics.median(t["render_s"] + t["noise_s"] for t in stages)
    return {"case": name, "samples": len(indices), "ours_s": o, "generate_s": g, "raw_s": r,
            "render_stage_s": rs, "stages": st,
            "images_per_s": images / o, "raw_images_per_s": images / r,
            "fraction": r / o, "fraction_generate": r / g, "fraction_render": r / rs,
            "camera_rays_m": statistics.median(c["primary"] for c in rays) / 1e6,
            "shadow_rays_m": statistics.median(c["shadow"] for c in rays) / 1e6,
            "bytes": tree_bytes(root) / len(indices)}


def codecs_case(cfg, tmp: Path) -> list[dict]:
    """One sample written with each codec: bytes, write and read seconds."""
    rig = config_rig(cfg)
    sample = render_sample(draw_scene(cfg, rig, 0))
    digest = sample.checksum()
    rows = []
    for codec, level in CODECS:
        path = tmp / f"codec-{codec}-{level}"
        t0 = time.perf_counter()
        write_group(path, sample, digest, Storage(codec=codec, level=level))
        t1 = time.perf_counter()
        back = read_sample(path)
        t2 = time.perf_counter()
        assert back.verify(), f"{codec} {level}: read back differs"
        rows.append({"codec": codec, "level": level, "bytes": tree_bytes(path),
                     "write_s": t1 - t0, "read_s": t2 - t1})
        shutil.rmtree(path)
        print(f"  codec {codec} {level}: {rows[-1]['bytes'] / 1e6:.1f} MB, write "
              f"{t1 - t0:.2f} s, read {t2 - t1:.2f} s", flush=True)
    raw = rows[0]["bytes"]
    for r in rows:
        r["ratio"] = raw / r["bytes"]
    return rows


def scaling_case(cfg, n: int, tmp: Path) -> dict:
    """Samples per second of ``generate_dataset`` with 1 and 2 workers: over a run of ``n``
    samples (start-up included: the worker processes import and load their kernels), and at
    the margin (a run of ``2 n`` minus the run of ``n``: the steady rate)."""
    from station.dataset import generate_dataset

    out = {}
    for workers in (1, 2):
        runs = [generate_dataset(cfg, tmp / f"scale-{workers}-{k}.zarr", k, workers=workers,
                                 progress=False) for k in (n, 2 * n)]
        extra_s = runs[1].seconds - runs[0].seconds
        marginal = n / extra_s if extra_s > 0 else float("nan")  # nan: lost in the noise
        out[workers] = (runs[0].samples_per_second, marginal)
        print(f"  {workers} worker(s): {runs[0].samples_per_second:.3f} samples/s over {n}, "
              f"{marginal:.3f} at the margin", flush=True)
    return {"samples": n, "rate_1": out[1][0], "rate_2": out[2][0],
            "speedup": out[2][0] / out[1][0], "marginal_1": out[1][1],
            "marginal_2": out[2][1], "marginal_speedup": out[2][1] / out[1][1]}


def mitsuba_case(size: int, tmp: Path) -> dict | None:
    """The same sample (sphere and backdrop) in Mitsuba 3 at 1 spp against our whole sample."""
    from _mitsuba_scene import MitsubaFringeRenderer, unavailable_reason

    variant = next((v for v in ("llvm_ad_rgb", "scalar_rgb") if unavailable_reason(v) is None),
                   None)
    if variant is None:
        print(f"  Mitsuba: {unavailable_reason('scalar_rgb')}", flush=True)
        return {"skipped": unavailable_reason("scalar_rgb")}
    from sim.render.scene import PlaneObject, Scene, SphereObject

    cfg = config(size, {"kind": "pinhole"}, sphere_only=True, distortion=False)
    rig = config_rig(cfg)
    scene = draw_scene(cfg, rig, 0)
    sph, plane = scene.objects
    ours_scene = Scene(objects=[
        SphereObject(diameter_mm=sph.size_mm, albedo=sph.albedo, pose=sph.pose),
        PlaneObject(size_mm=plane.extent_mm, albedo=plane.albedo, pose=plane.pose)])
    patterns = scene.patterns.images(tuple(rig.projector.size))
    render_sample(scene)  # warm-up
    tm: dict[str, float] = {}
    t0 = time.perf_counter()
    sample = render_sample(scene, timings=tm)
    images = tm["geometry_s"] + tm["render_s"]  # the noise-free images, as Mitsuba's
    root = tmp / "mitsuba.zarr"
    (root / "samples").mkdir(parents=True)
    write_sample(root, sample, cfg.storage)
    ours = time.perf_counter() - t0
    mts = 0.0
    for cam in rig.cameras:
        r = MitsubaFringeRenderer(ours_scene, cam, rig.projector, scene.lenses[0], spp=1,
                                  variant=variant)
        r.render(patterns[0])  # warm-up (JIT)
        t0 = time.perf_counter()
        r.render_all(patterns)
        mts += time.perf_counter() - t0
    print(f"  Mitsuba {variant}: {mts:.2f} s for 2 x 12 images at 1 spp; ours {ours:.2f} s "
          f"for the whole sample, {images:.2f} s for its noise-free images", flush=True)
    return {"variant": variant, "mitsuba_s": mts, "ours_s": ours, "ratio": mts / ours,
            "ours_images_s": images, "images_ratio": mts / images}


def report(s: dict) -> str:
    lines = [
        "# Data-set generation throughput",
        "",
        f"`benchmarks/dataset_throughput.py`, {s['date']} on {s['machine']}; cameras "
        f"{s['size']} x {s['size']}, 3-frequency 4-step phase shift (12 images per camera, 2 "
        f"cameras), 8-bit with shot and read noise, every label and truth map, codec "
        f"{s['codec']}; {s['threads']} threads; medians over {s['samples']} samples per case; "
        f"load average {s['load'][0]:.1f} at the start, {s['load'][1]:.1f} at the end (the "
        "machine is shared: compare ratios within a row, not absolute times across runs). "
        "Raw = the sample's Embree queries replayed (the CPU limit of its tracing). Ours, in "
        "three stages: (a) end to end, generate + write the sample; (b) generate only (scene, "
        "render, noise, labels and truth maps, in memory); (c) the render stage alone, what "
        "raw embreex is compared to: trace, the 12 patterns gathered, the sensor's noise, i.e. "
        "the images. Fraction = raw / ours.",
        "",
        "| case | camera rays | shadow rays | raw embreex, s | (a) end to end, s | (b) generate, "
        "s | (c) render stage, s | (a) raw / ours (target >= "
        f"{TARGET} pinhole) | (b) raw / generate | (c) raw / render stage | images/s (a) | "
        "MB/sample |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in s["cases"]:
        lines.append(f"| {c['case']} | {c['camera_rays_m']:.2f} M | {c['shadow_rays_m']:.2f} M | "
                     f"{c['raw_s']:.2f} | {c['ours_s']:.2f} | {c['generate_s']:.2f} | "
                     f"{c['render_stage_s']:.2f} | **{c['fraction']:.2f}** | "
                     f"**{c['fraction_generate']:.2f}** | **{c['fraction_render']:.2f}** | "
                     f"{c['images_per_s']:.1f} | {c['bytes'] / 1e6:.1f} |")
    lines += ["", "Where the time goes (medians, s per sample; render = trace + gather + the "
              "noise-free response; labels = the Feng/Zuo labels and the truth maps; write = "
              "sha256, zstd and the durable write with its fsyncs):", "",
              "| case | scene draw | geometry | trace | gather | render | noise | labels | "
              "write |", "|---|---|---|---|---|---|---|---|---|"]
    for c in s["cases"]:
        t = c["stages"]
        lines.append(f"| {c['case']} | {t['draw_s']:.2f} | {t['geometry_s']:.2f} | "
                     f"{t['trace_s']:.2f} | {t['gather_s']:.2f} | {t['render_s']:.2f} | "
                     f"{t['noise_s']:.2f} | {t['labels_s']:.2f} | {t['write_s']:.2f} |")
    m = s.get("mitsuba")
    lines += ["", "## Mitsuba 3", ""]
    if m is None or "skipped" in (m or {}):
        lines.append(f"Not measured: {(m or {}).get('skipped', 'not run')}.")
    else:
        lines.append(f"Same sample at {s['mitsuba_size']} x {s['mitsuba_size']} (sphere before a "
                     "backdrop plane, pinhole, no distortion), "
                     f"Mitsuba `{m['variant']}` at 1 sample per pixel for 2 x 12 images: "
                     f"{m['mitsuba_s']:.2f} s; our whole sample (images, labels, truth maps, "
                     f"written): {m['ours_s']:.2f} s; Mitsuba / ours = **{m['ratio']:.2f}**; "
                     f"our noise-free images alone (geometry and render stage): "
                     f"{m['ours_images_s']:.2f} s, Mitsuba / ours = "
                     f"**{m['images_ratio']:.2f}**.")
    sc = s["scaling"]
    lines += ["", "## Scaling (pinhole, `generate_dataset`)", "",
              f"Over a run of {sc['samples']} samples (worker start-up included) and at the "
              f"margin (a run of {2 * sc['samples']} minus the run of {sc['samples']}: the "
              f"steady rate); load average {s['scaling_load'][0]:.1f} before, "
              f"{s['scaling_load'][1]:.1f} after.", "",
              "| workers | samples/s (run) | images/s (run) | samples/s (margin) | images/s "
              "(margin) |", "|---|---|---|---|---|",
              f"| 1 | {sc['rate_1']:.3f} | {sc['rate_1'] * 24:.1f} | {sc['marginal_1']:.3f} | "
              f"{sc['marginal_1'] * 24:.1f} |",
              f"| 2 | {sc['rate_2']:.3f} | {sc['rate_2'] * 24:.1f} | {sc['marginal_2']:.3f} | "
              f"{sc['marginal_2'] * 24:.1f} |",
              "", f"Speed-up 1 -> 2 workers: **{sc['speedup']:.2f}** over the run, "
              f"**{sc['marginal_speedup']:.2f}** at the margin."]
    lines += ["", "## Bytes per sample (one pinhole sample, lossless)", "",
              "| codec | level | MB | ratio | write, s | uncompressed MB/s written | read, s |",
              "|---|---|---|---|---|---|---|"]
    raw_mb = s["codecs"][0]["bytes"] / 1e6
    for r in s["codecs"]:
        lines.append(f"| {r['codec']} | {r['level']} | {r['bytes'] / 1e6:.1f} | "
                     f"{r['ratio']:.2f} | {r['write_s']:.2f} | {raw_mb / r['write_s']:.0f} | "
                     f"{r['read_s']:.2f} |")
    rate2 = sc["marginal_2"] if sc["marginal_2"] > sc["rate_2"] else sc["rate_2"]  # nan: run
    per_core = rate2 / 2
    lines += ["", "## Projected time for 10,000 samples", "",
              f"2 cores (2 workers, measured rate {rate2:.3f} samples/s): "
              f"**{10000 / rate2 / 3600:.1f} h**. N Dask workers of one core each at the "
              f"measured per-core rate ({per_core:.3f} samples/s), scaling assumed linear: "
              + ", ".join(f"N = {n}: {10000 / (n * per_core) / 3600:.2f} h" for n in (8, 32, 128))
              + "."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=960, help="camera width and height, px")
    ap.add_argument("--samples", type=int, default=2, help="samples per case (medians)")
    ap.add_argument("--scaling-samples", type=int, default=8,
                    help="samples of the shorter scaling run (the longer one makes twice as many)")
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--no-mitsuba", action="store_true")
    ap.add_argument("--mitsuba-size", type=int, default=480,
                    help="camera size of the Mitsuba comparison (its scalar variant is slow)")
    ap.add_argument("--no-write", action="store_true", help="do not rewrite the results file")
    args = ap.parse_args(argv)
    load0 = os.getloadavg()[0]
    tmp = Path(tempfile.mkdtemp(prefix="dataset-bench-"))
    try:
        lens_path = measured_lens_file(tmp / "lens.npz", (args.size, args.size))
        idx = list(range(args.samples))
        cases = []
        print("pinhole", flush=True)
        pin = config(args.size, {"kind": "pinhole"})
        cases.append(time_case("pinhole", pin, idx, args.threads, tmp))
        print("measured lens", flush=True)
        cases.append(time_case("measured lens", config(args.size, {"kind": "measured",
                                                                    "path": str(lens_path)}),
                               idx, args.threads, tmp))
        print("codecs", flush=True)
        codecs = codecs_case(pin, tmp)
        print("scaling", flush=True)
        scaling_load = os.getloadavg()[0]
        scaling = scaling_case(pin, args.scaling_samples, tmp)
        scaling_load = (scaling_load, os.getloadavg()[0])
        mts = None if args.no_mitsuba else mitsuba_case(args.mitsuba_size, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    s = {"date": datetime.date.today().isoformat(), "machine": machine(), "size": args.size,
         "threads": args.threads, "samples": args.samples, "mitsuba_size": args.mitsuba_size,
         "codec": f"{pin.storage.codec} {pin.storage.level}",
         "load": (load0, os.getloadavg()[0]), "cases": cases, "codecs": codecs,
         "scaling": scaling, "scaling_load": scaling_load, "mitsuba": mts}
    text = report(s)
    print(text)
    if not args.no_write:
        RESULTS.parent.mkdir(exist_ok=True)
        RESULTS.write_text(text)
    return s


if __name__ == "__main__":
    main()
