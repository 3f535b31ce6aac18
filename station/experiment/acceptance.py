"""The experiment's verdicts and printed rows: ``acceptance`` (ltc against real, Gaussian
against ltc), one position's ``--json`` shape and progress line."""

from __future__ import annotations

import numpy as np

from station.experiment.config import MODELS, VIRTUAL

def public_row(row: dict) -> dict:
    """One position in the ``ltc demo --json`` shape (micrometres)."""
    models = {}
    for n, m in row["models"].items():
        d = {}
        if "size_mm" in m:
            d["size_um"] = round(m["size_mm"] * 1e3, 2)
        if "cad" in m:
            d["cad_mean_um"] = round(m["cad"]["mean_mm"] * 1e3, 2)
            d["cad_rmse_um"] = round(m["cad"]["rmse_mm"] * 1e3, 2)
        for k in ("mean", "rmse", "mean_icp", "rmse_icp"):
            if f"{k}_mm" in m:
                d[f"{k}_um"] = round(m[f"{k}_mm"] * 1e3, 2)
        models[n] = d
    return {"name": row["name"], "kind": row["kind"], "defocus": row["defocus"],
            "defocus_mm": row["defocus_mm"], "models": models}


def position_line(row: dict) -> str:
    """One line per position: ltc and Gaussian against real, sizes."""
    m = row["models"]
    head = f"{row['name']} ({row['kind']}, {row['defocus']}, {row['defocus_mm']:+.0f} mm):"
    parts = [f"{n} {m[n]['mean_mm'] * 1e3:+.1f}/{m[n]['rmse_mm'] * 1e3:.1f} um" for n in VIRTUAL]
    if "size_mm" in m["real"]:
        parts.append("size " + " ".join(f"{n} {m[n]['size_mm'] * 1e3:+.0f}" for n in MODELS)
                     + " um, on shared pixels ltc - real " + f"{size_vs_real_um(m['ltc']):+.0f}"
                     + " um")
    return head + " " + ", ".join(parts)


def size_vs_real_um(m: dict) -> float:
    """A virtual scanner's size minus the real scanner's, compared on the pixels both clouds
    share (``shared_size_mm``), um."""
    return (m["size_shared_mm"] - m["size_shared_real_mm"]) * 1e3


def acceptance(rows: list[dict], mean_um: float = 5.0, rmse_um: float = 10.0,
               size_um: float = 20.0) -> dict:
    """The issue's acceptance on the sphere and ball-bar positions: ltc against real (mean
    within +-mean_um, RMSE <= rmse_um, size within size_um of real's at every position,
    sizes compared on the pixels both clouds share: ``size_vs_real_um``); Gaussian worse
    than ltc at every large-defocus position in |mean| and size error; and how similar the
    two are near focus. ``ltc_worst.size_own_um``: the same on each scanner's own points."""
    sel = [r for r in rows if r["kind"] in ("sphere", "ballbar")]
    ltc_ok, gauss_worse = [], []
    worst = {"mean_um": 0.0, "rmse_um": 0.0, "size_um": 0.0, "size_own_um": 0.0}
    for r in sel:
        m = r["models"]
        l, g, real = m["ltc"], m["gaussian"], m["real"]
        dl = abs(size_vs_real_um(l))
        worst["mean_um"] = max(worst["mean_um"], abs(l["mean_mm"]) * 1e3)
        worst["rmse_um"] = max(worst["rmse_um"], l["rmse_mm"] * 1e3)
        worst["size_um"] = max(worst["size_um"], dl)
        worst["size_own_um"] = max(worst["size_own_um"],
                                   abs(l["size_mm"] - real["size_mm"]) * 1e3)
        ok = abs(l["mean_mm"]) * 1e3 <= mean_um and l["rmse_mm"] * 1e3 <= rmse_um \
            and dl <= size_um
        if not ok:
            ltc_ok.append(r["name"])
        if r["defocus"] == "large":
            dg = abs(size_vs_real_um(g))
            if not (abs(g["mean_mm"]) > abs(l["mean_mm"]) and dg > dl):
                gauss_worse.append(r["name"])
    slight = [r for r in sel if r["defocus"] == "slight"]
    near = {n: {"abs_mean_um": float(np.mean([abs(r["models"][n]["mean_mm"]) for r in slight]) * 1e3),
                "rmse_um": float(np.mean([r["models"][n]["rmse_mm"] for r in slight]) * 1e3)}
            for n in ("ltc", "gaussian")} if slight else {}
    return {"ltc_within_limits": not ltc_ok, "ltc_failing": ltc_ok,
            "gaussian_worse_at_large": not gauss_worse, "gaussian_not_worse": gauss_worse,
            "ltc_worst": worst, "near_focus_average": near,
            "limits": {"mean_um": mean_um, "rmse_um": rmse_um, "size_um": size_um}}
