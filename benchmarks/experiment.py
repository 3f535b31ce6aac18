"""Write an ``ltc experiment`` / ``ltc demo`` run's results (its ``results.json``) into
``benchmarks/results/experiment.md``, rewritten whole.

    .venv/bin/ltc demo --out out/demo                      # or: ltc experiment --out out/exp
    .venv/bin/python benchmarks/experiment.py out/demo/results.json
    .venv/bin/python benchmarks/experiment.py out/paper/results.json --variant paper-size \
        --command ".venv/bin/ltc experiment --paper-size --out out/paper"

``--variant NAME`` writes ``benchmarks/results/experiment-NAME.md`` instead (the
``--paper-size`` run keeps its own file).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from station.experiment.report import pose_table, tables
from station.experiment.rows import PositionRow

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import write_results  # noqa: E402

TITLE = "Experiment: measured LTC against Gaussian and pinhole (ltc experiment / ltc demo)"


def section(res: dict, command: str) -> str:
    """The results file's body for one run's ``results.json``."""
    cfg, acc = res["config"], res["acceptance"]
    st = res["station"]
    rt = res["render_vs_pinhole"]
    lines = ["The reference paper's experiment as one command: `ltc experiment` / "
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
    ltc_ok = ("met" if acc["ltc_within_limits"]
              else "NOT met at " + ", ".join(acc["ltc_failing"]))
    gauss_ok = ("yes" if acc["gaussian_worse_at_large"]
                else "no at " + ", ".join(acc["gaussian_not_worse"]))
    own = f" (own points: {w['size_own_um']:.1f} um)." if "size_own_um" in w else "."
    lines += [
        f"- ltc against real at every sphere and ball-bar position (|mean| <= 5 um, RMSE <= 10 "
        f"um, size within 20 um of real's on the pixels both clouds share): {ltc_ok}; "
        f"worst |mean| {w['mean_um']:.1f} um, RMSE {w['rmse_um']:.1f} um, "
        f"size {w['size_um']:.1f} um{own}",
        f"- Gaussian worse than ltc at every large-defocus position (|mean| and size): "
        f"{gauss_ok}.",
        "- Render time against the pinhole (same positions): " + ", ".join(
            f"{k} {v:.1f} x" for k, v in rt.items()) + ".", ""]
    rows = [PositionRow.from_json(r) for r in res["rows"]]
    lines += tables(rows)
    pose = pose_table(rows)  # runs through the real-scan folder (rows with "validation")
    if pose:
        lines += ["", *pose]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="results.json of the run")
    ap.add_argument("--command", default=".venv/bin/ltc demo --out out/demo",
                    help="the command that made it (shown in the results file)")
    ap.add_argument("--variant", help="write benchmarks/results/experiment-VARIANT.md")
    args = ap.parse_args(argv)
    res = json.loads(args.results.read_text())
    path = write_results(__file__, TITLE + (f", {args.variant}" if args.variant else ""),
                         section(res, args.command), variant=args.variant)
    print(f"{path} written")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
