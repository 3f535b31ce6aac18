"""Render benchmark: our Embree renderer against Mitsuba 3 and against raw embreex.

The scene, devices and patterns are in ``_bench_scene.py``; the Mitsuba side and how its
conventions are matched to ours in ``_mitsuba_scene.py``; its latest results in
``benchmarks/results/render_vs_mitsuba.md``; how to read them in ``benchmarks/README.md``.

Every case runs in its own worker process (so each has its own peak memory), and the cases
compared with each other take turns repeat by repeat (so load from other processes on the
machine hits them alike); times are medians over the repeats.

Cases: ours and Mitsuba rendering the 12 fringe images with a pinhole (ours 1 ray per pixel;
Mitsuba at ``--pinhole-spp`` and at 1 spp) and with a 64-sample thin lens; ours' tracing
throughput against raw embreex on the same rays (the primary and shadow queries our tracer
makes, recorded and replayed: ``trace_throughput.py``); ours' cost of 24 patterns
against 1.

Run (``scripts/bench_setup.sh`` installs Mitsuba and prints the LLVM path)::

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so \\
        .venv/bin/python benchmarks/render_vs_mitsuba.py --write-results
    .venv/bin/python benchmarks/render_vs_mitsuba.py --scale 0.25 --repeats 1   # smoke run
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _bench_scene import (  # noqa: E402
    BenchConfig, band_pixels, bench_lens, bench_patterns, bench_rig, bench_scene,
)
from _mitsuba_scene import irradiance_scale_at, unavailable_reason  # noqa: E402
from _render_report import compare, report_markdown, summarise  # noqa: E402
from _results import command_line, write_results  # noqa: E402

from sim.render.images import (  # noqa: E402
    CameraResponse, ProjectorResponse, RenderSettings, camera_response, project_patterns, render,
    render_camera,
)
from trace_throughput import record_queries, replay, summarise_queries  # noqa: E402

from sim.render.trace import trace_camera  # noqa: E402

REPLY = "@@bench "
TITLE = "Rendering: ours against Mitsuba 3 and raw embreex"
RESULTS_JSON = "results.json"
SETTINGS = RenderSettings(projector=ProjectorResponse(input_bits=None),
                          camera=CameraResponse(quantize=False))
GROUPS = (("ours-pinhole", "mitsuba-pinhole", "mitsuba-pinhole-1spp"),
          ("ours-thin", "mitsuba-thin"), ("ours-extras",))


def rss_mb() -> float:
    """Resident memory of this process now, MB."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3  # kB on Linux


# ------------------------------------------------------------------------------- worker cases


def warm_up(geom, rig, lens) -> None:
    """Build the BVH and whatever our tracer compiles or caches on first use (as Mitsuba's
    warm-up image compiles its kernels): trace and render a few pixels, and digitise them as
    ``render_camera`` does."""
    tr = trace_camera(geom, rig.cameras[0], rig.projector, lens, pixels=np.arange(256))
    camera_response(render(tr, bench_patterns(rig)[1][:1], SETTINGS), SETTINGS.camera)


class OursCase:
    """Our renderer: 12 images of one camera, trace once plus one gather per pattern. Each
    repeat renders into the arrays of the one before (``render_camera(out=...)``), as a
    sequence of renders would, and as Mitsuba's side stacks its images into the same array."""

    def __init__(self, cfg: BenchConfig, lens_kind: str) -> None:
        t0 = time.perf_counter()
        self.rig = bench_rig(cfg)
        self.lens = bench_lens(lens_kind, cfg)
        self.geom = bench_scene().trace_geometry()
        self.patterns = bench_patterns(self.rig)[1]
        warm_up(self.geom, self.rig, self.lens)
        self.setup_s = time.perf_counter() - t0
        self.result = None

    def run(self, repeat: int) -> dict:
        t0 = time.perf_counter()
        cols = project_patterns(self.patterns, SETTINGS.projector)
        self.result = render_camera(self.geom, self.rig, 0, self.lens, cols, SETTINGS.camera, None,
                                    out=self.result)
        return dict(seconds=time.perf_counter() - t0, rays=self.result.n_rays, **self.result.timings)

    def save(self, path: Path) -> None:
        r = self.result
        np.savez(path, radiance=r.radiance, depth=r.depth, lit=r.lit, object_id=r.object_id)


class MitsubaCase:
    """Mitsuba: one render per pattern image (the texture changes, the scene is traced anew)."""

    def __init__(self, cfg: BenchConfig, lens_kind: str, spp: int) -> None:
        from _mitsuba_scene import MitsubaFringeRenderer

        t0 = time.perf_counter()
        rig = bench_rig(cfg)
        self.scale = irradiance_scale_at(rig.projector, np.zeros(3))
        self.renderer = MitsubaFringeRenderer(bench_scene(), rig.cameras[0], rig.projector,
                                              bench_lens(lens_kind, cfg), spp, cfg.variant,
                                              cfg.sampler, self.scale)
        self.patterns = bench_patterns(rig)[1]
        self.renderer.render(self.patterns[0], seed=10**6)  # compiles the kernels
        self.setup_s = time.perf_counter() - t0
        self.images = None

    def run(self, repeat: int) -> dict:
        t0 = time.perf_counter()
        self.images = self.renderer.render_all(self.patterns, seed=1000 * repeat, out=self.images)
        return dict(seconds=time.perf_counter() - t0)

    def save(self, path: Path) -> None:
        np.savez(path, radiance=self.images, scale=np.array(self.scale))


class ExtrasCase:
    """Ours' tracing throughput against raw embreex on the same rays (pinhole: the whole frame;
    thin lens: a band of rows), and the cost of 24 patterns against 1 (trace included)."""

    def __init__(self, cfg: BenchConfig) -> None:
        t0 = time.perf_counter()
        self.rig = bench_rig(cfg)
        self.cam = self.rig.cameras[0]
        self.geom = bench_scene().trace_geometry()
        w, h = self.cam.size
        self.subsets = {"pinhole": (bench_lens("pinhole", cfg), np.arange(w * h, dtype=np.int64)),
                        "thin": (bench_lens("thin", cfg), band_pixels(self.cam, cfg.band_fraction))}
        self.queries = {}
        for kind, (lens, pix) in self.subsets.items():  # exactly the queries trace_camera makes
            self.queries[kind] = record_queries(self.geom, lambda: trace_camera(
                self.geom, self.cam, self.rig.projector, lens, pixels=pix))
        self.one = bench_patterns(self.rig)[1][:1]
        self.many = bench_patterns(self.rig, "both")[1]
        for lens, _ in self.subsets.values():
            warm_up(self.geom, self.rig, lens)
        self.setup_s = time.perf_counter() - t0

    def run(self, repeat: int) -> dict:
        out = {}
        for kind, (lens, pix) in self.subsets.items():
            tr = trace_camera(self.geom, self.cam, self.rig.projector, lens, pixels=pix)
            t0 = time.perf_counter()
            replay(self.geom, self.queries[kind], os.cpu_count() or 1)
            raw_s = time.perf_counter() - t0
            n_raw = summarise_queries(self.queries[kind])["primary"]
            out[f"{kind}_ours_rays"], out[f"{kind}_raw_rays"] = tr.rays, n_raw
            out[f"{kind}_ours_rays_per_s"] = tr.rays / tr.seconds
            out[f"{kind}_raw_rays_per_s"] = n_raw / raw_s
            for label, pats in (("1", self.one), ("24", self.many)):
                t0 = time.perf_counter()
                tr = trace_camera(self.geom, self.cam, self.rig.projector, lens, pixels=pix)
                render(tr, pats, SETTINGS)
                out[f"{kind}_patterns_{label}_s"] = time.perf_counter() - t0
        return out

    def save(self, path: Path) -> None:
        pass


def make_case(name: str, cfg: BenchConfig):
    if name == "ours-extras":
        return ExtrasCase(cfg)
    who, lens_kind, *rest = name.split("-")
    if who == "ours":
        return OursCase(cfg, lens_kind)
    spp = 1 if rest == ["1spp"] else (cfg.pinhole_spp if lens_kind == "pinhole" else cfg.thin_samples)
    return MitsubaCase(cfg, lens_kind, spp)


def reply(payload: dict) -> None:
    print(REPLY + json.dumps(payload), flush=True)


def worker_main(name: str, cfg: BenchConfig) -> None:
    """Set the case up, then answer ``run`` and ``save`` commands (JSON lines on stdin)."""
    base = rss_mb()
    case = make_case(name, cfg)
    reply(dict(setup_s=case.setup_s, rss_imports_mb=base, rss_setup_mb=rss_mb()))
    for line in sys.stdin:
        cmd = json.loads(line)
        if cmd["cmd"] == "run":
            reply(case.run(cmd["repeat"]))
        elif cmd["cmd"] == "save":
            case.save(Path(cmd["path"]))
            reply(dict(peak_rss_mb=peak_rss_mb()))
            return


# ------------------------------------------------------------------------------- orchestration


class Worker:
    """A worker process of one case, driven by JSON lines."""

    def __init__(self, name: str, cfg: BenchConfig) -> None:
        self.name = name
        self.proc = subprocess.Popen([sys.executable, __file__, "--worker", name, "--config", cfg.model_dump_json()],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.ready = self._answer()

    def _answer(self) -> dict:
        for line in self.proc.stdout:
            if line.startswith(REPLY):
                return json.loads(line[len(REPLY):])
            sys.stderr.write(f"[{self.name}] {line}")
        code = self.proc.wait()
        raise RuntimeError(f"benchmark worker '{self.name}' ended (exit code {code}) without answering; "
                           "its error is printed above")

    def call(self, **cmd) -> dict:
        self.proc.stdin.write(json.dumps(cmd) + "\n")
        self.proc.stdin.flush()
        return self._answer()


def run_cases(cfg: BenchConfig, names: list[str], out_dir: Path) -> dict:
    """Run every group of cases, repeats interleaved within a group; returns per case its setup,
    runs and peak memory, and saves its images to ``out_dir / <case>.npz``."""
    results = {}
    for group in GROUPS:
        members = [n for n in group if n in names]
        workers = []
        for n in members:
            print(f"setting up {n} ...", flush=True)
            workers.append(Worker(n, cfg))
        for rep in range(cfg.repeats):
            for w in workers:
                r = w.call(cmd="run", repeat=rep)
                took = f"{r['seconds']:.2f} s" if "seconds" in r else \
                    f"pinhole trace {r['pinhole_ours_rays_per_s'] / 1e6:.2f} M rays/s"
                print(f"  {w.name} repeat {rep + 1}/{cfg.repeats}: {took}", flush=True)
                results.setdefault(w.name, dict(setup=w.ready, runs=[]))["runs"].append(r)
        for w in workers:
            results[w.name]["memory"] = w.call(cmd="save", path=str(out_dir / f"{w.name}.npz"))
            w.proc.wait()
    return results


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--config", help=argparse.SUPPRESS)
    ap.add_argument("--scale", type=float, default=1.0, help="image sizes times this (smoke runs: 0.25)")
    ap.add_argument("--repeats", type=int, default=5, help="timed repeats per case (median reported)")
    ap.add_argument("--pinhole-spp", type=int, default=64,
                    help="Mitsuba pinhole samples per pixel for the agreement (1 spp is timed too)")
    ap.add_argument("--thin-samples", type=int, default=64, help="thin-lens samples per pixel, both renderers")
    ap.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (scalar_rgb needs no LLVM)")
    ap.add_argument("--sampler", default="stratified", help="Mitsuba sampler")
    ap.add_argument("--no-mitsuba", action="store_true", help="only our cases")
    ap.add_argument("--save", type=Path, help="keep every case's images (npz) and the results in this folder")
    ap.add_argument("--reanalyse", type=Path, help="no rendering: redo the comparison and the report "
                    "of the run saved in this folder")
    ap.add_argument("--json", type=Path, help="write the results as JSON")
    ap.add_argument("--write-results", action="store_true",
                    help="rewrite benchmarks/results/render_vs_mitsuba.md with this run")
    args = ap.parse_args(argv)
    if args.worker:
        worker_main(args.worker, BenchConfig.model_validate_json(args.config))
        return 0
    cfg = BenchConfig(scale=args.scale, repeats=args.repeats, pinhole_spp=args.pinhole_spp,
                      thin_samples=args.thin_samples, variant=args.variant, sampler=args.sampler,
                      mitsuba=not args.no_mitsuba)
    if cfg.mitsuba and not args.reanalyse and (why := unavailable_reason(cfg.variant)):
        print(f"Mitsuba cases skipped: {why}", flush=True)
        cfg = cfg.model_copy(update={"mitsuba": False})
    if args.reanalyse:
        if not (args.reanalyse / RESULTS_JSON).is_file():
            raise FileNotFoundError(f"--reanalyse {args.reanalyse}: no {RESULTS_JSON} there; give the "
                                    "folder of an earlier run with --save")
        s = json.loads((args.reanalyse / RESULTS_JSON).read_text())
        cfg = BenchConfig(**s["config"])
        s["agreement"] = compare(cfg, args.reanalyse) if cfg.mitsuba else {}
    else:
        s = run(cfg, args.save)
    text = report_markdown(s)
    print("\n" + text)
    if args.json:
        args.json.write_text(json.dumps(s, indent=2))
    if args.write_results:
        write_results(__file__, TITLE, text, command=command_line())
    return 0


def run(cfg: BenchConfig, save: Path | None) -> dict:
    """Every case, then the comparison; the summary (``_render_report.summarise``). With
    ``save``, the images and the summary stay in that folder (``--reanalyse`` reads them)."""
    names = [n for g in GROUPS for n in g if cfg.mitsuba or not n.startswith("mitsuba")]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="render_bench_") as tmp:
        out_dir = save or Path(tmp)
        out_dir.mkdir(parents=True, exist_ok=True)
        res = run_cases(cfg, names, out_dir)
        agree = compare(cfg, out_dir) if cfg.mitsuba else {}
        s = summarise(cfg, res, agree)
        s["wall_s"] = time.perf_counter() - t0
        (out_dir / RESULTS_JSON).write_text(json.dumps(s, indent=2))
    return s


if __name__ == "__main__":
    sys.exit(main())
