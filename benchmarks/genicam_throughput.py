"""GenICam capture throughput: our GenICamCamera against a minimal raw Aravis loop.

Both read the same free-running stream from Aravis's fake GigE Vision camera on loopback
(tests/gv_fake.py, in a child process), with the same ROI, pixel format, frame rate setting,
number of stream buffers and frame count. "Raw" is the least a Python program must do per
frame: ``timeout_pop_buffer``, check the status, ``get_image_data`` into a numpy array,
``push_buffer``. "Ours" is ``GenICamCamera.capture()`` in free run (status and frame-id checks,
deadline, copy into a writeable array, Frame). Frames/s is counted from the first frame to the
last; ours and raw take turns, medians of ``--repeats``. Target: ours / raw >= 0.9.

    .venv/bin/python benchmarks/genicam_throughput.py
    .venv/bin/python benchmarks/genicam_throughput.py --frames 200 --repeats 1   # smoke run
"""

from __future__ import annotations

import argparse
import datetime
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "benchmarks")]

from drivers.genicam import CameraFrameError, GenICamCamera, _aravis  # noqa: E402
from _results import captured, command_line, text_block, write_results  # noqa: E402
from gv_fake import running_fake_camera  # noqa: E402


def run_ours(address: str, roi: tuple[int, int, int, int], fmt: str, rate: float, n: int,
             n_buffers: int) -> tuple[float, int, float]:
    """Good frames/s of GenICamCamera.capture() in free run, bad frames (incomplete or lost:
    raised as CameraFrameError), CPU ms per frame of this process."""
    with GenICamCamera(address, roi=roi, pixel_format=fmt, trigger=None, frame_rate_hz=rate,
                       n_buffers=n_buffers) as camera:
        camera.capture(timeout=2.0)  # acquisition running, first frame in
        bad = 0
        cpu, start = time.process_time(), time.perf_counter()
        for _ in range(n):
            try:
                camera.capture(timeout=2.0)
            except CameraFrameError:
                bad += 1
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu
        return (n - bad) / wall, bad, 1000 * cpu / n


def run_raw(address: str, roi: tuple[int, int, int, int], fmt: str, rate: float, n: int,
            n_buffers: int) -> tuple[float, int, float]:
    """Good frames/s of a minimal PyGObject Aravis loop, bad frames (status not SUCCESS or a
    frame-id gap), CPU ms per frame of this process."""
    arv = _aravis()
    camera = arv.Camera.new(address)
    camera.set_acquisition_mode(arv.AcquisitionMode.CONTINUOUS)
    camera.set_pixel_format_from_string(fmt)
    camera.set_region(*roi)
    camera.set_frame_rate(rate)
    camera.clear_triggers()
    stream = camera.create_stream(None, None)
    for _ in range(n_buffers):
        stream.push_buffer(arv.Buffer.new_allocate(camera.get_payload()))
    dtype = np.uint8 if fmt == "Mono8" else np.uint16
    camera.start_acquisition()
    try:
        buffer = stream.timeout_pop_buffer(2_000_000)
        stream.push_buffer(buffer)
        bad, last = 0, buffer.get_frame_id()
        cpu, start = time.process_time(), time.perf_counter()
        for _ in range(n):
            buffer = stream.timeout_pop_buffer(2_000_000)
            frame_id = buffer.get_frame_id()
            if buffer.get_status() == arv.BufferStatus.SUCCESS and frame_id in (last + 1, 1):
                np.frombuffer(buffer.get_image_data(), dtype).reshape(
                    buffer.get_image_height(), buffer.get_image_width())
            else:
                bad += 1
            last = frame_id
            stream.push_buffer(buffer)
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu
        return (n - bad) / wall, bad, 1000 * cpu / n
    finally:
        camera.stop_acquisition()
        del stream, camera


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rates", type=float, nargs="+", default=[1000.0, 200.0],
                        help="fake camera frame rates, Hz (its maximum is 1000)")
    parser.add_argument("--buffers", type=int, default=16)
    parser.add_argument("--write-results", action="store_true",
                        help="rewrite benchmarks/results/genicam_throughput.md with this run")
    args = parser.parse_args()
    if args.write_results:
        with captured() as out:
            run(args)
        write_results(__file__, "GenICam capture throughput: ours against a raw Aravis loop",
                      text_block(out.getvalue()), command=command_line())
        return
    run(args)


def run(args: argparse.Namespace) -> None:
    """Every rate and case, printed."""
    cases = [((0, 0, 512, 512), "Mono8"), ((0, 0, 1024, 1024), "Mono16")]
    print(f"# {datetime.date.today()} {platform.node()} {platform.processor() or platform.machine()}"
          f", Python {platform.python_version()}, {args.frames} frames, {args.repeats} repeats, "
          f"{args.buffers} buffers; good frames/s (bad frames), CPU ms/frame of the reader")
    with running_fake_camera("BENCH1") as fake:
        for rate_hz in args.rates:
            for roi, fmt in cases:
                ours, raw = [], []
                for _ in range(args.repeats):
                    raw.append(run_raw(fake.address, roi, fmt, rate_hz, args.frames, args.buffers))
                    ours.append(run_ours(fake.address, roi, fmt, rate_hz, args.frames,
                                         args.buffers))
                o = statistics.median(v[0] for v in ours)
                r = statistics.median(v[0] for v in raw)
                show = lambda runs: ", ".join(f"{v[0]:.0f} ({v[1]}) {v[2]:.2f}" for v in runs)
                print(f"{rate_hz:6g} Hz {roi[2]}x{roi[3]} {fmt:6s}: ours {o:6.1f}/s, raw {r:6.1f}/s,"
                      f" ratio {o / r:.3f}   [ours {show(ours)}; raw {show(raw)}]")


if __name__ == "__main__":
    main()
