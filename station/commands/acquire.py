"""Measure: show the Fourier and localisation patterns at every depth, capture them.

Run an acquisition into a run store (zarr). Every frame is written durably; an interrupted run
continues with --resume at the first frame not done. One writer at a time: the store's lock
file names its holder.
"""

from __future__ import annotations

import argparse
import logging

from station.errors import UsageError

OPTIONS = {"config": None, "out": "run store to create (RUN.zarr)",
           "force": "replace the run store in --out with a new run (the old one stays until the "
                    "new one is complete; only a run store is replaced; never one a live "
                    "writer holds)",
           "json": None, "quiet": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--resume", action="store_true",
                   help="finish the run in --out (its config must be the same)")


def run(args: argparse.Namespace) -> dict:
    from station.acquisition.backend import preflight
    from station.api import acquire, load_config
    from station.outputs import RUN_STORE, check_output, staged

    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, format="ltc acquire: %(levelname)s: %(message)s")
    args.resume_hint = (f"; finish with: ltc acquire {args.config} --out {args.out} --resume")
    config = load_config(args.config)
    preflight(config, str(args.config))
    if args.out.exists() and not args.resume and not args.force:
        raise UsageError(f"--out {args.out} exists; pass --resume to finish that run, "
                         "--force to replace it with a new run, or choose another path")
    if args.resume:
        summary = acquire(config, args.out, resume=True, progress=not args.quiet,
                          force=args.force)
        return {**summary, "out": str(args.out)}
    out = check_output(args.out, args.force, kind=RUN_STORE, inputs=[args.config],
                       parent_must_exist=True)
    if out.exists():  # staged() refuses a store a live writer holds
        args.resume_hint = (f"; the old run store {out} is unchanged; start again with: "
                            f"ltc acquire {args.config} --out {out} --force")
    with staged(out, RUN_STORE) as target:
        summary = acquire(config, target, resume=False, progress=not args.quiet)
    return {**summary, "run": str(out), "out": str(out)}


def text(s: dict) -> str:
    return (f"ltc acquire: {s['status']}: {s['frames_written']} frames in {s['seconds']:.1f} s "
            f"({s['frames_per_second']:.1f}/s) -> {s['out']}; retries {s['retries'] or 'none'}; "
            f"saturated frames {s['saturated_frames']}"
            + (f"; recaptured {len(s['frames_recaptured'])} damaged frame(s) "
               f"{[tuple(f) for f in s['frames_recaptured']]}"
               if s.get("frames_recaptured") else ""))
