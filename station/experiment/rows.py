"""The experiment's numbers of one position (``PositionRow``) and of one scanner there
(``ModelNumbers``): the rows of ``results.json`` and ``positions/NAME.json`` (docs/formats.md,
"Experiment"). Lengths in mm, times in s."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any


@dataclass(frozen=True)
class DistanceStats:
    """Signed distances of a cloud's points (mm): count, mean, RMSE, std, min, max."""

    points: int
    mean_mm: float
    rmse_mm: float
    std_mm: float
    min_mm: float
    max_mm: float

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class ModelNumbers:
    """One scanner's numbers at one position; None: not measured there (left out of the
    JSON).

    points : the cloud's points; render_s : its rendering time, s.
    cad : the CAD part's points against the CAD mesh (CAD positions).
    size_mm : sphere diameter or ball-bar length minus nominal on the scanner's own points
    (``sizes.size_fit``), fit_rms_mm : the fits' largest RMS (spheres and ball bars).
    size_shared_mm, size_shared_real_mm : this scanner's and the real scanner's size minus
    nominal refitted on the pixels both clouds share, size_shared_points : their count
    (virtual scanners, spheres and ball bars: ``sizes.shared_size_mm``).
    mean_mm, rmse_mm : signed distances to the real cloud by pixel correspondence, unaligned;
    ``*_icp_mm`` after ICP; ``*_nn_mm`` nearest-surface distances of every point;
    pixels_compared : the pixels compared (virtual scanners).
    """

    points: int
    render_s: float
    cad: DistanceStats | None = None
    size_mm: float | None = None
    fit_rms_mm: float | None = None
    size_shared_mm: float | None = None
    size_shared_real_mm: float | None = None
    size_shared_points: int | None = None
    mean_mm: float | None = None
    rmse_mm: float | None = None
    mean_icp_mm: float | None = None
    rmse_icp_mm: float | None = None
    mean_nn_mm: float | None = None
    rmse_nn_mm: float | None = None
    pixels_compared: int | None = None

    @property
    def size_vs_real_um(self) -> float | None:
        """This scanner's size minus the real scanner's on the pixels both clouds share, um
        (None where not compared)."""
        if self.size_shared_mm is None or self.size_shared_real_mm is None:
            return None
        return (self.size_shared_mm - self.size_shared_real_mm) * 1e3

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is not None:
                out[f.name] = v.to_json() if isinstance(v, DistanceStats) else v
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ModelNumbers:
        names = {f.name for f in fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"unknown fields {sorted(unknown)}")
        values = dict(data)
        if values.get("cad") is not None:
            values["cad"] = DistanceStats(**values["cad"])
        return cls(**values)


@dataclass(frozen=True)
class PositionRow:
    """One position's numbers: name (S1.., B1.., C1), kind ('sphere', 'ballbar', 'cad'),
    defocus group ('slight', 'large'), defocus_mm (depth along camera 0's axis minus the
    focus distance), the object's world centre (3,) mm, and per scanner (real, ltc,
    gaussian, pinhole) its ``ModelNumbers``."""

    name: str
    kind: str
    defocus: str
    defocus_mm: float
    centre_mm: list[float]
    models: dict[str, ModelNumbers]

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "defocus": self.defocus,
                "defocus_mm": self.defocus_mm, "centre_mm": list(self.centre_mm),
                "models": {n: m.to_json() for n, m in self.models.items()}}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> PositionRow:
        return cls(name=str(data["name"]), kind=str(data["kind"]),
                   defocus=str(data["defocus"]), defocus_mm=float(data["defocus_mm"]),
                   centre_mm=[float(x) for x in data["centre_mm"]],
                   models={n: ModelNumbers.from_json(m) for n, m in data["models"].items()})
