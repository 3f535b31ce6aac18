"""The experiment's verdicts and printed rows: ``acceptance`` (ltc against real, Gaussian
against ltc), one position's ``--json`` shape and progress line."""

from __future__ import annotations

from typing import Any

import numpy as np

from station.experiment.config import MODELS, VIRTUAL
from station.experiment.rows import ModelNumbers, PositionRow


def public_row(row: PositionRow) -> dict[str, Any]:
    """One position in the ``ltc demo --json`` shape (micrometres)."""
    models: dict[str, dict[str, float]] = {}
    for n, m in row.models.items():
        d: dict[str, float] = {}
        if m.size_mm is not None:
            d["size_um"] = round(m.size_mm * 1e3, 2)
        if m.cad is not None:
            d["cad_mean_um"] = round(m.cad.mean_mm * 1e3, 2)
            d["cad_rmse_um"] = round(m.cad.rmse_mm * 1e3, 2)
        for k in ("mean", "rmse", "mean_icp", "rmse_icp"):
            v = getattr(m, f"{k}_mm")
            if v is not None:
                d[f"{k}_um"] = round(v * 1e3, 2)
        models[n] = d
    return {"name": row.name, "kind": row.kind, "defocus": row.defocus,
            "defocus_mm": row.defocus_mm, "models": models}


def position_line(row: PositionRow) -> str:
    """One line per position: ltc and Gaussian against real, sizes."""
    m = row.models
    head = f"{row.name} ({row.kind}, {row.defocus}, {row.defocus_mm:+.0f} mm):"
    parts = [f"{n} {_mm(m[n].mean_mm) * 1e3:+.1f}/{_mm(m[n].rmse_mm) * 1e3:.1f} um"
             for n in VIRTUAL]
    if m["real"].size_mm is not None:
        parts.append("size " + " ".join(f"{n} {_mm(m[n].size_mm) * 1e3:+.0f}" for n in MODELS)
                     + " um, on shared pixels ltc - real " + f"{size_vs_real_um(m['ltc']):+.0f}"
                     + " um")
    return head + " " + ", ".join(parts)


def _mm(value: float | None) -> float:
    """A number that the row's kind guarantees (refuses None: a bug, not bad data)."""
    if value is None:
        raise TypeError("a number the position's kind always has is missing")
    return value


def size_vs_real_um(m: ModelNumbers) -> float:
    """A virtual scanner's size minus the real scanner's, compared on the pixels both clouds
    share (``shared_size_mm``), um."""
    v = m.size_vs_real_um
    if v is None:
        raise TypeError("no shared-pixel size: not a virtual scanner at a sphere or ball bar")
    return v


def acceptance(rows: list[PositionRow], mean_um: float = 5.0, rmse_um: float = 10.0,
               size_um: float = 20.0) -> dict[str, Any]:
    """The acceptance on the sphere and ball-bar positions: ltc against real (mean within
    +-mean_um, RMSE <= rmse_um, size within size_um of real's at every position, sizes
    compared on the pixels both clouds share: ``size_vs_real_um``); Gaussian worse than ltc
    at every large-defocus position in |mean| and size error; and how similar the two are
    near focus. ``ltc_worst.size_own_um``: the same on each scanner's own points."""
    sel = [r for r in rows if r.kind in ("sphere", "ballbar")]
    ltc_ok, gauss_worse = [], []
    worst = {"mean_um": 0.0, "rmse_um": 0.0, "size_um": 0.0, "size_own_um": 0.0}
    for r in sel:
        m = r.models
        lt, g, real = m["ltc"], m["gaussian"], m["real"]
        l_mean, l_rmse = _mm(lt.mean_mm), _mm(lt.rmse_mm)
        dl = abs(size_vs_real_um(lt))
        worst["mean_um"] = max(worst["mean_um"], abs(l_mean) * 1e3)
        worst["rmse_um"] = max(worst["rmse_um"], l_rmse * 1e3)
        worst["size_um"] = max(worst["size_um"], dl)
        worst["size_own_um"] = max(worst["size_own_um"],
                                   abs(_mm(lt.size_mm) - _mm(real.size_mm)) * 1e3)
        ok = abs(l_mean) * 1e3 <= mean_um and l_rmse * 1e3 <= rmse_um and dl <= size_um
        if not ok:
            ltc_ok.append(r.name)
        if r.defocus == "large":
            dg = abs(size_vs_real_um(g))
            if not (abs(_mm(g.mean_mm)) > abs(l_mean) and dg > dl):
                gauss_worse.append(r.name)
    slight = [r for r in sel if r.defocus == "slight"]
    near = {n: {"abs_mean_um": float(np.mean([abs(_mm(r.models[n].mean_mm))
                                              for r in slight]) * 1e3),
                "rmse_um": float(np.mean([_mm(r.models[n].rmse_mm) for r in slight]) * 1e3)}
            for n in ("ltc", "gaussian")} if slight else {}
    return {"ltc_within_limits": not ltc_ok, "ltc_failing": ltc_ok,
            "gaussian_worse_at_large": not gauss_worse, "gaussian_not_worse": gauss_worse,
            "ltc_worst": worst, "near_focus_average": near,
            "limits": {"mean_um": mean_um, "rmse_um": rmse_um, "size_um": size_um}}
