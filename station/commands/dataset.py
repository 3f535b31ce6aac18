"""Generate a fringe data set for learning with the virtual scanner.

Make --samples samples of a data-set config (TOML, docs/formats.md "Fringe data set"): per
sample and camera the fringe images, the numerator and denominator, background, modulation,
wrapped and absolute phase, fringe order, projector coordinates, depth, normals and a mask,
and the sample's scene; written into the zarr v3 data set --out. On every core by default,
in one process with --workers 1, on a local Dask cluster with --dask or an existing one with
--scheduler; every engine gives the same data set bit for bit. A killed run continues when
the same command is run again (finished samples are verified by checksum and kept).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from station.commands import at_least

OPTIONS = {"out": "data set folder (zarr v3) to create or continue",
           "force": "replace --out (a data set of another config, or anything else)",
           "json": None, "quiet": None, "workers": None, "dask": None,
           "scheduler": "compute on an existing Dask cluster (e.g. tcp://host:8786); --out "
                        "must be on a path every worker can write"}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path, help="data-set config (TOML)")
    p.add_argument("--samples", type=at_least(1), required=True, metavar="N",
                   help="number of samples (indices 0 .. N-1)")


def run(args: argparse.Namespace) -> dict:
    from station.dataset import generate_dataset

    args.resume_hint = (f"; continue with: ltc dataset {args.config} --out {args.out} "
                        f"--samples {args.samples}")
    return generate_dataset(args.config, args.out, args.samples, workers=args.workers,
                            dask=args.dask, scheduler=args.scheduler, progress=not args.quiet,
                            force=args.force).to_json()


def text(s: dict) -> str:
    sp = ", ".join(f"{k} {v}" for k, v in s["splits"].items())
    return (f"data set {s['out']}: {s['samples']} samples ({s['made']} made, {s['kept']} kept), "
            f"{sp}; {s['seconds']:.1f} s, {s['samples_per_second']:.2f} samples/s, "
            f"{s['engine']}; {s['bytes'] / 1e6:.1f} MB")
