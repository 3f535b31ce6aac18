"""The unit of work of a data-set run: make sample ``index`` and write it into the data set.

A pure function of its arguments (JSON texts and an index), so any engine (this process,
local processes, Dask workers) runs it and gets the same bytes.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

from sim.dataset.config import DatasetConfig
from sim.dataset.generate import render_sample
from sim.dataset.randomise import draw_scene
from sim.dataset.store import write_sample
from sim.optics.rig import Rig


@functools.lru_cache(maxsize=4)
def _parsed(config_json: str, rig_json: str) -> tuple[DatasetConfig, Rig]:
    return DatasetConfig.model_validate(json.loads(config_json)), Rig.model_validate_json(rig_json)


def make_sample(config_json: str, rig_json: str, root: str, index: int) -> tuple[int, str, str]:
    """Generate sample ``index`` and write it durably into the data set ``root``; returns
    ``(index, checksum, split)``."""
    cfg, rig = _parsed(config_json, rig_json)
    sample = render_sample(draw_scene(cfg, rig, index))
    digest = write_sample(Path(root), sample, cfg.storage)
    return index, digest, sample.scene.split


def ensure_sample(config_json: str, rig_json: str, root: str, index: int
                  ) -> tuple[int, str, str, bool]:
    """Sample ``index`` of the data set ``root``, made only when it is not already there whole:
    a sample group whose arrays still match its checksum is kept. Returns
    ``(index, checksum, split, kept)``."""
    from sim.dataset.store import SAMPLES, read_sample, sample_name

    path = Path(root) / SAMPLES / sample_name(index)
    if path.exists():
        try:
            s = read_sample(path)
            if s.verify() and s.index == index:
                return index, s.checksum, s.split, True
        except ValueError:
            pass
    return (*make_sample(config_json, rig_json, root, index), False)
