"""``ltc validate``: a twin validated against a real scanner's scans (a real-scan folder).

Per position: scan the real images exactly as ``ltc scan`` does; locate the artefact; refine
its pose by analysis by synthesis with the primary twin (the first of ``build_twins``); render
and scan every twin at that pose (each other twin's own one-step pose is reported: where its
bias puts the artefact); estimate the camera response; compare (``compare_twin``). Written
into ``out``: ``validation.json`` (the inputs and their SHA-256), ``positions/NAME.json`` and
``NAME.npz`` per finished position (a rerun takes them up), ``results.json``, ``report.md``
and ``figures/``. One writer at a time (``writer.lock``); a finished folder is not
overwritten without ``force``.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from station.errors import UsageError
from station.validation.folder import (
    CadArtefact,
    Pose,
    RealPosition,
    RealScan,
    RealScanError,
    load_real_scan,
    write_durable,
)

if TYPE_CHECKING:
    from sim.fpp.decode import DecodeSettings
    from sim.optics.lens import LensModel
    from station.validation.twin import TwinScan

Log = Callable[[str], None]
DEFAULT_PIXEL_SAMPLES = 4  # subpixels per axis of a twin of area-integrating camera pixels
POSITIONS = "positions"


@dataclass(frozen=True)
class PositionResult:
    """Every number of one position (mm unless named): the real scan's report and fit, the
    refined pose and its steps (um), per twin its one-step pose offset from the refined pose
    (um), the true pose's offsets where the position file gives one, the camera response, the
    twins' comparisons and seconds."""

    name: str
    kind: str
    defocus: str | None
    real_points: int
    real_scan: dict
    real_size_mm: float | None
    real_fit_rms_mm: float
    refined_pose: dict
    refine_steps_um: list[float]
    refine_converged: bool
    twin_pose_offset_um: dict[str, float]
    true_offsets_um: dict[str, float] | None
    response: dict
    twins: dict[str, dict]
    seconds: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class ValidationResult:
    """The whole validation: the positions, the twins (the first is primary), a summary per
    twin (worst |mean|, RMSE and size against real) and the folder's report."""

    real_dir: str
    twins: list[str]
    positions: list[dict]
    summary: dict
    report: str
    seconds: dict[str, float]
    figures: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def input_digests(scan: RealScan, lens_paths: list[str | Path]) -> dict[str, str]:
    """SHA-256 of every input file: scan file, rig, patterns, lenses, position files, images."""
    folder = scan.folder
    files = [folder / "scan.toml", folder / scan.spec.rig, folder / scan.spec.patterns]
    for p in scan.positions:
        files += sorted(f for f in p.folder.rglob("*") if f.is_file())
    out = {str(f.relative_to(folder)): _sha256(f) for f in files}
    out.update({f"lens {i}: {Path(p).name}": _sha256(Path(p)) for i, p in enumerate(lens_paths)})
    return out


def _start(out: Path, record: dict, force: bool) -> bool:
    """Make ``out`` this validation's folder or resume it; returns whether it resumes."""
    path = out / "validation.json"
    if path.exists():
        before = json.loads(path.read_text(encoding="utf-8"))
        if (out / "results.json").exists() or before != record:
            if not force:
                why = ("holds a finished validation" if (out / "results.json").exists()
                       else "holds a validation of other inputs or settings")
                raise UsageError(f"--out {out} {why} ({path}); choose a new --out, or --force "
                                 "to validate again into it")
            shutil.rmtree(out / POSITIONS, ignore_errors=True)
            for f in ("results.json", "report.md"):
                (out / f).unlink(missing_ok=True)
        else:
            return True
    elif out.exists() and any(p.name != "writer.lock" for p in out.iterdir()):
        raise UsageError(f"--out {out} exists and is not a validation's folder; choose a new "
                         "--out")
    out.mkdir(parents=True, exist_ok=True)
    write_durable(path, json.dumps(record, indent=1).encode())
    return False


def _decode(pixel_variance_px2: float) -> DecodeSettings:
    from sim.fpp.decode import DecodeSettings

    return DecodeSettings(pixel_variance_px2=pixel_variance_px2)


def validate_position(scan: RealScan, pos: RealPosition, twins: dict[str, tuple], *,
                      dark: list[np.ndarray] | None = None, noise: bool = False,
                      pixel_samples: int | None = None, keep: dict | None = None
                      ) -> tuple[PositionResult, dict[str, np.ndarray]]:
    """Validate every twin at one position (see the module docstring); returns its result
    and its maps (per twin ``NAME.by_pixel_mm`` with ``.points_mm``; per twin and camera 0
    ``NAME.image_diff_dn`` and ``NAME.phase_diff_rad``; ``real.image``). ``keep``: filled
    with the real cloud (``real``), the real stacks (``real_images``), each twin's
    ``TwinScan`` (by name), its camera 0 images in counts (``images.NAME``) and the
    ``response``."""
    from sim.fpp.decode import scan_with_report
    from station.validation.compare import compare_twin, image_differences
    from station.validation.locate import fit_near, locate, pose_offset_um, refine_pose
    from station.validation.twin import estimate_response, render_scan, scene_at

    rig, patterns, art = scan.rig, scan.patterns, pos.spec.artefact
    psize = rig.projector.size
    t0 = time.perf_counter()
    stacks = pos.images(rig, patterns)
    try:
        real, real_report = scan_with_report(stacks, patterns, rig,
                                             _decode(scan.spec.pixel_variance_px2))
    except ValueError as exc:
        raise RealScanError(f"position {pos.name}: the real scan failed: {exc}") from exc
    t_real = time.perf_counter() - t0
    mesh, mesh_path = None, None
    if isinstance(art, CadArtefact):
        from sim.metrology.measure import load_mesh

        mesh_path = pos.folder / art.mesh
        mesh = load_mesh(mesh_path)
    real_fit = locate(real, art, pos.name, mesh)
    if not isinstance(art, CadArtefact):
        real_fit = fit_near(real, art, real_fit.pose, pos.name)
    t_locate = time.perf_counter() - t0 - t_real
    resp = scan.spec.response
    projector = {"input_bits": resp.projector_input_bits, "gamma": resp.projector_gamma}
    if pixel_samples is None:
        pixel_samples = 1 if scan.spec.pixel_variance_px2 == 0 else DEFAULT_PIXEL_SAMPLES
    # our renderer samples pixel centres: area-integrating twins are rendered on subpixels
    # and binned, and decoded as the real images are
    decode_twin = _decode(0.0 if pixel_samples == 1 else scan.spec.pixel_variance_px2)
    render_s: dict[str, float] = {}

    def scan_at(lenses: tuple[LensModel, ...], name: str) -> Callable[[Pose], TwinScan]:
        def run(pose: Pose) -> TwinScan:
            s = render_scan(rig, lenses, patterns, scene_at(art, pose, pos.name, mesh_path),
                            pos.name, None, decode_twin, projector=projector,
                            pixel_samples=pixel_samples)
            render_s[name] = render_s.get(name, 0.0) + s.render_s + s.scan_s
            return s
        return run

    names = list(twins)
    primary = names[0]
    ref = refine_pose(art, real_fit, real_fit.pose, scan_at(twins[primary], primary), pos.name,
                      mesh, real_cloud=real)
    pose = ref.pose
    scans = {primary: ref.last}
    offsets = {primary: 0.0}
    for n in names[1:]:
        scans[n] = scan_at(twins[n], n)(pose)
        own = fit_near(scans[n].cloud, art, pose, pos.name, mesh)
        from station.validation.locate import corrected_pose, pose_correction

        one_step = corrected_pose(art, pose, pose_correction(real_fit, own, art, real,
                                                             scans[n].cloud))
        offsets[n] = pose_offset_um(one_step, pose, art)
    t_twins = time.perf_counter() - t0 - t_real - t_locate
    bits = resp.bit_depth or (16 if stacks[0].dtype.itemsize >= 2 else 8) \
        if stacks[0].dtype.kind in "ui" else None
    response = estimate_response(stacks, scans[primary].radiance, patterns, psize, dark, bits)
    rng = np.random.default_rng(0) if noise else None
    world_mesh = None
    if mesh is not None:
        world_mesh = mesh.copy()
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = np.asarray(pose.R), np.asarray(pose.t)
        world_mesh.apply_transform(T)
    results, maps = {}, {"real.image": np.asarray(stacks[0][-1], np.float32)}
    for n in names:
        s = scans[n]
        imgs = []
        for i in range(len(rig.cameras)):
            counts = response.apply(s.radiance[i], i, rng)
            imgs.append(image_differences(stacks[i], counts, s.lit[i], patterns, psize, i))
        own_fit = None if mesh is not None else fit_near(s.cloud, art, pose, pos.name)
        c = compare_twin(n, s.cloud, real, real_fit, own_fit, art, pos.name, imgs, world_mesh)
        results[n] = c.to_json() | {"scan": s.report.to_json()}
        from sim.metrology.compare import compare_by_pixel

        bp = compare_by_pixel(s.cloud, real)
        maps[f"{n}.by_pixel_mm"] = bp.distances
        maps[f"{n}.points_mm"] = np.asarray(s.cloud.points)[bp.index]
        maps[f"{n}.image_diff_dn"] = imgs[0][1].astype(np.float32)
        maps[f"{n}.phase_diff_rad"] = imgs[0][2].astype(np.float32)
        maps[f"{n}.image"] = response.apply(s.radiance[0][-1:], 0, None)[0].astype(np.float32)
        if keep is not None:
            keep[n] = s
            keep[f"images.{n}"] = response.apply(s.radiance[0], 0, None)
    if keep is not None:
        keep.update(real=real, real_images=stacks, response=response)
    true = None
    if pos.spec.true_pose is not None:
        true = {"real_fit": pose_offset_um(real_fit.pose, pos.spec.true_pose, art),
                "refined": pose_offset_um(pose, pos.spec.true_pose, art)}
        for n in names[1:]:
            s_fit = fit_near(scans[n].cloud, art, pose, pos.name, mesh)
            from station.validation.locate import corrected_pose, pose_correction

            true[f"refined_{n}"] = pose_offset_um(
                corrected_pose(art, pose, pose_correction(real_fit, s_fit, art, real,
                                                          scans[n].cloud)),
                pos.spec.true_pose, art)
    total = time.perf_counter() - t0
    res = PositionResult(
        pos.name, art.kind, pos.spec.defocus, int(len(real.points)), real_report.to_json(),
        None if isinstance(art, CadArtefact) else real_fit.size_mm, real_fit.rms_mm,
        pose.model_dump(mode="json"), ref.steps_um, ref.converged, offsets, true,
        response.to_json(), results,
        {"real_scan": t_real, "locate": t_locate, "twins": t_twins,
         "render_and_scan": float(sum(render_s.values())), "total": total,
         **{f"render_and_scan_{k}": v for k, v in render_s.items()}})
    return res, maps


def _save(folder: Path, res: PositionResult, maps: dict[str, np.ndarray]) -> None:
    import io

    buf = io.BytesIO()
    arrays: dict[str, Any] = dict(maps)  # names and arrays for np.savez
    np.savez(buf, **arrays)
    write_durable(folder / f"{res.name}.npz", buf.getvalue())
    write_durable(folder / f"{res.name}.json", json.dumps(res.to_json(), indent=1).encode())


def _load(folder: Path, name: str) -> tuple[dict, dict] | None:
    import zipfile

    j, z = folder / f"{name}.json", folder / f"{name}.npz"
    if not j.exists():
        return None
    try:
        row = json.loads(j.read_text(encoding="utf-8"))
        with np.load(z, allow_pickle=False) as f:
            maps = {k: f[k] for k in f.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise RealScanError(f"position {name}: {z} unreadable ({exc}); delete {j} and it to "
                            "validate the position again") from exc
    return row, maps


def summarise(rows: list[dict], twins: list[str]) -> dict:
    """Per twin the worst |mean|, RMSE (by pixel, unaligned) and size against real (shared
    pixels) over the sphere and ball-bar positions, um; and per non-primary twin whether it
    is worse than the primary at every large-defocus position (|mean| and size)."""
    out: dict = {}
    sel = [r for r in rows if r["kind"] != "cad"]
    for t in twins:
        ms = [abs(r["twins"][t]["mean_mm"]) * 1e3 for r in rows]
        rs = [r["twins"][t]["rmse_mm"] * 1e3 for r in rows]
        sz = [abs(r["twins"][t]["size_shared_mm"] - r["twins"][t]["size_shared_real_mm"]) * 1e3
              for r in sel]
        out[t] = {"worst_abs_mean_um": max(ms, default=0.0), "worst_rmse_um": max(rs, default=0.0),
                  "worst_size_vs_real_um": max(sz, default=0.0)}
    primary = twins[0]
    large = [r for r in sel if r.get("defocus") == "large"]
    for t in twins[1:]:
        worse = [r["name"] for r in large
                 if abs(r["twins"][t]["mean_mm"]) > abs(r["twins"][primary]["mean_mm"])
                 and abs(r["twins"][t]["size_shared_mm"] - r["twins"][t]["size_shared_real_mm"])
                 > abs(r["twins"][primary]["size_shared_mm"]
                       - r["twins"][primary]["size_shared_real_mm"])]
        out[t]["worse_than_primary_at_large"] = bool(large) and len(worse) == len(large)
        out[t]["large_positions_worse"] = worse
    return out


def validate(real_dir: str | Path, lenses: list[str | Path], out: str | Path, *,
             positions: list[str] | None = None, gaussian_sigma_mm: float | None = None,
             gaussian_samples: int | None = None, smoothing_nodes: float = 0.0,
             noise: bool = False, pixel_samples: int | None = None, force: bool = False,
             log: Log = print) -> ValidationResult:
    """Validate the twins of ``lenses`` against the real-scan folder ``real_dir`` into
    ``out`` (see the module docstring); returns the result (also ``out/results.json``)."""
    from sim.storage.lock import StoreLock
    from station.validation.report import write_report
    from station.validation.twin import build_twins

    t0 = time.perf_counter()
    out = Path(out)
    if out.exists() and not (out / "validation.json").exists() and any(
            p.name != "writer.lock" for p in out.iterdir()):
        raise UsageError(f"--out {out} exists and is not a validation's folder; choose a new "
                         "--out")
    scan = load_real_scan(real_dir, positions)
    twins = build_twins(scan.rig, lenses, gaussian_sigma_mm, gaussian_samples, smoothing_nodes)
    dark = None
    if scan.spec.response.dark is not None:
        from sim.fpp.scan_input import _read_image

        dark = []
        for i, p in enumerate(scan.spec.response.dark):
            im = _read_image(scan.folder / p)
            if im is None or im.shape != (scan.rig.cameras[i].height, scan.rig.cameras[i].width):
                raise RealScanError(f"camera {i}: dark frame {scan.folder / p} unreadable or not "
                                    "the camera's size")
            dark.append(im)
    record = {"real_dir": str(Path(real_dir).resolve()), "lenses": [str(p) for p in lenses],
              "twins": list(twins), "gaussian_sigma_mm": gaussian_sigma_mm,
              "smoothing_nodes": smoothing_nodes, "noise": noise,
              "pixel_samples": pixel_samples,
              "positions": [p.name for p in scan.positions],
              "inputs_sha256": input_digests(scan, lenses)}
    out.mkdir(parents=True, exist_ok=True)
    with StoreLock(out, force=force):
        resumed = _start(out, record, force)
        if resumed:
            log(f"resuming the validation in {out}")
        rows, all_maps = [], {}
        for k, pos in enumerate(scan.positions):
            done = _load(out / POSITIONS, pos.name)
            if done is None:
                res, maps = validate_position(scan, pos, twins, dark=dark, noise=noise,
                                              pixel_samples=pixel_samples)
                _save(out / POSITIONS, res, maps)
                row = res.to_json()
            else:
                row, maps = done
            rows.append(row)
            all_maps[pos.name] = maps
            log(f"[{k + 1}/{len(scan.positions)}] {position_line(row)}")
        summary = summarise(rows, list(twins))
        result = ValidationResult(str(real_dir), list(twins), rows, summary,
                                  str(out / "report.md"), {"total": time.perf_counter() - t0})
        figures = write_report(result, all_maps, out)
        result = ValidationResult(result.real_dir, result.twins, rows, summary, result.report,
                                  {"total": time.perf_counter() - t0}, figures)
        write_durable(out / "results.json", json.dumps(result.to_json(), indent=1).encode())
        return result


def position_line(row: dict) -> str:
    """One line per position: each twin's mean / RMSE against real (um), the refinement."""
    parts = [f"{t} {m['mean_mm'] * 1e3:+.1f}/{m['rmse_mm'] * 1e3:.1f} um"
             for t, m in row["twins"].items()]
    steps = ", ".join(f"{s:.1f}" for s in row["refine_steps_um"])
    return (f"{row['name']} ({row['kind']}): " + ", ".join(parts)
            + f"; pose refined in {len(row['refine_steps_um'])} steps ({steps} um)")
