"""``ltc cameras [--json]``: the cameras this machine can see, with what to put in ``[camera]``."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "cameras",
        help="list the GenICam (GigE Vision, USB3 Vision) and OpenCV cameras this machine sees",
        description="List the cameras this machine can open: GenICam devices found by Aravis "
        "(vendor, model, serial number, protocol, address; about 1 s of GigE Vision discovery) "
        "and Linux video devices OpenCV opens by index. Use a serial number as [camera] serial "
        "(kind = \"genicam\") or an index as [camera] source (kind = \"opencv\"). Exit code 1 "
        "when Aravis is not installed (the OpenCV devices are still listed).",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from drivers.camera import list_video_devices
    from drivers.genicam import AravisUnavailable, list_cameras

    problems = []
    try:
        genicam = list_cameras()
    except AravisUnavailable as exc:
        genicam = []
        problems.append(str(exc))
    opencv = list_video_devices()
    if args.json:
        print(json.dumps({"genicam": [dataclasses.asdict(c) for c in genicam],
                          "opencv": [dataclasses.asdict(d) for d in opencv],
                          "errors": problems}))
    else:
        print(f"GenICam cameras (Aravis): {len(genicam)}")
        for c in genicam:
            where = f" at {c.address}" if c.address else ""
            print(f"  serial = {c.serial!r}  device_id = {c.device_id!r}  "
                  f"({c.vendor} {c.model}, {c.protocol}{where})")
        print(f"OpenCV video devices: {len(opencv)}")
        for d in opencv:
            print(f"  source = {d.index}  ({d.path}, {d.name!r})")
    for problem in problems:
        print(f"ltc cameras: error: {' '.join(problem.split())}", file=sys.stderr)
    return 1 if problems else 0
