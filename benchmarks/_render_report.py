"""What ``render_vs_mitsuba.py`` makes of its cases: the image comparison, the ratios, and the
report (markdown, printed and put into ``benchmarks/README.md``)."""

from __future__ import annotations

import datetime
from pathlib import Path

import numpy as np
from _bench_scene import (
    STEPS,
    BenchConfig,
    agreement,
    bench_lens,
    bench_rig,
    bench_scene,
    blur_radius_px,
    comparison_mask,
    machine,
    phase_rms_rad,
    surface_points,
)
from _mitsuba_scene import to_our_radiance

EDGE_MARGIN_PX = 2  # comparison mask: this far from silhouettes, shadow edges and the projector border
LABELS = {"ours-pinhole": "ours, pinhole (1 ray/px)", "mitsuba-pinhole": "Mitsuba, pinhole ({spp} spp)",
          "mitsuba-pinhole-1spp": "Mitsuba, pinhole (1 spp)", "ours-thin": "ours, thin lens ({k} rays/px)",
          "mitsuba-thin": "Mitsuba, thin lens ({k} spp)"}
COMPARED = (("pinhole", ("mitsuba-pinhole", "mitsuba-pinhole-1spp")), ("thin", ("mitsuba-thin",)))
SPEED = (("ours-pinhole", "mitsuba-pinhole-1spp"), ("ours-pinhole", "mitsuba-pinhole"), ("ours-thin",
                                                                                         "mitsuba-thin"))


def compare(cfg: BenchConfig, out_dir: Path) -> dict:
    """Agreement of Mitsuba's images (converted to our radiance) with ours on lit pixels away
    from edges, overall and per scene object, from the ``<case>.npz`` files in ``out_dir``."""
    rig = bench_rig(cfg)
    cam, proj = rig.cameras[0], rig.projector
    names = [o.name for o in bench_scene().objects]
    out = {}
    for lens_kind, cases in COMPARED:
        ours = np.load(out_dir / f"ours-{lens_kind}.npz")
        rad, depth, obj = ours["radiance"].astype(np.float64), ours["depth"], ours["object_id"]
        margin = EDGE_MARGIN_PX + int(np.ceil(blur_radius_px(cam, bench_lens(lens_kind, cfg), depth)))
        white = 2.0 * rad[:STEPS].mean(axis=0)  # the 4 shifts of one period average to A = white / 2
        mask = comparison_mask(ours["lit"], obj, margin) & (white > 0)
        pts = surface_points(cam, depth)
        for case in cases:
            m = np.load(out_dir / f"{case}.npz")
            theirs = to_our_radiance(m["radiance"], pts, proj, float(m["scale"]))
            a = agreement(rad, theirs, white, mask)
            a["lit_pixels"] = int(ours["lit"].sum())
            a["phase_rms_rad"] = phase_rms_rad(rad[-STEPS:], theirs[-STEPS:], mask)
            a["by_object"] = {n: agreement(rad, theirs, white, mask & (obj == i)) for i,
                              n in enumerate(names)}
            out[case] = a
    return out


def _median(runs: list[dict], key: str) -> float:
    return float(np.median([r[key] for r in runs]))


def summarise(cfg: BenchConfig, res: dict, agree: dict) -> dict:
    """Medians, ratios and agreement of one run as a JSON-able dict."""
    s = {"date": datetime.date.today().isoformat(), "machine": machine(), "config": cfg.model_dump()}
    cases = {}
    for name, r in res.items():
        if name == "ours-extras":
            continue
        cases[name] = dict(median_s=_median(r["runs"], "seconds"), runs_s=[x["seconds"] for x in r["runs"]],
                           setup_s=r["setup"]["setup_s"], peak_rss_mb=r["memory"]["peak_rss_mb"],
                           rss_imports_mb=r["setup"]["rss_imports_mb"])
        if name.startswith("ours"):
            cases[name]["breakdown_s"] = {k: _median(r["runs"], k) for k in ("trace_s", "gather_s",
                                                                             "response_s")}
            cases[name]["rays"] = r["runs"][-1]["rays"]
    s["cases"] = cases
    s["speed_ratios"] = {f"{theirs} / {ours}": cases[theirs]["median_s"] / cases[ours]["median_s"]
                         for ours, theirs in SPEED if ours in cases and theirs in cases}
    s["agreement"] = agree
    if "ours-extras" in res:
        runs = res["ours-extras"]["runs"]
        ex = {}
        for kind in ("pinhole", "thin"):
            ours_r, raw_r = _median(runs, f"{kind}_ours_rays_per_s"), _median(runs, f"{kind}_raw_rays_per_s")
            ex[kind] = dict(rays=runs[-1][f"{kind}_ours_rays"], raw_rays=runs[-1][f"{kind}_raw_rays"],
                            ours_rays_per_s=ours_r, raw_rays_per_s=raw_r, throughput_fraction=ours_r / raw_r,
                            patterns_1_s=_median(runs, f"{kind}_patterns_1_s"),
                            patterns_24_s=_median(runs, f"{kind}_patterns_24_s"))
            ex[kind]["patterns_24_over_1"] = ex[kind]["patterns_24_s"] / ex[kind]["patterns_1_s"]
        s["extras"] = ex
    return s


def _pct(x: float, digits: int = 3) -> str:
    return f"{100 * x:.{digits}f} %"


def report_markdown(s: dict) -> str:
    """The run's results as markdown (the README's "Results" subsection)."""
    cfg = BenchConfig(**s["config"])
    lab = {k: v.format(spp=cfg.pinhole_spp, k=cfg.thin_samples) for k, v in LABELS.items()}
    rig = bench_rig(cfg)
    (cw, ch), (pw, ph) = rig.cameras[0].size, rig.projector.size
    L = [f"Run of {s['date']} on {s['machine']}; the whole run took {s.get('wall_s', 0.0):.0f} s.", "",
         f"Camera {cw} x {ch}, projector {pw} x {ph}, 12 images, median of {cfg.repeats} repeats; "
         f"Mitsuba variant `{cfg.variant}`, `{cfg.sampler}` sampler.", ""]
    if s["cases"]:
        L += ["| case | 12 images, s (median) | repeats, s | setup, s | peak memory, MB |",
              "|---|---|---|---|---|"]
        for name, c in s["cases"].items():
            runs = ", ".join(f"{x:.3g}" for x in c["runs_s"])
            L.append(f"| {lab[name]} | {c['median_s']:.2f} | {runs} | {c['setup_s']:.1f} "
                     f"| {c['peak_rss_mb']:.0f} |")
        L.append("")
        for name in ("ours-pinhole", "ours-thin"):
            if name in s["cases"]:
                b = s["cases"][name]["breakdown_s"]
                L.append(f"- {lab[name]}: trace {b['trace_s']:.2f} s, gather {b['gather_s']:.2f} s, "
                         f"camera response {b['response_s']:.2f} s; "
                         f"{s['cases'][name]['rays'] / 1e6:.1f} M camera rays.")
        L.append("")
    if s["speed_ratios"]:
        L += ["Time ratio, Mitsuba / ours (target >= 3 at equal samples):", ""]
        for k, v in s["speed_ratios"].items():
            a, b = k.split(" / ")
            L.append(f"- {lab[a]} vs {lab[b]}: **{v:.1f}x**")
        L.append("")
    if s["agreement"]:
        L += ["Agreement on lit pixels away from edges, |Mitsuba - ours| / (the pixel's white level) over "
              "all 12 images, Mitsuba converted to our radiance (target: pinhole within 1 % of white):", "",
              f"| Mitsuba case | pixels | median | 99th pct | max | mean signed | values > 1 % | phase RMS, "
              f"period {pw / 64:g} px | sphere: 99th pct, max | plane: 99th pct, max |",
              "|---|---|---|---|---|---|---|---|---|---|"]
        for name, a in s["agreement"].items():
            by = [f"{_pct(o['p99'])}, {_pct(o['max'], 2)}" for o in a["by_object"].values()]
            L.append(f"| {lab[name]} | {a['pixels']} of {a['lit_pixels']} lit | {_pct(a['median'])} | "
                     f"{_pct(a['p99'])} | {_pct(a['max'], 2)} | {100 * a['bias']:+.4f} % | "
                     f"{_pct(a['over_1pct'], 4)} | {a['phase_rms_rad']:.4f} rad | {' | '.join(by)} |")
        L.append("")
    if "extras" in s:
        L += ["| ours | camera rays | ours, M rays/s | raw embreex, M rays/s | fraction (target >= 0.8) | "
              "1 pattern, s | 24 patterns, s | 24 / 1 (target <= 1.5) |", "|---|---|---|---|---|---|---|---|"]
        for kind, e in s["extras"].items():
            what = "pinhole, whole frame" if kind == "pinhole" else \
                f"thin lens, {100 * cfg.band_fraction:g} % of the rows"
            L.append(f"| {what} | {e['rays'] / 1e6:.2f} M | {e['ours_rays_per_s'] / 1e6:.2f} | "
                     f"{e['raw_rays_per_s'] / 1e6:.2f} | **{e['throughput_fraction']:.2f}** | "
                     f"{e['patterns_1_s']:.2f} | {e['patterns_24_s']:.2f} | "
                     f"**{e['patterns_24_over_1']:.2f}** |")
        L.append("")
    return "\n".join(L)
