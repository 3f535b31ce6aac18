"""The experiment's numbers of one position (``PositionRow``), of one scanner there
(``ModelNumbers``) and of the validation path there (``PoseValidation``): the rows of
``results.json`` and ``positions/NAME.json`` (docs/formats.md, "Experiment"). Lengths in mm,
times in s, unless named."""

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
class PoseValidation:
    """The validation path's figures at one position (``station.experiment.validated``, the
    numbers of ``ltc validate``'s ``PositionResult``; no timings, so that a resumed position's
    row is the one first written).

    true_offsets_um : offsets from the true pose, um: ``real_fit`` (the real cloud's own fit),
    ``refined`` (the pose refined with the first twin, the measured-LTC scanner) and
    ``refined_TWIN`` (one refinement step with each other twin from there); None without a
    true pose.
    refine_steps_um : the analysis-by-synthesis corrections, um; refine_converged : whether
    the last fell below 1 um.
    twin_pose_offset_um : per twin its one-step pose's offset from the refined pose, um.
    response : the camera response (``station.validation.twin.Response.to_json``: per camera
    ``gain``, ``offset``, ``read_noise_dn``, ``shot_dn``; ``bits``, ``source``).
    images : per twin, per camera the fringe image and phase differences against real
    (``station.validation.compare.ImageStats.to_json``).
    """

    true_offsets_um: dict[str, float] | None
    refine_steps_um: list[float]
    refine_converged: bool
    twin_pose_offset_um: dict[str, float]
    response: dict[str, Any]
    images: dict[str, list[dict[str, Any]]]

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> PoseValidation:
        names = [f.name for f in fields(cls)]
        if set(data) != set(names):
            raise ValueError(f"validation: fields {sorted(data)}, expected {sorted(names)}")
        offsets = data["true_offsets_um"]
        return cls(
            true_offsets_um=None if offsets is None
            else {str(k): float(v) for k, v in offsets.items()},
            refine_steps_um=[float(x) for x in data["refine_steps_um"]],
            refine_converged=bool(data["refine_converged"]),
            twin_pose_offset_um={str(k): float(v)
                                 for k, v in data["twin_pose_offset_um"].items()},
            response=dict(data["response"]),
            images={str(k): [dict(c) for c in v] for k, v in data["images"].items()})


@dataclass(frozen=True)
class PositionRow:
    """One position's numbers: name (S1.., B1.., C1), kind ('sphere', 'ballbar', 'cad'),
    defocus group ('slight', 'large'), defocus_mm (depth along camera 0's axis minus the
    focus distance), the object's world centre (3,) mm, and per scanner (real, ltc,
    gaussian, pinhole) its ``ModelNumbers``; ``validation``: the validation path's figures
    (``PoseValidation``; None: not validated, left out of the JSON)."""

    name: str
    kind: str
    defocus: str
    defocus_mm: float
    centre_mm: list[float]
    models: dict[str, ModelNumbers]
    validation: PoseValidation | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name, "kind": self.kind, "defocus": self.defocus,
            "defocus_mm": self.defocus_mm, "centre_mm": list(self.centre_mm),
            "models": {n: m.to_json() for n, m in self.models.items()}}
        if self.validation is not None:
            out["validation"] = self.validation.to_json()
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> PositionRow:
        return cls(name=str(data["name"]), kind=str(data["kind"]),
                   defocus=str(data["defocus"]), defocus_mm=float(data["defocus_mm"]),
                   centre_mm=[float(x) for x in data["centre_mm"]],
                   models={n: ModelNumbers.from_json(m) for n, m in data["models"].items()},
                   validation=None if data.get("validation") is None
                   else PoseValidation.from_json(data["validation"]))
