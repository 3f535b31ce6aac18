"""Fuzzing the file openers of the station (config TOML, run store and LTC store attributes):
every mutated or garbage input opens or raises a one-line error naming the file
(tests/support/fuzz_inputs.py)."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given

from station.acquisition.config import example_text, load_config
from station.acquisition.patterns import StationPatternPlan
from station.acquisition.run_store import FrameMeta, RunStore
from station.ltc.store import create_ltc_store, mark_depth_complete, open_ltc_volume
from tests.support.fuzz_inputs import FUZZ, file_inputs, mutated_tree, opens_or_names_file

pytestmark = pytest.mark.timeout(120)

WORK = Path(tempfile.mkdtemp(prefix="ltc-fuzz-station-"))
CONFIG = example_text("fake").encode()


def _run_store() -> Path:
    path = WORK / "run.zarr"
    plan = StationPatternPlan.for_lcd((32, 16), 4, 4)
    store = RunStore.create(path, config={"a": 1}, plan=plan, depths_mm=[10.0, 20.0],
                            camera_size=(8, 6), bit_depth=10, lcd_size=(32, 16),
                            lcd_pitch_mm=0.1, tile_px=4)
    meta = FrameMeta(stage_target_mm=10.0, stage_measured_mm=10.0, swap_index=1,
                     swap_time_s=0.0, camera_timestamp_s=0.0, frame_id=0, exposure_ms=1.0)
    store.write_frame(0, 0, np.full((6, 8), 7, np.uint16), meta)
    return path


def _ltc_store() -> Path:
    path = WORK / "ltc.zarr"
    g = create_ltc_store(path, depths_mm=[10.0, 20.0], camera_size=(8, 6), period=4,
                         pitch_mm=0.1, lcd_size=(32, 16), tile_px=4,
                         attrs={"camera_matrix": np.eye(3).tolist()})
    for depth in range(2):
        mark_depth_complete(g, depth, all_tiles=True)
    return path


RUN, LTC = _run_store(), _ltc_store()
RUN_META, LTC_META = ((p / "zarr.json").read_bytes() for p in (RUN, LTC))


def _open_run(path: Path) -> None:
    store = RunStore.open(path)
    store.done(), store.config, store.display_lut
    if store.done()[0, 0]:
        store.read_frame(0, 0)


def _with_meta(store: Path, data: bytes, opener) -> None:
    (store / "zarr.json").write_bytes(data)
    opens_or_names_file(opener, store)


def test_the_unmutated_inputs_open():
    assert load_config(_write("c.toml", CONFIG)).depths_mm
    _open_run(RUN)
    assert open_ltc_volume(LTC).camera_size == (8, 6)


def _write(name: str, data: bytes) -> Path:
    path = WORK / name
    path.write_bytes(data)
    return path


@FUZZ
@given(file_inputs(CONFIG))
def test_station_config_toml(data):
    opens_or_names_file(load_config, _write("fuzz.toml", data))


def _attrs_tree(meta: bytes):
    return mutated_tree(json.loads(meta)["attributes"])


def _meta_with(meta: bytes, attrs) -> bytes:
    doc = json.loads(meta)
    doc["attributes"] = attrs
    return json.dumps(doc).encode()


@FUZZ
@given(_attrs_tree(RUN_META))
def test_run_store_attributes(attrs):
    _with_meta(RUN, _meta_with(RUN_META, attrs), _open_run)


@FUZZ
@given(file_inputs(RUN_META))
def test_run_store_metadata_bytes(data):
    _with_meta(RUN, data, _open_run)


@FUZZ
@given(_attrs_tree(LTC_META))
def test_ltc_store_attributes(attrs):
    _with_meta(LTC, _meta_with(LTC_META, attrs), open_ltc_volume)


@FUZZ
@given(file_inputs(LTC_META))
def test_ltc_store_metadata_bytes(data):
    _with_meta(LTC, data, open_ltc_volume)
