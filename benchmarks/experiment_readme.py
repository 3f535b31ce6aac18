"""Write an ``ltc experiment`` / ``ltc demo`` run's results into benchmarks/README.md, section
"Experiment: measured LTC vs Gaussian (ltc experiment)" (nothing else changes).

    .venv/bin/ltc demo --out out/demo                      # or: ltc experiment --out out/exp
    .venv/bin/python benchmarks/experiment_readme.py out/demo/results.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from station.experiment.report import tables
from station.experiment.rows import PositionRow

README = Path(__file__).resolve().with_name("README.md")

SECTION = "## Experiment: measured LTC vs Gaussian (ltc experiment)"


def section(res: dict, command: str) -> str:
    """The README section of one run's ``results.json``."""
    cfg, acc = res["config"], res["acceptance"]
    st = res["station"]
    rt = res["render_vs_pinhole"]
    lines = [SECTION, "",
             "The reference paper's experiment as one command (issue 16): `ltc experiment` / "
             "`ltc demo` (station/experiment/). Method and figures: the run's `report.md`; "
             "every number: its `results.json`.", "",
             f"    {command}", "",
             f"Run of {res['date']} on {res['machine']}; {res['seconds']['total']:.0f} s in all"
             + (f" (demo wall clock {res['seconds']['demo']:.0f} s)" if "demo" in res["seconds"]
                else "") + ".", "",
             f"- Rig `small_rig({cfg['scale']})`, cameras {cfg['camera_size'][0]} x "
             f"{cfg['camera_size'][1]} px; real = true lenses, {cfg['real_samples']} samples, "
             f"soft clipping edge; ltc = measured, K = {res['lenses'][0]['samples']} every "
             f"{cfg['lens_grid_step']} px; Gaussian sigma "
             + ", ".join(f"{x['gaussian_sigma_mm']:.3f}" for x in res["lenses"]) + " mm.",
             ]
    if st:
        lines.append("- Station per camera: " + "; ".join(
            f"camera {i} {s['total_s']:.0f} s (" + ", ".join(
                f"{k} {v:.0f} s" for k, v in s["seconds"].items() if v) + f"), optical centre "
            f"error {s['optical_centre_error_mm'] * 1e3:.0f} um" for i, s in enumerate(st)) + ".")
    w = acc["ltc_worst"]
    lines += [
        f"- ltc against real at every sphere and ball-bar position (|mean| <= 5 um, RMSE <= 10 "
        f"um, size within 20 um of real's on the pixels both clouds share): {'met' if acc['ltc_within_limits'] else 'NOT met at ' + ', '.join(acc['ltc_failing'])}; "
        f"worst |mean| {w['mean_um']:.1f} um, RMSE {w['rmse_um']:.1f} um, size {w['size_um']:.1f} um"
        + (f" (own points: {w['size_own_um']:.1f} um)." if "size_own_um" in w else "."),
        f"- Gaussian worse than ltc at every large-defocus position (|mean| and size): "
        f"{'yes' if acc['gaussian_worse_at_large'] else 'no at ' + ', '.join(acc['gaussian_not_worse'])}.",
        "- Render time against the pinhole (same positions): " + ", ".join(
            f"{k} {v:.1f} x" for k, v in rt.items()) + ".", ""]
    lines += tables([PositionRow.from_json(r) for r in res["rows"]])
    return "\n".join(lines) + "\n"


def write_readme(text: str, path: Path = README) -> None:
    """Replace the generated part of the section starting at ``SECTION`` (up to the next
    ``## `` heading or the first hand-written ``### `` subsection, whose headings are not
    among the generated tables') with ``text``, or insert it before "## Tracing throughput";
    nothing else changes (the hand-written analyses after the tables are kept)."""
    lines = path.read_text().splitlines()
    new = text.strip().splitlines() + [""]
    own = {ln for ln in new if ln.startswith("### ")}
    if SECTION in lines:
        start = lines.index(SECTION)
        end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")
                    or (lines[i].startswith("### ") and lines[i] not in own)), len(lines))
        lines[start:end] = new
    else:
        at = next((i for i, ln in enumerate(lines) if ln.startswith("## Tracing")), len(lines))
        lines[at:at] = new
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="results.json of the run")
    ap.add_argument("--command", default=".venv/bin/ltc demo --out out/demo",
                    help="the command that made it (shown in the section)")
    args = ap.parse_args(argv)
    res = json.loads(args.results.read_text())
    write_readme(section(res, args.command))
    print(f"README section '{SECTION}' written")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
