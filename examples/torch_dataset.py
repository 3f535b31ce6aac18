"""A fringe data set as a PyTorch ``Dataset``: the numpy interface it wraps, and the wrapper.

``FringeSamples`` is all a deep-learning framework needs and depends on none: ``len`` and
``[i]`` give one training pair as numpy arrays, here the Feng/Zuo task (a fringe image in,
numerator and denominator out), for one split of the data set. The PyTorch wrapper below
only turns those arrays into tensors; torch is imported when this file is run, never when it
is imported.

    python examples/torch_dataset.py fringes.zarr        # iterate one epoch of batches
"""

from __future__ import annotations

import sys

import numpy as np

import sim.dataset


class FringeSamples:
    """Training pairs of one split: ``input`` (1, H, W) float32, the first fringe image of
    the finest frequency; ``target`` (2, H, W) float32, its numerator M and denominator D;
    ``mask`` (H, W) bool, valid pixels. One item per sample and camera."""

    def __init__(self, path: str, split: str = "train") -> None:
        self.data = sim.dataset.open(path)
        self.items = [(i, c) for i in self.data.indices(split)
                      for c in range(len(self.data.manifest["rig"]["cameras"]))]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, k: int) -> dict[str, np.ndarray]:
        index, cam = self.items[k]
        s = self.data.sample(index, ["images", "numerator", "denominator", "mask"])
        a = s.cameras[cam]
        fine = fine_frequency(s.scene)
        first = fine_images(s.scene)[0]
        return {"input": a["images"][first][None].astype(np.float32),
                "target": np.stack([a["numerator"][fine], a["denominator"][fine]]),
                "mask": a["mask"] == 1}


def fine_frequency(scene) -> int:
    """Index along the labels' frequency axis of the finest period."""
    periods = getattr(scene.patterns, "periods_px", None)
    return int(np.argmin(periods)) if periods else 0


def fine_images(scene) -> list[int]:
    """Image indices of the finest period's phase shifts, in shift order."""
    from sim.dataset.generate import phase_groups

    groups = phase_groups(scene)
    return min(groups, key=lambda g: g[0])[1]


if __name__ == "__main__":
    import torch  # noqa: PLC0415 - only when run
    from torch.utils.data import DataLoader, Dataset

    class TorchFringes(Dataset):
        def __init__(self, path: str, split: str = "train") -> None:
            self.samples = FringeSamples(path, split)

        def __len__(self) -> int:
            return len(self.samples)

        def __getitem__(self, k: int):
            return {key: torch.from_numpy(v) for key, v in self.samples[k].items()}

    loader = DataLoader(TorchFringes(sys.argv[1]), batch_size=4, shuffle=True)
    for batch in loader:
        print({k: tuple(v.shape) for k, v in batch.items()})
