"""Check a run store, an LTC store or a lens file for damage; changes nothing.

Reads every checksummed byte: each done frame of a run store against its crc32c, each done
tile's chunks of an LTC store against the recorded checksums, each member of a lens file
against its CRC-32 and its fields. Prints one line per damaged item, naming it, and exits 1
when anything is damaged. What is merely not written yet (a run or a reconstruction to
finish with --resume) is reported, not counted as damage.
"""

from __future__ import annotations

import argparse
from pathlib import Path

OPTIONS = {"json": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("store", type=Path, metavar="STORE",
                   help="run store, LTC store (zarr folders) or lens file (.npz)")


def run(args: argparse.Namespace) -> dict:
    from station.api import verify_store

    return verify_store(args.store).to_json()


def text(r: dict) -> str:
    head = (f"{r['path']}: {r['kind']}, {r['checked']} item(s) checked: "
            + ("no damage" if r["ok"] else f"{len(r['damaged'])} damaged"))
    return "\n".join([head, *(f"  damaged: {m}" for m in r["damaged"]),
                      *(f"  incomplete: {m}" for m in r["incomplete"])])
