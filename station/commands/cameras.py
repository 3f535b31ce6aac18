"""List the GenICam (GigE Vision, USB3 Vision) and OpenCV cameras this machine sees.

List the cameras this machine can open: GenICam devices found by Aravis (vendor, model, serial
number, protocol, address; about 1 s of GigE Vision discovery) and Linux video devices OpenCV
opens by index. Use a serial number as [camera] serial (kind = "genicam") or an index as
[camera] source (kind = "opencv"). Exit code 1 when Aravis is not installed (the OpenCV
devices are still listed).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

OPTIONS = {"json": None}


def run(args: argparse.Namespace) -> dict:
    from drivers.camera import list_video_devices
    from drivers.genicam import AravisUnavailable, list_cameras

    problems = []
    try:
        genicam = list_cameras()
    except AravisUnavailable as exc:
        genicam = []
        problems.append(" ".join(str(exc).split()))
    for problem in problems:
        print(f"ltc cameras: error: {problem}", file=sys.stderr)
    return {"genicam": [dataclasses.asdict(c) for c in genicam],
            "opencv": [dataclasses.asdict(d) for d in list_video_devices()],
            "errors": problems, "ok": not problems}


def text(r: dict) -> str:
    lines = [f"GenICam cameras (Aravis): {len(r['genicam'])}"]
    lines += [f"  serial = {c['serial']!r}  device_id = {c['device_id']!r}  ({c['vendor']} "
              f"{c['model']}, {c['protocol']}" + (f" at {c['address']})" if c["address"] else ")")
              for c in r["genicam"]]
    lines.append(f"OpenCV video devices: {len(r['opencv'])}")
    lines += [f"  source = {d['index']}  ({d['path']}, {d['name']!r})" for d in r["opencv"]]
    return "\n".join(lines)
