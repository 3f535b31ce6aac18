"""Soak: the real ZaberStage against the fake controller (pyserial URL transport, real time, fast
speeds) through thousands of moves with the fake's fault switches thrown at random (seeded).

Every call must end in success or a typed StageError within its deadline + 0.5 s; after each
error the driver's rest position is right or explicitly unknown, and the next move recovers.
``pytest -s`` prints the counts."""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from drivers.stage import StageError, ZaberStage
from drivers.zaber_protocol import ACCEL_UNIT, SPEED_UNIT
from fakes.zaber import Faults, register_url_handler, remove_url_device, url_device

SEED = 20240617
MOVES = 2000  # main moves (recovery and concurrent moves come on top)
WALL_CAP_S = 100.0  # stop early past this; at least MIN_MOVES must have run
MIN_MOVES = 600
P_FAULT = 0.08
UM = 0.1  # microstep, um
SPEED_MM_S, ACCEL_MM_S2 = 2000.0, 200_000.0
T = 0.1  # per-command reply timeout, s
STAGE = dict(microstep_um=UM, travel_mm=(0.0, 40.0), tolerance_um=0.1, timeout_s=T, settle_s=0.0,
             poll_s=0.002, margin_s=0.2, no_progress_s=0.1)
KINDS = ("drop_reply", "drop_move_reply", "delay_reply", "garble_reply", "bad_checksum", "silent",
         "stall", "stop_short", "idle_glitch", "info_lines", "alert_lines", "vanish", "vanish_on_move",
         "stop_from_thread", "concurrent_move")


@pytest.fixture
def soak_url() -> Iterator[str]:
    register_url_handler()
    url_device("soak", limit_max=450_000, position=50_000,
               maxspeed=round(SPEED_MM_S * 1000 / UM * SPEED_UNIT),
               accel=round(ACCEL_MM_S2 * 1000 / UM * ACCEL_UNIT))
    yield "fakezaber://soak"
    remove_url_device("soak")


@pytest.mark.slow
def test_soak_thousands_of_moves_with_random_faults(soak_url: str) -> None:
    rng = np.random.default_rng(SEED)
    device = url_device("soak")
    faults_injected: collections.Counter[str] = collections.Counter()
    outcomes: collections.Counter[str] = collections.Counter()
    longest_fail = longest_call = 0.0
    moves = 0
    with ZaberStage(soak_url, **STAGE) as stage:
        stage.home()
        bound = stage.move_deadline_s(40.0) + 2 * T + STAGE["settle_s"]  # documented worst case
        lock = threading.Lock()

        def timed(call: Callable[[], float], target: float, label: str) -> str:
            """Run one move; check its deadline and result; return its outcome name."""
            nonlocal longest_fail, longest_call, moves
            started = time.monotonic()
            try:
                result = call()
                outcome = "ok"
            except StageError as exc:  # anything else fails the test as it is
                outcome = type(exc).__name__
                assert str(exc).startswith(f"{soak_url}: "), exc  # names the port
            elapsed = time.monotonic() - started
            assert elapsed <= bound + 0.5, (label, outcome, elapsed)
            with lock:
                moves += 1
                outcomes[outcome] += 1
                longest_call = max(longest_call, elapsed)
                if outcome != "ok":
                    longest_fail = max(longest_fail, elapsed)
            if outcome == "ok":
                assert result == pytest.approx(target, abs=1e-5)
            return outcome

        def target_mm() -> float:
            return round(float(rng.uniform(0.0, 40.0)), 4)

        def in_thread(fn: Callable[[], object], delay: float) -> threading.Thread:
            thread = threading.Thread(target=lambda: (time.sleep(delay), fn()))
            thread.start()
            return thread

        def arm(kind: str, helpers: list[threading.Thread]) -> None:
            f = device.faults
            delay = float(rng.uniform(0.0, 0.015))  # reply faults land at a random command
            setters: dict[str, Callable[[], None]] = {
                "drop_reply": lambda: setattr(f, "drop_replies", 1),
                "drop_move_reply": lambda: setattr(f, "drop_on", "move"),
                "delay_reply": lambda: (setattr(f, "delay_s", 1.2 * T), setattr(f, "delay_replies", 1)),
                "garble_reply": lambda: setattr(f, "garble_replies", 1),
                "bad_checksum": lambda: setattr(f, "bad_checksum_replies", 1),
                "silent": lambda: setattr(f, "silent", True),
                "idle_glitch": lambda: setattr(f, "idle_glitch", True),
                "info_lines": lambda: setattr(f, "info_lines", 2),
                "alert_lines": lambda: setattr(f, "alert_lines", 2),
                "vanish": lambda: setattr(f, "vanish", True),
            }
            if kind in setters:
                helpers.append(in_thread(setters[kind], delay))
            elif kind == "stall":
                f.stall_at = float(rng.uniform(0.0, 1.0))
            elif kind == "stop_short":
                f.stop_short = int(rng.integers(2, 2000))
            elif kind == "vanish_on_move":
                f.vanish_on = "move"
            elif kind == "stop_from_thread":
                helpers.append(in_thread(stage.stop, delay))
            elif kind == "concurrent_move":
                other = target_mm()
                helpers.append(in_thread(lambda: timed(lambda: stage.move_to(other), other,
                                                       "concurrent"), delay))

        def check_rest_position(label: str) -> None:
            if stage.position_known:  # right: the axis rests where the driver thinks
                assert not device.busy, label
                assert abs(stage.last_position_mm * 1000 / UM - device.position) <= 1, label

        wall_start = time.monotonic()
        for i in range(MOVES):
            if time.monotonic() - wall_start > WALL_CAP_S:
                break
            kind = str(rng.choice(KINDS)) if rng.random() < P_FAULT else None
            helpers: list[threading.Thread] = []
            if kind:
                faults_injected[kind] += 1
                arm(kind, helpers)
            target = target_mm()
            outcome = timed(lambda target=target: stage.move_to(target), target, f"move {i} ({kind})")
            for thread in helpers:
                thread.join()
            device.faults = Faults()  # whatever was armed and unused is disarmed
            check_rest_position(f"after move {i} ({kind}): {outcome}")
            if outcome == "ok" and kind != "concurrent_move":
                assert stage.position_known and device.position == round(target * 1000 / UM)
            if outcome != "ok":  # the next operation recovers
                time.sleep(1.5 * T)  # let a delayed reply, if any, fall due (it is then discarded)
                again = target_mm()
                assert timed(lambda again=again: stage.move_to(again), again, f"recovery {i}") == "ok", kind
                assert stage.position_known and device.position == round(again * 1000 / UM)
        wall = time.monotonic() - wall_start

    report = (f"\nsoak: {i + 1} main moves, {moves} move calls in all, {wall:.1f} s wall (seed {SEED})"
              f"\n  faults injected: {dict(sorted(faults_injected.items()))}"
              f"\n  outcomes: {dict(sorted(outcomes.items()))}"
              f"\n  longest time to fail: {longest_fail:.3f} s; longest call: {longest_call:.3f} s; "
              f"bound {bound:.3f} s + 0.5 s")
    print(report)
    assert i + 1 >= MIN_MOVES, report
    assert sum(faults_injected.values()) >= 0.04 * (i + 1), report  # faults were really thrown
    assert outcomes["ok"] > 0.8 * moves, report
