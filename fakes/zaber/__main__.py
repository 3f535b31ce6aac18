"""``python -m fakes.zaber``: serve a fake Zaber stage on a pseudo-terminal until Ctrl-C."""

from __future__ import annotations

import argparse
import signal
import time

from fakes.zaber.device import FakeZaberDevice
from fakes.zaber.pty import FakeZaberPty


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m fakes.zaber", description=__doc__)
    parser.add_argument("--address", type=int, default=1, help="device address 1-99")
    parser.add_argument("--limit-max", type=int, default=1_066_666, help="travel in microsteps")
    parser.add_argument("--position", type=int, default=0, help="power-up position, microsteps")
    parser.add_argument("--checksums", action="store_true", help="replies carry :CC checksums")
    args = parser.parse_args(argv)
    # Ctrl-C (SIGINT) stops the server even when the parent started us with SIGINT ignored
    # (a background job, or a test process whose worker pools set it so)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    device = FakeZaberDevice(
        address=args.address,
        limit_max=args.limit_max,
        position=args.position,
        reply_checksums=args.checksums,
    )
    try:
        with FakeZaberPty(device) as server:
            print(f"fake Zaber device {args.address} on {server.port}", flush=True)
            print("  try: python -m serial.tools.miniterm --eol LF", server.port, "115200")
            print(f"  then type: /{args.address} 1 get pos")
            print(f"  or: ZaberStage({server.port!r}, microstep_um=0.047625, travel_mm=(0, 50))")
            print("  Ctrl-C stops", flush=True)
            while True:  # short sleeps: a SIGINT landing just before one is seen within 0.2 s
                time.sleep(0.2)
    except KeyboardInterrupt:
        print("stopped")


if __name__ == "__main__":
    main()
